"""The `rlpipe` command line, as a user runs it: real processes on one tiny trained run.

Processes cost ~4 s of CPU each (torch + TorchRL imports), so the commands that read the shared run
run two at a time in one module fixture; the full matrix of bad inputs also goes through the CLI's
``main()`` in this process, and a representative part of it through real processes.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import os
import shutil
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import gymnasium
import imageio.v2 as imageio
import numpy as np
import pytest
import torch

ENTRY_POINT = str(Path(sys.executable).parent / "rlpipe")
MODULE = [sys.executable, "-m", "rlpipe.scripts.cli"]
TINY = ["num_iterations=300", "initial_collect_steps=100", "eval_interval=100", "num_eval_episodes=2",
        "log_interval=100", "checkpoint_interval=100", "policy_save_interval=100"]


def run_cli(args, cwd: Path, timeout: float = 300, entry_point: bool = False) -> subprocess.CompletedProcess:
    command = ([ENTRY_POINT] if entry_point else MODULE) + [str(a) for a in args]
    return subprocess.run(command, cwd=cwd, capture_output=True, text=True, timeout=timeout)


def snapshot(folder: Path) -> dict[str, tuple]:
    state = {}
    for path in sorted(Path(folder).rglob("*")):
        rel = str(path.relative_to(folder))
        if path.is_dir():
            state[rel] = ("dir", path.stat().st_mtime_ns)
        else:
            st = path.stat()
            state[rel] = (st.st_size, st.st_mtime_ns, hashlib.sha256(path.read_bytes()).hexdigest())
    return state


def assert_one_line_error(code: int, stderr: str, *words: str) -> None:
    lines = stderr.strip().splitlines()
    assert code == 2, f"exit {code}; stderr:\n{stderr}"
    assert len(lines) == 1, f"expected one line on stderr, got:\n{stderr}"
    assert lines[0].startswith("rlpipe: error:"), lines[0]
    for word in words:
        assert word in lines[0], f"{word!r} not in {lines[0]!r}"


def frames_of(path: Path) -> list[np.ndarray]:
    with imageio.get_reader(path) as reader:
        return [frame for frame in reader]


# --- one trained run, and the commands that read it -------------------------------------------------


@pytest.fixture(scope="module")
def cli_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("cli")
    proc = run_cli(["train", "dqn", *TINY, "--out", "run", "--no-progress"], cwd=root, entry_point=True)
    return root, root / "run", proc


@pytest.fixture(scope="module")
def commands(cli_run):
    root, run, train = cli_run
    assert train.returncode == 0, train.stderr
    other = root / "other-run"
    shutil.copytree(run, other)
    jobs = {
        "eval": ["eval", run, "--episodes", "3", "--json", "--ecdf"],
        "eval-text": ["eval", run, "--episodes", "2"],
        "video": ["video", run, "--episodes", "1"],
        "video-random": ["video", run, "--episodes", "1", "--random", "--out", root / "videos" / "random.mp4"],
        "plot": ["plot", run, other, "--out", root / "both.png"],
        "presets": ["presets"],
        "keys": ["train", "dqn", "--keys"],
        "keys-overridden": ["train", "dqn", "batch_size=7", "collector.workers=3", "--keys"],
    }
    with ThreadPoolExecutor(max_workers=2) as pool:
        results = dict(zip(jobs, pool.map(lambda args: run_cli(args, cwd=root), jobs.values())))
    return root, run, results


def test_train_exits_0_and_prints_average_return(cli_run):
    root, run, proc = cli_run
    assert proc.returncode == 0, proc.stderr
    assert "AverageReturn" in proc.stdout and "AverageEpisodeLength" in proc.stdout
    assert "Traceback" not in proc.stderr
    summary = json.loads((run / "summary.json").read_text())
    assert f"AverageReturn = {summary['final_average_return']:.2f}" in proc.stdout
    assert (summary["iterations"], summary["frames"], summary["updates"]) == (300, 400, 300)
    for name in ("config.json", "metrics.csv", "policy/policy.pt2", "returns.png", "checkpoints/latest"):
        assert (run / name).exists(), name
    assert not (root / "runs").exists(), "--out was given: nothing goes to the default runs/ folder"


def test_eval_prints_json_and_writes_the_ecdf(commands):
    root, run, results = commands
    proc = results["eval"]
    assert proc.returncode == 0, proc.stderr
    data = json.loads(proc.stdout.strip().splitlines()[-1])
    assert len(data["returns"]) == 3
    assert data["AverageReturn"] == pytest.approx(sum(data["returns"]) / 3)
    # CartPole pays 1 per step, for at most 200 steps in v0: whole returns, each its episode's length
    assert data["AverageEpisodeLength"] == pytest.approx(data["AverageReturn"])
    assert all(r == int(r) and 1 <= r <= 200 for r in data["returns"]), data["returns"]
    assert (run / "ecdf.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_eval_prints_text(commands):
    proc = commands[2]["eval-text"]
    assert proc.returncode == 0, proc.stderr
    assert "AverageReturn = " in proc.stdout and "AverageEpisodeLength = " in proc.stdout
    # the same default seed: the episodes of the 3-episode evaluation above, its first two
    returns = json.loads(commands[2]["eval"].stdout.strip().splitlines()[-1])["returns"]
    assert f"AverageReturn = {sum(returns[:2]) / 2:.2f}" in proc.stdout, (proc.stdout, returns)


def _episode_length(run: Path, seed: int) -> int:
    """Length of the episode that `rlpipe video` records: the exported policy on gymnasium's CartPole."""
    policy = torch.export.load(str(run / "policy" / "policy.pt2")).module()
    env = gymnasium.make("CartPole-v0")
    obs, _ = env.reset(seed=seed)
    for t in range(1, 1000):
        action = int(policy(torch.as_tensor(obs, dtype=torch.float32)[None])[0])
        obs, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            return t
    raise AssertionError("episode did not end")


