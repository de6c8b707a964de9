"""Test settings: headless rendering, one thread per process (2-core machines), quiet warnings."""

import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")

import pytest  # noqa: E402
import torch  # noqa: E402

torch.set_num_threads(1)


@pytest.fixture
def run_dir(tmp_path):
    """A path for a run directory that does not exist yet."""
    return tmp_path / "run"
