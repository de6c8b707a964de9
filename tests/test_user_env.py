"""A user's own env from the command line: ``env=package.module:Class``, ``env=package:Id-v0`` and
``env_kwargs.KEY=VALUE``, as a user with an env in a package of their own (not installed, on PYTHONPATH) runs them.

One short run of the `rlpipe` program on collector processes and the background evaluator (each imports the
package itself) is shared by the checks of what a user does with it afterwards: eval, video and report (in this
process, the package on its sys.path) and --resume (the program again, its processes again). The refusals fail
before anything is trained, in this process.
"""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from rlpipe.envs import make_env
from rlpipe.scripts.cli import main

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")

ENTRY_POINT = str(Path(sys.executable).parent / "rlpipe")
PACKAGE = "rlpipe_test_arm"
HORIZON = 12  # env_kwargs.horizon: the episode length every process's env must have (the class's default is 50)

ENVS_PY = '''
import gymnasium
import numpy as np
from gymnasium import spaces


class TinyArm(gymnasium.Env):
    """A point on a line pushed towards the origin: observation (position, velocity), one action in [-1, 1]."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}

    def __init__(self, size: float = 1.0, horizon: int = 50, render_mode=None):
        self.size, self.horizon, self.render_mode = size, horizon, render_mode
        self.observation_space = spaces.Box(-np.inf, np.inf, (2,), np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.x, self.v, self.t = self.np_random.uniform(-self.size, self.size), 0.0, 0
        return self._obs(), {}

    def step(self, action):
        self.v = 0.9 * self.v + 0.1 * float(np.clip(action[0], -1.0, 1.0))
        self.x += self.v
        self.t += 1
        return self._obs(), -abs(self.x), False, self.t >= self.horizon, {}

    def _obs(self):
        return np.array([self.x, self.v], dtype=np.float32)

    def render(self):
        frame = np.zeros((32, 32, 3), dtype=np.uint8)
        frame[:, int(np.clip((self.x / self.size + 1) * 16, 0, 31))] = 255
        return frame


def make_arm(size: float = 1.0, horizon: int = 50) -> gymnasium.Env:
    return TinyArm(size, horizon)


class Buttons(TinyArm):
    def __init__(self):
        super().__init__()
        self.action_space = spaces.Discrete(3)

    def step(self, action):
        return super().step([int(action) - 1.0])


class NotAnEnv:
    pass


def unannotated():
    return TinyArm()


def not_an_env() -> gymnasium.Env:
    return {"x": 1}
'''

INIT_PY = f'''
import gymnasium

gymnasium.register(id="TinyArm-v0", entry_point="{PACKAGE}.envs:TinyArm")
'''

SMALL = ["actor_fc_layer_params=[8]", "critic_joint_fc_layer_params=[8]", "batch_size=16", "initial_collect_steps=40",
         "learning_starts=40", "log_interval=40", "eval_interval=40", "num_eval_episodes=2", "checkpoint_interval=40",
         "policy_save_interval=40", "collector.frames_per_batch=20"]


@pytest.fixture(scope="module")
def package(tmp_path_factory) -> Path:
    """A folder holding the user's package (importable only with it on PYTHONPATH)."""
    root = tmp_path_factory.mktemp("userpkg")
    (root / PACKAGE).mkdir()
    (root / PACKAGE / "__init__.py").write_text(INIT_PY)
    (root / PACKAGE / "envs.py").write_text(ENVS_PY)
    return root