def test_video_of_the_trained_policy(commands):
    root, run, results = commands
    proc = results["video"]
    assert proc.returncode == 0, proc.stderr
    path = run / "trained-agent.mp4"
    assert str(path.name) in proc.stdout
    frames = frames_of(path)
    assert len(frames) == 1 + _episode_length(run, seed=0), "one frame at reset and one per step"
    assert len(frames) > 8
    assert frames[0].shape == (400, 600, 3)
    assert frames[0].std() > 0, "blank frames"


def test_video_of_a_random_policy(commands):
    root, run, results = commands
    proc = results["video-random"]
    assert proc.returncode == 0, proc.stderr
    frames = frames_of(root / "videos" / "random.mp4")
    assert len(frames) > 10
    assert frames[0].shape == (400, 600, 3)
    assert not list((root / "videos").glob(".video.*")), "temporary file left behind"


def test_plot_two_runs(commands):
    root, _, results = commands
    proc = results["plot"]
    assert proc.returncode == 0, proc.stderr
    png = root / "both.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 5000


def test_presets_lists_the_dqn_presets(commands):
    proc = commands[2]["presets"]
    assert proc.returncode == 0, proc.stderr
    lines = {line.split()[0]: line for line in proc.stdout.splitlines() if line.strip()}
    assert "CartPole-v0" in lines["dqn"] and "20000" in lines["dqn"]
    assert "CartPole-v1" in lines["dqn-cartpole-v1"]


def test_keys_lists_every_key_with_value_and_help(commands):
    from rlpipe.pipelines.config import flat_keys
    from rlpipe.pipelines.dqn import DQNConfig

    proc = commands[2]["keys"]
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout
    for key in flat_keys(DQNConfig):
        assert f"\n{key}=" in "\n" + out, key
    assert "batch_size=64" in out and "fc_layer_params=[100]" in out and 'env="CartPole-v0"' in out
    assert "collector.workers=1" in out
    assert "transitions per update" in out  # batch_size's help


