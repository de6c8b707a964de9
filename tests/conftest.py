"""Test settings: headless rendering, one thread per process (2-core machines), quiet warnings."""

import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")

import signal  # noqa: E402
import sys  # noqa: E402

import pytest  # noqa: E402
import torch  # noqa: E402

torch.set_num_threads(1)
# ... and every run a test starts, in this process or another: two pytest workers share 2 cores, and a run's own
# choice (num_threads=-1) of two threads, timed on a moment's idle core, slows to a crawl once the other worker is
# busy (most likely why a td3 learning check took 371 s in CI instead of ~40). rlpipe keeps OMP_NUM_THREADS as its cap.
os.environ["OMP_NUM_THREADS"] = "1"

# The tests press Ctrl-C as a terminal user does. Run from a background job or nohup, the suite
# would start with SIGINT ignored, and so would every process it starts (as rlpipe then wants):
# give it Python's usual handler, which its child processes get back as the default.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)
# Likewise the terminal closing (test_supervision sends SIGHUP): under nohup the suite starts with SIGHUP
# ignored, every run it starts inherits that, and rlpipe keeps a signal ignored at its start ignored (a
# nohup user asked for it), so the run would never stop. A CI run under nohup failed so on 2026-11-27.
if hasattr(signal, "SIGHUP") and signal.getsignal(signal.SIGHUP) is signal.SIG_IGN:
    signal.signal(signal.SIGHUP, signal.SIG_DFL)


@pytest.fixture
def tmpfs(tmp_path):
    """``tmpfs(size)``: a file system of its own of ``size`` ('4m', '32m'), to fill; the test is skipped where
    mounting is not allowed. Unmounted at the test's end."""
    import subprocess

    mounts = []

    def make(size: str):
        mount = tmp_path / f"disk{len(mounts)}"
        mount.mkdir()
        made = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(mount)], capture_output=True)
        if made.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here: {made.stderr.decode().strip()}")
        mounts.append(mount)
        return mount

    yield make
    for mount in mounts:
        subprocess.run(["umount", "-l", str(mount)], check=False)


@pytest.fixture
def run_dir(tmp_path):
    """A path for a run directory that does not exist yet."""
    return tmp_path / "run"


@pytest.fixture
def ctrl_c_on_call():
    """``ctrl_c_on_call(where, n)``: a hook (any signature) that presses Ctrl-C, a real SIGINT to
    this process as the terminal sends it, on its ``n``-th call from inside a function named
    ``where``; calls from elsewhere are not counted."""

    def make(where: str, n: int):
        calls = 0

        def hook(*_):
            nonlocal calls
            frame = sys._getframe(1)
            while frame is not None and frame.f_code.co_name != where:
                frame = frame.f_back
            if frame is not None:
                calls += 1
                if calls == n:
                    os.kill(os.getpid(), signal.SIGINT)

        return hook

    return make


# --- the order of the files, and which worker runs what ----------------------------------------------------------

# Ray's tests start a Ray instance each (a dozen processes, a cluster of two nodes): one at a time on the machine
# (test_backends.py runs its contract on a local Ray too).
RAY_FILES = ("tests/test_backends.py", "tests/test_ray.py", "tests/test_ray_faults.py", "tests/test_tune_ray.py")


def _unit(item: pytest.Item) -> str:
    """The part of the suite one pytest-xdist worker runs whole: the item's file, the Ray files as one."""
    path = item.nodeid.split("::", 1)[0]
    return "ray" if path in RAY_FILES else path


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config, items):
    """The units longest first: those with the most long tests (marked slow), then by their number of tests. A
    worker that takes a long file last keeps the run going while the other has nothing left to do; begun first, the
    long files share the two workers and the short ones fill in at the end."""
    units: dict[str, list[pytest.Item]] = {}
    for item in items:
        units.setdefault(_unit(item), []).append(item)

    def longest_first(unit: list[pytest.Item]) -> tuple[int, int]:
        return -sum(item.get_closest_marker("slow") is not None for item in unit), -len(unit)

    order = sorted(units.values(), key=longest_first)
    items[:] = [item for unit in order for item in unit]


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    """pyproject's addopts run the tests on pytest-xdist workers, a test file at a time (``--dist loadfile``):
    a file's tests share its module fixtures (a trained run that many checks read), made once on one worker.
    The Ray files go to one worker as one unit. The units are handed out in the order above, not xdist's own (by
    number of tests). (``--dist loadgroup`` with ``xdist_group`` marks would be finer, but with pytest 9.2 xdist
    3.8 silently ignores the marks: pytest-dev/pytest-xdist#1386.)"""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    config.option.loadscopereorder = False  # xdist's ``--no-loadscope-reorder``: the units in collection order

    class RayFilesTogether(LoadFileScheduling):
        def _split_scope(self, nodeid: str) -> str:
            scope = super()._split_scope(nodeid)
            return "ray" if scope in RAY_FILES else scope

    return RayFilesTogether(config, log)


# --- a Ray cluster for the tests that join one --------------------------------------------------------------------

_cluster = None  # the cluster while it is up


@pytest.fixture
def ray_cluster():
    """A Ray cluster of two nodes on this machine, a head and one more, a CPU each (test_ray, test_ray_faults,
    test_tune_ray). Tests of one file that join one in a row share it: it is shut down after a test whose next test
    is in another file or does not join one. Each of them checks that its runs left it
    up and without their actors."""
    global _cluster
    if _cluster is None:
        pytest.importorskip("ray", reason="Ray is not installed: `pip install -e '.[ray]'` (scripts/setup.sh does)")
        from ray.cluster_utils import Cluster

        cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
        try:
            cluster.add_node(num_cpus=1)
            cluster.wait_for_nodes()
        except BaseException:
            cluster.shutdown()
            raise
        _cluster = cluster
    return _cluster


@pytest.hookimpl(trylast=True)
def pytest_runtest_teardown(item, nextitem):
    """After a test's own teardown: the cluster shut down unless the next test, in the same file, joins it too."""
    global _cluster
    if _cluster is not None and (nextitem is None or nextitem.path != item.path
                                 or "ray_cluster" not in nextitem.fixturenames):
        cluster, _cluster = _cluster, None
        cluster.shutdown()


@pytest.fixture
def play():
    """``play(policy_pt2, env_id, episodes, seed)``: each episode's return of an exported ``policy.pt2`` acting
    greedily in gymnasium's own env (episode ``i`` reset with ``seed + i``); every action is checked to lie in the
    env's action space."""
    def run(policy_path, env_id: str, episodes: int, seed: int) -> list[float]:
        import gymnasium

        policy = torch.export.load(str(policy_path)).module()
        env, returns = gymnasium.make(env_id), []
        for episode in range(episodes):
            obs, _ = env.reset(seed=seed + episode)
            total, done = 0.0, False
            while not done:
                with torch.no_grad():
                    action = policy(torch.as_tensor(obs, dtype=torch.float32)[None])[0].numpy()
                assert env.action_space.contains(action), action
                obs, reward, terminated, truncated, _ = env.step(action)
                total, done = total + float(reward), terminated or truncated
            returns.append(total)
        env.close()
        return returns

    return run
