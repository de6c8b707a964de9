"""``rlpipe bench anytime``: the rule every side is evaluated by (marks of the run's own time, the rule's evaluations
left out), its curves and bands, bad input, and one tiny real run (rlpipe's side only: the peers' venvs download
gigabytes)."""

from __future__ import annotations

import json
import time

import pytest

from rlpipe.scripts.bench import anytime
from rlpipe.scripts.bench.peers.ttr_rule import Marks
from rlpipe.scripts.cli import main


@pytest.mark.unit
def test_a_mark_is_due_on_the_runs_own_time_and_its_evaluation_is_left_out():
    marks = Marks([5.0, 20.0], eval_episodes=3, launch_unix=time.time() - 10.0)
    assert marks.due() and not marks.done()
    seeds = [marks.episode_seed(k) for k in range(3)]

    def evaluate():
        time.sleep(0.2)  # an evaluation's time: not the run's
        return {"last": ([1.0, 2.0, 3.0], [10, 10, 10])}

    marks.record(evaluate, env_steps=100, updates=50)
    point, = marks.points
    assert point["mark_s"] == 5.0 and 10.0 <= point["trained_s"] < 20.0
    assert point["last"]["return"] == 2.0 and (point["env_steps"], point["updates"]) == (100, 50)
    assert marks.excluded >= 0.2 and marks.elapsed() < time.time() - marks.launch - 0.2
    assert not marks.due()  # 20 s of the run's own time have not passed
    # the next mark's episodes are seeded by the mark alone: the same for every side and every run
    assert [marks.episode_seed(k) for k in range(3)] != seeds
    assert Marks([5.0], 3, launch_unix=0.0).episode_seed(1) == seeds[1]


@pytest.mark.unit
def test_the_band_is_a_bootstrap_interval_of_the_mean_over_three_seeds_or_more():
    runs = [{"env": "E", "side": "sbx", "seed": s, "points": [{"last": {"return": r}}, {"last": {"return": r + 10}}]}
            for s, r in ((0, 1.0), (1, 2.0), (2, 6.0))]
    c = anytime.curves(runs, [1.0, 2.0])["E"]["sbx"]
    assert c["mean"] == [3.0, 13.0]
    assert 1.0 <= c["low"][0] < 3.0 < c["high"][0] <= 6.0
    two = anytime.curves(runs[:2], [1.0, 2.0])["E"]["sbx"]
    assert two["mean"] == [1.5, 11.5] and two["low"] == [None, None]  # two seeds: no interval claimed


@pytest.mark.parametrize("argv, said", [
    (["--budget", "0"], "--budget 0: expected a positive duration"),
    (["--budget", "ten"], "--budget ten: expected a positive duration"),
    (["--marks", "0"], "--marks 0: expected a positive count"),
    (["--peers", "cleanrl"], "unknown peer 'cleanrl' for anytime"),
])
def test_bad_input_is_one_line_and_nothing_is_written(tmp_path, capsys, argv, said):
    out = tmp_path / "bench"
    assert main(["bench", "anytime", "--envs", "Pendulum-v1", *argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and said in err, err
    assert not out.exists()


@pytest.mark.slow
def test_a_tiny_run_evaluates_rlpipes_exported_and_last_policy_at_each_mark(tmp_path, capsys):
    out, figures = tmp_path / "bench", tmp_path / "anytime.json"
    code = main(["bench", "anytime", "--envs", "Reacher-v5", "--budget", "16", "--marks", "2", "--peers", "none",
                 "--seeds", "1", "--seed", "100", "--eval-episodes", "2", "--out", str(out), "--json", str(figures)])
    assert code == 0
    printed = capsys.readouterr().out
    data = json.loads(figures.read_text())
    (run,) = data["runs"]
    assert run["side"] == "rlpipe" and run["rc"] == 0 and not run["failed"]
    first, second = run["points"]
    assert (first["mark_s"], second["mark_s"]) == (8.0, 16.0)
    assert first["mark_s"] <= first["trained_s"] < second["mark_s"] <= second["trained_s"]
    assert 0 < first["env_steps"] < second["env_steps"]
    for point in run["points"]:
        assert len(point["exported"]["returns"]) == len(point["last"]["returns"]) == 2
    summary = json.loads((out / "Reacher-v5" / "rlpipe-seed100" / "run" / "summary.json").read_text())
    assert summary["stopped_because"] == "anytime" and summary["frames"] >= second["env_steps"]
    assert data["curves"]["Reacher-v5"]["rlpipe"]["seeds"]["100"] == [p["exported"]["return"] for p in run["points"]]
    assert "| rlpipe (mean [95% CI]) |" in printed and "| rlpipe (last), seed 100 |" in printed