def test_keys_shows_the_values_the_overrides_give_and_where_each_came_from(commands):
    proc = commands[2]["keys-overridden"]
    assert proc.returncode == 0, proc.stderr
    assert "\nbatch_size=7\n    [command line] " in proc.stdout
    assert "\ncollector.workers=3\n    [command line] " in proc.stdout
    assert "\ngamma=1.0\n    [default] " in proc.stdout  # where each value came from


# --- bad input: one line, exit 2, nothing written --------------------------------------------------


def _damage_policy(run: Path) -> None:
    (run / "policy" / "policy.onnx").write_bytes(b"\x08\x07 not an ONNX model" * 10)


BAD_INPUTS = {
    # name: (argv with RUN for a copy of the trained run, words the error names, damage to the copy)
    "unknown-env": (["train", "dqn", "env=CartPol-v0", "--out", "new"], ["CartPol-v0", "CartPole-v0"], None),
    "continuous-env": (["train", "dqn", "env=Pendulum-v1", "--out", "new"], ["Pendulum-v1", "discrete"], None),
    "unknown-key": (["train", "dqn", "batchsize=3", "--out", "new"], ["batchsize", "batch_size"], None),
    "ill-typed": (["train", "dqn", "batch_size=abc", "--out", "new"], ["batch_size", "integer"], None),
    "zero-batch": (["train", "dqn", "batch_size=0", "--out", "new"], ["batch_size", "positive"], None),
    "negative-iterations": (["train", "dqn", "num_iterations=-1", "--out", "new"], ["num_iterations", "positive"], None),
    "unknown-preset": (["train", "dqm", "--out", "new"], ["dqm", "dqn"], None),
    "out-holds-a-run": (["train", "dqn", *TINY, "--out", "RUN"], ["already holds a run", "--resume"], None),
    "resume-not-a-run": (["train", "dqn", "--resume", "."], ["not a run directory"], None),
    "resume-other-algo": (["train", "sac", "--resume", "RUN"], ["dqn", "sac"], None),
    "resume-and-other-out": (["train", "dqn", "--resume", "RUN", "--out", "elsewhere"], ["--out", "--resume"], None),
    "out-is-a-file": (["train", "dqn", "--out", "RUN/config.json"], ["not a directory"], None),
    "out-not-empty": (["train", "dqn", "--out", "RUN/policy"], ["not empty"], None),
    "eval-not-a-run": (["eval", ".", "--episodes", "3"], ["not a run directory"], None),
    "video-not-a-run": (["video", ".", "--episodes", "1"], ["not a run directory"], None),
    "plot-not-a-run": (["plot", "RUN", ".", "--out", "x.png"], ["not a run directory"], None),
    "eval-zero-episodes": (["eval", "RUN", "--episodes", "0"], ["--episodes"], None),
    "eval-corrupt-policy": (["eval", "RUN", "--episodes", "2"], ["policy.onnx", "corrupt"], _damage_policy),
    "video-corrupt-policy": (["video", "RUN", "--episodes", "1"], ["policy.onnx", "corrupt"], _damage_policy),
    "bad-device": (["train", "dqn", "device=foo", "--out", "new"], ["device"], None),
    "override-after-options": (["train", "dqn", "--out", "new", "batch_size=0"], ["batch_size"], None),
    "argparse-error": (["eval", "RUN", "--episodes", "abc"], ["--episodes"], None),
    # issue 11: seeds, sizes that cannot be allocated, machine limits, devices, envs, places to write
    "negative-seed": (["train", "dqn", "seed=-1", "--out", "new"], ["seed=-1", "from 0 to"], None),
    "huge-seed": (["train", "dqn", "seed=123456789012345678901234567890", "--out", "new"], ["seed=", "from 0 to"], None),
    "seed-over-2**31": (["train", "dqn", "seed=4294967296", "--out", "new"], ["seed=", "from 0 to"], None),
    "nan-learning-rate": (["train", "dqn", "learning_rate=nan", "--out", "new"], ["learning_rate=nan", "finite"], None),
    "inf-learning-rate": (["train", "dqn", "learning_rate=inf", "--out", "new"], ["learning_rate=inf", "finite"], None),
    "nan-epsilon": (["train", "dqn", "epsilon_greedy=nan", "--out", "new"], ["epsilon_greedy=nan", "finite"], None),
    "nan-policy-noise": (["train", "td3", "policy_noise=nan", "--out", "new"], ["policy_noise=nan", "finite"], None),
    "inf-tau": (["train", "td3", "target_update_tau=-inf", "--out", "new"], ["target_update_tau", "finite"], None),
    "nan-initial-alpha": (["train", "sac", "env=Pendulum-v1", "initial_alpha=nan", "--out", "new"],
                          ["initial_alpha=nan", "finite"], None),
    "inf-reward-scale": (["train", "sac", "env=Pendulum-v1", "reward_scale_factor=inf", "--out", "new"],
                         ["reward_scale_factor=inf", "finite"], None),
    "huge-replay": (["train", "dqn", "replay_buffer_capacity=1000000000000", "--out", "new"],
                    ["replay_buffer_capacity=1000000000000", "available", "at most"], None),
    "huge-replay-sac": (["train", "sac", "env=Pendulum-v1", "replay_buffer_capacity=100000000000", "--out", "new"],
                        ["replay_buffer_capacity", "available"], None),
    "huge-layers": (["train", "dqn", "fc_layer_params=[1000000,1000000]", "--out", "new"],
                    ["fc_layer_params", "available"], None),
    "huge-block": (["train", "dqn", "collector.frames_per_batch=10000000000", "--out", "new"],
                   ["collector.frames_per_batch", "available"], None),
    "absurd-threads": (["train", "dqn", "num_threads=100000", "--out", "new"], ["num_threads=100000", "CPUs"], None),
    "absurd-workers": (["train", "dqn", "collector.workers=100000", "--out", "new"],
                       ["collector.workers=100000", "at most"], None),
    "cuda-index-absent": (["train", "dqn", "device=cuda:99", "--out", "new"], ["device='cuda:99'", "cpu"], None),
    "meta-device": (["train", "dqn", "device=meta", "--out", "new"], ["device='meta'", "cpu"], None),
    "bad-choice": (["train", "dqn", "initial_collect_policy=greedy", "--out", "new"], ["initial_collect_policy"], None),
    "atari-extra": (["train", "dqn", "env=ALE/Pong-v5", "--out", "new"], ["ALE/Pong-v5", "rlpipe[atari]"], None),
    "multidiscrete-actions": (["train", "dqn", "env=rlpipe-test/MultiDiscreteActions-v0", "--out", "new"],
                              ["MultiDiscrete", "Discrete"], None),
    "text-observations": (["train", "dqn", "env=rlpipe-test/TextObservations-v0", "--out", "new"],
                          ["Text", "Box"], None),
    "frozenlake-to-sac": (["train", "sac", "env=FrozenLake-v1", "--out", "new"], ["FrozenLake-v1", "continuous"], None),
    # issue 22: CrossQ's own keys and action space
    "cartpole-to-crossq": (["train", "crossq", "env=CartPole-v1", "--out", "new"], ["CartPole-v1", "continuous"], None),
    "zero-policy-delay": (["train", "crossq-pendulum", "policy_delay=0", "--out", "new"], ["policy_delay=0", "positive"],
                          None),
    "adam-beta1-of-1": (["train", "crossq-pendulum", "adam_beta1=1", "--out", "new"], ["adam_beta1=1", "[0, 1)"], None),
    "out-under-a-file": (["train", "dqn", "--out", "RUN/config.json/new"], ["config.json", "is a file"], None),
    "out-in-sys": (["train", "dqn", "--out", "/sys/rlpipe-test/run"], ["/sys", "cannot write"], None),
    "out-in-proc": (["train", "dqn", "--out", "/proc/rlpipe-test"], ["/proc", "cannot write"], None),
    # issue 21: the stopping rule's keys, and rlpipe bench time-to-return's options
    "zero-target-window": (["train", "dqn", "target_return=100", "target_window=0", "--out", "new"],
                           ["target_window=0", "positive"], None),
    "ttr-unknown-task": (["bench", "time-to-return", "--tasks", "pendulum-sax", "--peers", "none"],
                         ["pendulum-sax", "pendulum-sac"], None),
    "ttr-unknown-peer": (["bench", "time-to-return", "--peers", "stable"], ["stable", "sb3"], None),
    "ttr-override-after-peers": (["bench", "time-to-return", "--peers", "none", "gamma=0.99"],
                                 ["'gamma=0.99'", "key=value overrides go before the options"], None),
    "ttr-bad-threads": (["bench", "time-to-return", "--threads", "sb3=x"], ["--threads sb3=x", "SIDE=N"], None),
    "ttr-bad-cap": (["bench", "time-to-return", "--cap", "tfagent=30000"], ["--cap tfagent=30000", "SIDE=STEPS"], None),
    "ttr-too-many-side-seeds": (["bench", "time-to-return", "--seeds", "2", "--side-seeds", "tfagents=3"],
                                ["--side-seeds tfagents=3", "from 1 to --seeds (2)"], None),
    "ttr-negative-first-seed": (["bench", "time-to-return", "--seed", "-1", "--tasks", "pendulum-sac"],
                                ["--seed=-1", "the first seed, an integer from 0 to"], None),
    "ttr-bad-override": (["bench", "time-to-return", "batchsize=3", "--tasks", "pendulum-sac"],
                         ["batchsize", "batch_size"], None),
}
# One of each kind in a real process (a config key, a run folder in the way, a file that is not what it should
# be, memory, a missing extra, a place that cannot be written); every case above runs through main() here.
# with rlpipe[atari] installed (ale-py) an ALE id is no longer an error: that case is for machines without it, as CI's
ATARI_INSTALLED = importlib.util.find_spec("ale_py") is not None
SUBPROCESS_CASES = ["unknown-key", "out-holds-a-run", "eval-corrupt-policy", "huge-replay",
                    *([] if ATARI_INSTALLED else ["atari-extra"]), "out-in-sys"]