def rlpipe(package: Path, *args: str, cwd: Path, timeout: float = 400) -> subprocess.CompletedProcess:
    """The `rlpipe` command as a user runs it, with the package on PYTHONPATH (not in the current directory)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(package), os.environ.get("PYTHONPATH")]))}
    return subprocess.run([ENTRY_POINT, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)


def rows(run: Path) -> list[dict]:
    with open(run / "metrics.csv") as fh:
        return list(csv.DictReader(fh))


@pytest.fixture(scope="module")
def trained(package, tmp_path_factory) -> Path:
    """A SAC run on ``package.envs:TinyArm`` with env_kwargs, collected by two worker processes and evaluated in the
    background evaluator's process: each makes the env itself from the run's config."""
    cwd = tmp_path_factory.mktemp("work")
    proc = rlpipe(package, "train", "sac", f"env={PACKAGE}.envs:TinyArm", f"env_kwargs.horizon={HORIZON}",
                  "env_kwargs.size=0.5", *SMALL, "num_iterations=80", "collector.workers=2", "collector.sync=false",
                  "eval_in_background=true", "--out", "run", "--no-progress", cwd=cwd)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return cwd / "run"


def test_the_run_records_the_env_and_every_process_makes_it_with_its_kwargs(trained):
    saved = json.loads((trained / "config.json").read_text())
    config = saved.get("config", saved)
    assert config["env"] == f"{PACKAGE}.envs:TinyArm" and config["env_kwargs"] == {"horizon": HORIZON, "size": 0.5}
    metrics = rows(trained)
    train_lengths = {float(r["train_episode_length"]) for r in metrics if r["train_episode_length"]}
    eval_lengths = {float(r["average_episode_length"]) for r in metrics if r["average_episode_length"]}
    assert train_lengths == {HORIZON}, metrics  # the collector processes' envs
    assert eval_lengths == {HORIZON}, metrics  # the background evaluator's
    recipe = json.loads((trained / "policy" / "policy.json").read_text())["env_recipe"]
    assert recipe["make"] == f"from {PACKAGE}.envs import TinyArm; env = TinyArm(horizon={HORIZON}, size=0.5)"


def test_eval_video_and_report_on_the_run(package, trained, monkeypatch, capsys):
    monkeypatch.syspath_prepend(str(package))  # in this process: the commands make the env here, no child process
    assert main(["eval", str(trained), "--episodes", "2", "--json"]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert result["AverageEpisodeLength"] == HORIZON and result["env"] == f"{PACKAGE}.envs:TinyArm"

    video = trained / "trained-agent.mp4"
    video.unlink(missing_ok=True)
    assert main(["video", str(trained), "--episodes", "1"]) == 0, capsys.readouterr().err
    assert video.stat().st_size > 0

    (trained / "report.html").unlink()
    assert main(["report", str(trained)]) == 0, capsys.readouterr().err
    assert f"{PACKAGE}.envs:TinyArm" in (trained / "report.html").read_text()


def test_resume_continues_the_run_on_its_env(package, trained):
    before = int(json.loads((trained / "summary.json").read_text())["iterations"])
    proc = rlpipe(package, "train", "sac", "--resume", str(trained), f"num_iterations={before + 40}", "--no-progress",
                  cwd=trained.parent)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert int(json.loads((trained / "summary.json").read_text())["iterations"]) == before + 40
    lengths = {float(r["train_episode_length"]) for r in rows(trained) if r["train_episode_length"]}
    assert lengths == {HORIZON}


def test_gymnasiums_module_id_form_trains_with_env_kwargs(package, tmp_path, monkeypatch, capsys):
    monkeypatch.syspath_prepend(str(package))
    status = main(["train", "sac", f"env={PACKAGE}:TinyArm-v0", "env_kwargs.horizon=7", *SMALL, "num_iterations=40",
                   "collector.workers=1", "collector.sync=true", "eval_in_background=false", "--out", str(tmp_path / "run"),
                   "--no-progress"])
    assert status == 0, capsys.readouterr().err
    assert {float(r["average_episode_length"]) for r in rows(tmp_path / "run") if r["average_episode_length"]} == {7}
    recipe = json.loads((tmp_path / "run" / "policy" / "policy.json").read_text())["env_recipe"]
    assert recipe["make"] == f"import gymnasium; env = gymnasium.make('{PACKAGE}:TinyArm-v0', horizon=7)"


def test_a_function_annotated_to_return_an_env(package, monkeypatch):
    monkeypatch.syspath_prepend(str(package))
    env = make_env(f"{PACKAGE}.envs:make_arm", horizon=5)
    assert env.rollout(100).shape == (5,)


@pytest.mark.parametrize("overrides, expected", [
    ([f"env={PACKAGE}.envs:TinyArm", "env_kwargs.horizn=3"],
     "env_kwargs (horizn=3) do not fit TinyArm(size: float = 1.0, horizon: int = 50, render_mode=None): got an "
     "unexpected keyword argument 'horizn'"),
    ([f"env={PACKAGE}.nowhere:TinyArm"], f"cannot import {PACKAGE}.nowhere (ModuleNotFoundError"),
    (["env=no_such_package_here:Arm-v0"], "cannot import no_such_package_here (ModuleNotFoundError"),
    ([f"env={PACKAGE}.envs:TinyArn"], f"{PACKAGE}.envs has no attribute 'TinyArn' and registers no gymnasium id "
                                       "'TinyArn' (did you mean 'TinyArm'"),
    ([f"env={PACKAGE}.envs:NotAnEnv"], "is the class NotAnEnv, not a gymnasium.Env subclass; expected"),
    ([f"env={PACKAGE}.envs:unannotated"], "is a function with no return annotation; expected"),
    ([f"env={PACKAGE}.envs:not_an_env"], "not_an_env() returned a dict; expected a gymnasium.Env"),
    ([f"env={PACKAGE}.envs:Buttons"], f"SAC needs a continuous (Box) action space; env '{PACKAGE}.envs:Buttons' has "
                                      "a discrete action space of 3 actions"),
    ([f"env={PACKAGE}.envs:TinyArm", "env_kwargs.seed=3"], "expected keywords other than seed"),
])
def test_bad_input_is_one_line_exit_2_and_nothing_written(package, tmp_path, monkeypatch, capsys, overrides, expected):
    monkeypatch.syspath_prepend(str(package))
    monkeypatch.chdir(tmp_path)
    status = main(["train", "sac", *overrides, "--out", "run", "--no-progress"])
    err = capsys.readouterr().err
    assert status == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("rlpipe: error: ") and expected in lines[0], err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_bench_times_the_users_env_and_the_peers_make_it_with_its_kwargs(package, tmp_path):
    """`rlpipe bench time-to-return --envs PKG.envs:TinyArm`: the user's env is a task of its own (the sized default,
    its kwargs, the run's whole budget as the cap), and the SB3/SBX runner makes the same env with the same kwargs."""
    refused = rlpipe(package, "bench", "time-to-return", "--envs", f"{PACKAGE}.envs:TinyArm", "--peers", "none",
                     cwd=tmp_path)
    assert refused.returncode == 2 and "expected --target-return" in refused.stderr
    assert len(refused.stderr.strip().splitlines()) == 1 and not list(tmp_path.iterdir())
    proc = rlpipe(package, "bench", "time-to-return", f"env_kwargs.horizon={HORIZON}", "--envs", f"{PACKAGE}.envs:TinyArm",
                  "--target-return", "-2", "--seeds", "1", "--peers", "none", "--cap-scale", "0.02", "--out", "out",
                  "--json", "ttr.json", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    figures = json.loads((tmp_path / "ttr.json").read_text())
    task = figures["tasks"][f"{PACKAGE}.envs:TinyArm"]
    assert (task["algo"], task["target"]) == ("sac", -2.0)
    assert task["cap"] == int(50_000 * 0.02)  # the sized budget (at least 50,000 env steps), scaled
    (run,) = figures["runs"]
    assert run["side"] == "rlpipe" and run["env_steps"] > 0 and not run["failed"]
    config = json.loads(next((tmp_path / "out").rglob("config.json")).read_text())["config"]
    assert config["env_kwargs"] == {"horizon": HORIZON}

    from rlpipe.scripts.bench import time_to_return as ttr

    runner = Path(ttr.__file__).with_name("peers")  # on the path as the peer's venv runs ttr_sb3.py from there
    code = (f"import sys; sys.path[:0] = [{str(runner)!r}, {str(package)!r}]\n"
            "from ttr_sb3 import env_maker\n"
            f"env = env_maker('{PACKAGE}.envs:TinyArm', {{'horizon': {HORIZON}}})()\n"
            "env.reset(seed=0); n = 0; done = False\n"
            "while not done:\n    done = env.step(env.action_space.sample())[3]; n += 1\n"
            f"made = env_maker('{PACKAGE}:TinyArm-v0', {{}})()\n"
            "print(type(env).__name__, n, made.spec.id)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=60)
    assert out.stdout.split() == ["TinyArm", str(HORIZON), "TinyArm-v0"], out.stderr[-2000:]
