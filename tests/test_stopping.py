"""How a run ends: a time budget, and the reason summary.json and the last printed line give."""

from __future__ import annotations

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