class _MultiDiscreteActions(gymnasium.Env):
    """Envs whose spaces rlpipe cannot serve (registered for the in-process cases only)."""

    observation_space = gymnasium.spaces.Box(-1, 1, (2,))
    action_space = gymnasium.spaces.MultiDiscrete([2, 3])

    def __init__(self, **_):
        pass


class _TextObservations(_MultiDiscreteActions):
    observation_space = gymnasium.spaces.Text(8)
    action_space = gymnasium.spaces.Discrete(2)


for _name, _cls in (("MultiDiscreteActions", _MultiDiscreteActions), ("TextObservations", _TextObservations)):
    if f"rlpipe-test/{_name}-v0" not in gymnasium.registry:
        gymnasium.register(f"rlpipe-test/{_name}-v0", entry_point=_cls)


GUARD = ["num_iterations=50", "initial_collect_steps=0", "eval_interval=0", "num_eval_episodes=1"]


def _prepare(cli_run, root: Path, name: str) -> tuple[Path, list[str], list[str]]:
    """A fresh working folder for one case (with a copy of the run where the case needs one)."""
    argv, words, damage = BAD_INPUTS[name]
    if argv[0] == "train" and "--keys" not in argv:
        # small settings first, so that a case wrongly accepted fails fast instead of training for minutes
        argv = argv[:2] + GUARD + argv[2:]
    cwd = root / name
    cwd.mkdir(parents=True)
    if any(a == "RUN" or a.startswith("RUN/") for a in argv):
        shutil.copytree(cli_run[1], cwd / "RUN")
        if damage is not None:
            damage(cwd / "RUN")
    return cwd, argv, words


