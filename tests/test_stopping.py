"""How a run ends: a time budget, and the reason summary.json and the last printed line give."""

from __future__ import annotations

import csv
import json

import pytest

from rlpipe.scripts.cli import main

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


def test_a_time_budget_ends_the_run_and_says_so(tmp_path, capsys):
    """time_budget: the run stops at the block that crosses it, exports and saves as at its end, and both
    summary.json and the last line say why; without one, the last line names num_iterations."""
    from rlpipe.pipelines.config import duration_seconds

    assert [duration_seconds(t) for t in ("90", "90s", "10m", "2h", "1.5m")] == [90, 90, 600, 7200, 90]
    assert duration_seconds("10 minutes") is None and duration_seconds("0s") is None
    code = main(["train", "sac-pendulum", "time_budget=1s", "num_iterations=100000", "target_return=null",
                 "--no-progress", "--out", str(tmp_path / "run")])
    out = capsys.readouterr().out.strip().splitlines()
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert code == 0 and summary["stopped_because"] == "time_budget" and summary["iterations"] < 100000
    assert out[-1] == "stopped because the time budget 1s was spent"
    assert (tmp_path / "run" / "policy" / "policy.onnx").exists()
    code = main(["train", "sac-pendulum", "time_budget=10 minutes", "--out", str(tmp_path / "bad")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "time_budget" in err[0] and not (tmp_path / "bad").exists()



FADING_PY = '''
import gymnasium
import numpy as np
from gymnasium import spaces


class Fading(gymnasium.Env):
    """Five steps an episode; each step's reward falls with every reset this env instance has had, so each
    evaluation on one instance returns less than the one before it, whatever the policy."""

    def __init__(self):
        self.observation_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, (1,), np.float32)
        self.resets = 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.resets, self.t = self.resets + 1, 0
        return self.np_random.uniform(-1, 1, 2).astype(np.float32), {}

    def step(self, action):
        self.t += 1
        obs = self.np_random.uniform(-1, 1, 2).astype(np.float32)
        return obs, -0.01 * self.resets, False, self.t >= 5, {}
'''


def test_a_plateau_ends_the_run_and_the_best_evaluation_is_the_exported_policy(tmp_path, capsys, monkeypatch):
    """plateau + keep_best: on an env whose evaluations only get worse, the untrained policy's (step 0) stays the
    best through a checkpoint and a resume; the run ends at the plateau (five evaluations and half the run past it),
    says so, and exports the best evaluation's policy as policy.onnx, the last beside it as its step's file."""
    import numpy as np

    from rlpipe.pipelines.artifacts.export import load_policy

    (tmp_path / "fading_env.py").write_text(FADING_PY)
    monkeypatch.syspath_prepend(str(tmp_path))
    run = tmp_path / "run"
    keys = ["env=fading_env:Fading", "initial_collect_steps=100", "collect_steps_per_iteration=1", "eval_interval=100",
            "num_eval_episodes=2", "initial_eval=true", "plateau=0.5", "keep_best=true", "checkpoint_interval=100",
            "policy_save_interval=100", "--no-progress", "--out", str(run)]
    assert main(["train", "sac-pendulum", "num_iterations=300", *keys]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    summary = json.loads((run / "summary.json").read_text())
    assert summary["stopped_because"] == "num_iterations" and summary["best_evaluation"]["step"] == 0
    assert summary["best_evaluation"]["exported"] and out[-1].startswith("stopped because its last iteration came")
    assert main(["train", "sac-pendulum", "num_iterations=5000", *keys[:-2], "--resume", str(run)]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    summary = json.loads((run / "summary.json").read_text())
    assert summary["stopped_because"] == "plateau" and summary["iterations"] == 500, summary
    with open(run / "metrics.csv") as f:
        returns = {int(r["step"]): float(r["average_return"]) for r in csv.DictReader(f) if r["average_return"]}
    assert sorted(returns) == [0, 100, 200, 300, 400, 500] and max(returns.values()) == returns[0]
    assert summary["best_evaluation"] == {"step": 0, "frames": 0, "average_return": pytest.approx(returns[0], abs=1e-6),
                                          "exported": True}
    assert out[-1].startswith("stopped because a plateau: no greedy evaluation beat step 0's")
    assert any(line.startswith("policy: the best greedy evaluation's, step 0") for line in out)
    best, info = load_policy(run / "policy")
    last, _ = load_policy(run / "policy", step=500)
    assert info["chosen"] == "best" and info["best"]["step"] == 0 and info["best"]["last_step"] == 500
    page = (run / "report.html").read_text()  # the page says which policy was exported, and marks it
    assert "exported policy" in page and "step 0, AverageReturn" in page and "plateau" in page
    observations = np.random.default_rng(0).uniform(-1, 1, (64, 2)).astype(np.float32)
    assert not np.allclose(best(observations), last(observations))  # 400 updates apart
