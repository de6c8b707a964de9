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

# The tests press Ctrl-C as a terminal user does. Run from a background job or nohup, the suite
# would start with SIGINT ignored, and so would every process it starts (as rlpipe then wants):
# give it Python's usual handler, which its child processes get back as the default.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


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


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    """Under pytest-xdist's ``--dist loadgroup`` (pyproject's addopts), the tests that share a fixture
    wider than one test (a trained run that many checks read, defined in a test module) form one
    ``xdist_group``: they go to one worker as one unit, so the run is made once, not once per worker.
    Tests that share such fixtures through each other (``commands`` built on ``cli_run``) join one group.
    A test's own ``xdist_group`` mark (the Ray tests: one Ray at a time) is left as it is."""
    parent: dict[str, str] = {}

    def find(key: str) -> str:
        while parent.setdefault(key, key) != key:
            key = parent[key]
        return key

    shared = {}
    for item in items:
        info = getattr(item, "_fixtureinfo", None)  # pytest's record of the fixtures a test requests
        if info is None or item.get_closest_marker("xdist_group"):
            continue
        keys = [f"{defs[-1].baseid}::{name}" for name, defs in info.name2fixturedefs.items()
                if defs and defs[-1].scope != "function" and defs[-1].baseid.endswith(".py")]
        for key in keys[1:]:
            parent[find(key)] = find(keys[0])
        if keys:
            shared[item] = keys[0]
    for item, key in shared.items():
        item.add_marker(pytest.mark.xdist_group(find(key)))