@pytest.mark.parametrize("name", [n for n in BAD_INPUTS if not (ATARI_INSTALLED and n == "atari-extra")])
def test_bad_input_in_process(cli_run, tmp_path, monkeypatch, capfd, name):
    """The CLI's main() on each bad input: return 2, one line, the folder unchanged."""
    from rlpipe.scripts.cli import main

    cwd, argv, words = _prepare(cli_run, tmp_path, name)
    monkeypatch.chdir(cwd)
    before = snapshot(cwd)
    capfd.readouterr()
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse exits by itself
        code = exc.code
    assert_one_line_error(code, capfd.readouterr().err, *words)
    assert snapshot(cwd) == before, "a bad input wrote or changed files"


@pytest.fixture(scope="module")
def bad_processes(cli_run, tmp_path_factory):
    root = tmp_path_factory.mktemp("bad-inputs")

    def one(name):
        cwd, argv, _ = _prepare(cli_run, root, name)
        before = snapshot(cwd)
        proc = run_cli(argv, cwd=cwd, entry_point=True)
        return name, (proc, before, snapshot(cwd))

    with ThreadPoolExecutor(max_workers=2) as pool:
        return dict(pool.map(one, SUBPROCESS_CASES))


@pytest.mark.parametrize("name", SUBPROCESS_CASES)
def test_bad_input_in_a_real_process(bad_processes, name):
    proc, before, after = bad_processes[name]
    assert_one_line_error(proc.returncode, proc.stderr, *BAD_INPUTS[name][1])
    assert proc.stdout.strip() == ""
    assert after == before, "a bad input wrote or changed files"


def test_an_extra_that_is_not_installed_is_named(tmp_path):
    """Box2D hidden from a real process (a module of that name that fails to import, as a missing one does)."""
    hide = tmp_path / "without-box2d"
    hide.mkdir()
    (hide / "Box2D.py").write_text('raise ImportError("No module named \'Box2D\'", name="Box2D")\n')
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    proc = subprocess.run([ENTRY_POINT, "train", "td3", *GUARD, "env=LunarLanderContinuous-v3", "--out", "new"], cwd=cwd,
                          capture_output=True, text=True, timeout=300, env={**os.environ, "PYTHONPATH": str(hide)})
    assert_one_line_error(proc.returncode, proc.stderr, "LunarLanderContinuous-v3", 'pip install "gymnasium[box2d]"')
    assert list(cwd.iterdir()) == []


# --- output paths a command will write (`rlpipe video --out` calls check_output_file) ----------------


def test_check_output_file_refuses_a_directory_a_file_parent_and_a_read_only_place(tmp_path):
    from rlpipe.pipelines.errors import InputError
    from rlpipe.scripts.cli import check_output_file

    (tmp_path / "a-file").write_text("x")
    before = snapshot(tmp_path)
    cases = {tmp_path: "is a directory", tmp_path / "a-file" / "video.mp4": "is a file",
             tmp_path / "a-file" / "deeper" / "video.mp4": "is a file", Path("/sys/rlpipe-test/video.mp4"): "cannot write"}
    for path, words in cases.items():
        with pytest.raises(InputError) as info:
            check_output_file(path)
        assert str(info.value).startswith(f"--out {path}: ") and words in str(info.value) and "expected" in str(info.value)
    if os.geteuid() != 0:  # root writes into a read-only folder (the /sys case above covers root)
        locked = tmp_path / "locked"
        locked.mkdir(mode=0o555)
        with pytest.raises(InputError, match="cannot write"):
            check_output_file(locked / "video.mp4")
        locked.rmdir()
    check_output_file(tmp_path / "new" / "video.mp4")  # a new folder is fine
    check_output_file(tmp_path / "a-file")  # replacing a file is fine
    assert snapshot(tmp_path) == before


# --- every other failure: one line, and the traceback in a file --------------------------------------


class _Crashing(gymnasium.Env):
    """An env whose simulator fails: at its 30th step, or (``on_make``) as it is made."""

    observation_space = gymnasium.spaces.Box(-1, 1, (2,))
    action_space = gymnasium.spaces.Discrete(2)

    def __init__(self, on_make: bool = False, **_):
        if on_make:
            raise RuntimeError("the simulator could not start")
        self.steps = 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return np.zeros(2, np.float32), {}

    def step(self, action):
        self.steps += 1
        if self.steps == 30:
            raise RuntimeError("the simulator crashed")
        return np.zeros(2, np.float32), 1.0, False, False, {}


if "rlpipe-test/Crashing-v0" not in gymnasium.registry:
    gymnasium.register("rlpipe-test/Crashing-v0", entry_point=_Crashing)
    gymnasium.register("rlpipe-test/CrashingOnMake-v0", entry_point=_Crashing, kwargs={"on_make": True})


def test_a_crash_in_a_run_is_one_line_and_its_traceback_lands_in_the_run_directory(tmp_path, monkeypatch, capfd):
    from rlpipe.scripts.cli import main

    monkeypatch.chdir(tmp_path)
    capfd.readouterr()
    # a sized preset, named, keeps its settings on another env (`dqn` there would be sized first, playing the env
    # before the run directory exists); it gets its hint line first; the crash is one line
    code = main(["train", "dqn-cartpole-v0", *GUARD, "env=rlpipe-test/Crashing-v0", "--out", "run", "--no-progress"])
    err = [line for line in capfd.readouterr().err.strip().splitlines() if not line.startswith("rlpipe: hint:")]
    assert code == 1
    assert len(err) == 1 and err[0].startswith("rlpipe: error: RuntimeError: the simulator crashed"), err
    assert err[0].endswith("(full traceback in run/error.log)"), err
    log = (tmp_path / "run" / "error.log").read_text()
    assert "Traceback (most recent call last)" in log and "the simulator crashed" in log and "rlpipe train dqn" in log


def test_a_crash_before_the_run_directory_exists_leaves_its_traceback_in_a_temporary_file(tmp_path, monkeypatch, capfd):
    from rlpipe.scripts.cli import main

    monkeypatch.chdir(tmp_path)
    capfd.readouterr()
    code = main(["train", "dqn", *GUARD, "env=rlpipe-test/CrashingOnMake-v0", "--out", "run"])
    err = capfd.readouterr().err.strip().splitlines()
    assert code == 1 and len(err) == 1 and err[0].startswith("rlpipe: error: "), err
    assert "the simulator could not start" in err[0]
    log = Path(err[0].rsplit("(full traceback in ", 1)[1].rstrip(")"))
    try:
        assert log.parent == Path(tempfile.gettempdir()) and "Traceback" in log.read_text()
    finally:
        log.unlink()
    assert list(tmp_path.iterdir()) == []


# --- a run whose losses turn NaN --------------------------------------------------------------------


@pytest.mark.slow
def test_a_run_whose_parameters_turn_nan_stops_with_its_last_finite_checkpoint_and_resumes(tmp_path):
    """A parameter poisoned after update 130 (rlpipe's fault hook): the run stops at that block's end
    with one line, saves nothing more, and --resume continues from iteration 100's checkpoint."""
    steps = ["num_iterations=300", "initial_collect_steps=100", "eval_interval=100", "num_eval_episodes=1",
             "log_interval=50", "checkpoint_interval=100", "policy_save_interval=100", "--no-progress"]
    proc = subprocess.run([ENTRY_POINT, "train", "dqn", *steps, "--out", "run"], cwd=tmp_path, capture_output=True,
                          text=True, timeout=300, env={**os.environ, "RLPIPE_FAULT": "update@130:NAN"})
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 1, proc.stderr
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert lines[0].startswith("rlpipe: error: training diverged by iteration 150") and "loss_loss=nan" in lines[0]
    assert "run/checkpoints/step_0000000100" in lines[0] and "--resume run" in lines[0]
    run = tmp_path / "run"
    assert (run / "checkpoints" / "latest").read_text().strip() == "step_0000000100"
    state = torch.load(run / "checkpoints" / "step_0000000100" / "state.pt", weights_only=True)
    assert all(torch.isfinite(t).all() for t in state["loss"].values() if t.is_floating_point())
    assert not (run / "summary.json").exists()
    resumed = run_cli(["train", "dqn", *steps, "--resume", "run"], cwd=tmp_path, entry_point=True)
    assert resumed.returncode == 0, resumed.stderr
    assert json.loads((run / "summary.json").read_text())["iterations"] == 300


def test_a_learning_rate_that_diverges_stops_the_run(tmp_path, monkeypatch, capfd):
    from rlpipe.scripts.cli import main

    monkeypatch.chdir(tmp_path)
    capfd.readouterr()
    code = main(["train", "dqn", "learning_rate=1e30", *TINY, "collector.frames_per_batch=10", "--out", "run",
                 "--no-progress"])
    err = capfd.readouterr().err.strip().splitlines()
    assert code == 1 and len(err) == 1 and "training diverged by iteration" in err[0], err
    assert (tmp_path / "run" / "checkpoints" / "latest").read_text().strip() == "step_0000000000"


def test_metrics_hold_training_episode_length_and_count(cli_run):
    """CartPole pays 1 a step: a training episode's mean length is its mean return; the count only grows."""
    import csv

    with (cli_run[1] / "metrics.csv").open(newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if r["steps_per_s"]]
    assert rows and all(r["train_episode_length"] and r["episodes"] for r in rows)
    for r in rows:
        assert float(r["train_episode_length"]) == pytest.approx(float(r["train_episode_return"]), rel=1e-4)
    counts = [int(r["episodes"]) for r in rows]
    assert counts == sorted(counts) and counts[0] > 0
    # 400 env steps of CartPole episodes: about 400 / mean length of them
    assert counts[-1] >= 400 // max(float(r["train_episode_length"]) for r in rows) - 1


class _Corridor(gymnasium.Env):
    """A user's own env, made without a gymnasium id (no ``spec``): ten steps, paid 1 for action 1."""

    observation_space = gymnasium.spaces.Box(-1, 1, (2,), np.float32)
    action_space = gymnasium.spaces.Discrete(2)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return np.zeros(2, np.float32), {}

    def step(self, action):
        self.t += 1
        return np.zeros(2, np.float32), float(action), self.t >= 10, False, {}


def _corridor():
    from torchrl.envs import GymWrapper

    return GymWrapper(_Corridor(), categorical_action_encoding=True)


@pytest.mark.parametrize("configured, label", [("my-corridor", "my-corridor"), ("CartPole-v0", "_Corridor")])
def test_a_run_on_a_users_own_env_is_labelled_by_its_config_and_eval_says_what_to_do(configured, label, tmp_path,
                                                                                      monkeypatch, capfd):
    """Such a run was labelled "GymWrapper", and `rlpipe eval` on it said "unknown env id 'GymWrapper'"."""
    from rlpipe.pipelines import dqn
    from rlpipe.pipelines.config import apply_overrides
    from rlpipe.scripts.cli import main

    cfg = apply_overrides(dqn.DQN.preset(), [
        f"env={configured}", "fc_layer_params=[8]", "batch_size=8", "num_iterations=20", "initial_collect_steps=20",
        "eval_interval=0", "num_eval_episodes=1", "collector.sync=true", "collector.frames_per_batch=10",
        "eval_in_background=false", "log_interval=10"])
    result = dqn.DQN(cfg, env=_corridor).train(tmp_path / "run", progress=False)
    # the user's own name for it; a preset's gymnasium id left in the config is not this env: its class then
    assert result.summary["env"] == label
    assert json.loads((tmp_path / "run" / "config.json").read_text())["config"]["env"] == label
    monkeypatch.chdir(tmp_path)
    capfd.readouterr()
    for command in ("eval", "video"):
        code = main([command, "run"])
        err = capfd.readouterr().err.strip().splitlines()
        assert code == 2 and len(err) == 1, err
        assert f"trained on env {label!r}, which is no gymnasium id" in err[0] and "GymWrapper" not in err[0]
        assert "load_policy('run/policy')" in err[0]  # how to evaluate it: from Python, on the user's env
    assert not (tmp_path / "run" / "trained-agent.mp4").exists()
