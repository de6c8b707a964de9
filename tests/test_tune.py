"""`rlpipe tune` as a user runs it: a tiny study (DQN on CartPole-v1 to a return of 8, which the rule's
greedy check passes within the first episodes, so a trial is mostly its runs' start-up), stopped by Ctrl-C
while its second trial runs and rerun to the end: the stored study goes on without running its finished
trial again, and ends with the preset file, the page and the best setting timed on fresh seeds. The
pruner on Optuna's own studies; bad input refused in one line before anything is written; the trials on
a two-node Ray cluster.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

optuna = pytest.importorskip("optuna", reason="Optuna is not installed: `pip install -e '.[tune]'` (scripts/setup.sh does)")

from rlpipe.scripts.cli import main  # noqa: E402
from rlpipe.scripts.tune_trials import BehindBestPruner, trial_value  # noqa: E402

CLI = [sys.executable, "-m", "rlpipe.scripts.cli"]
# every trial's runs: no evaluations but the target's (2 greedy episodes), a log row every 50 iterations
TINY = ["eval_interval=0", "baseline_episodes=0", "target_eval_episodes=2", "log_interval=50"]
BASE = ["tune", "dqn", "env=CartPole-v1", "--target", "8", "--budget", "20m", "--cap", "90", *TINY]
STUDY = [*BASE, "--trials", "2"]
QUIET = {"RAY_USAGE_STATS_ENABLED": "0", "RAY_DEDUP_LOGS": "0"}


def tune(args: list[str], cwd: Path, env: dict | None = None, timeout: float = 900) -> subprocess.CompletedProcess:
    """``rlpipe tune`` in a session of its own (a fault's SIGINT goes to its group, as a terminal's Ctrl-C does)."""
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        proc = subprocess.Popen([*CLI, *args], cwd=cwd, stdout=out, stderr=err, text=True, start_new_session=True,
                                env={**os.environ, **QUIET, **(env or {})})
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        out.seek(0)
        err.seek(0)
        return subprocess.CompletedProcess(proc.args, proc.returncode, out.read(), err.read())


def load(out: Path):
    return optuna.load_study(storage=f"sqlite:///{out / 'study.db'}", study_name="tune")


def processes_under(path: Path) -> list[str]:
    found = []
    for pid in os.listdir("/proc"):
        try:
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if pid.isdigit() and str(path) in cmd:
            found.append(cmd)
    return found


@pytest.mark.slow
def test_a_study_stopped_by_ctrl_c_continues_on_rerun_and_writes_the_preset_page_and_fresh_seed_time(tmp_path,
                                                                                                    capsys):
    out = tmp_path / "study"
    first = tune([*STUDY, "--out", str(out)], tmp_path, env={"RLPIPE_FAULT": "tune_trial@1"})
    assert first.returncode == 130, first.stderr[-3000:]
    (line,) = first.stderr.strip().splitlines()  # one line
    assert line.startswith("rlpipe: interrupted; 1 finished trials kept in") and "rerun the same command" in line, line
    study = load(out)
    states = [t.state.name for t in study.trials]
    assert states == ["COMPLETE", "FAIL"]
    cut = study.trials[1]
    # the cut-short trial's runs were launched and ended with the tuner: none is left
    assert (out / "trials" / "0001" / "seed0" / "output.log").exists()
    assert processes_under(out / "trials") == []
    trial0_log = out / "trials" / "0000" / "seed0" / "output.log"
    stamp = trial0_log.stat().st_mtime_ns

    second = tune([*STUDY, "--out", str(out)], tmp_path)
    assert second.returncode == 0, second.stderr[-3000:]
    assert "running again the trials cut short: 1" in second.stdout
    assert "trial 0:" not in second.stdout  # the finished trial is not run again
    assert trial0_log.stat().st_mtime_ns == stamp
    study = load(out)
    assert [t.state.name for t in study.trials] == ["COMPLETE", "FAIL", "COMPLETE"]
    assert study.trials[2].params == cut.params  # the cut-short trial, asked again
    for t in (study.trials[0], study.trials[2]):  # two seeds each; a miss counts cap + penalty (90 + 90)
        assert len(t.user_attrs["seconds"]) == 2
        assert t.value == pytest.approx(sum(t.user_attrs["seconds"]) / 2)
        assert all(s == 180 or s < 90 for s in t.user_attrs["seconds"])

    results = json.loads((out / "results.json").read_text())
    assert results["best_trial"] == study.best_trial.number
    confirmation = results["confirmation"]
    assert confirmation["trial"] == study.best_trial.number and confirmation["seeds"] == [100, 101]
    assert (out / "confirm" / f"{study.best_trial.number:04d}" / "seed100" / "output.log").exists()
    assert f"on fresh seeds [100, 101]: {confirmation['value']:.1f} s" in second.stdout

    preset = Path(results["preset"])
    assert preset == out / "dqn-cartpole-v1-tuned.yaml" and preset.exists()
    capsys.readouterr()
    assert main(["train", str(preset), "--keys"]) == 0  # `rlpipe train PRESET --keys`, in this process
    keys = capsys.readouterr().out
    best = study.best_trial.params
    assert f"initial_collect_steps={best['initial_collect_steps']}\n" in keys
    assert f"fc_layer_params=[{best['width']}, {best['width']}]\n" in keys
    assert "env=\"CartPole-v1\"\n" in keys

    page = (out / "tune.html").read_text()
    assert "history.png" in page and (out / "history.png").stat().st_size > 0
    assert "fresh seeds 100, 101" in page and str(preset) in page


@pytest.mark.slow
def test_a_study_whose_tuner_was_killed_runs_the_trial_it_left_again_and_no_run_outlives_the_tuner(tmp_path):
    out = tmp_path / "study"
    args = [*BASE, "--trials", "1", "--confirm-seeds", "0", "--out", str(out)]
    # SIGKILL to the tuner (its group: the runs are in sessions of their own) while its first trial runs: a crash
    first = tune(args, tmp_path, env={"RLPIPE_FAULT": "tune_trial@0:SIGKILL"})
    assert first.returncode == -signal.SIGKILL
    assert (out / "trials" / "0000" / "seed0" / "output.log").exists()
    deadline = time.monotonic() + 60
    while processes_under(out / "trials") and time.monotonic() < deadline:
        time.sleep(0.5)
    assert processes_under(out / "trials") == []  # each run was told to stop when its tuner died
    (left,) = load(out).trials
    assert left.state.name == "RUNNING"  # as the crash left it

    second = tune(args, tmp_path)
    assert second.returncode == 0, second.stderr[-3000:]
    assert "running again the trials cut short: 0" in second.stdout
    study = load(out)
    assert [t.state.name for t in study.trials] == ["FAIL", "COMPLETE"]
    assert study.trials[1].params == left.params
    assert (out / "dqn-cartpole-v1-tuned.yaml").exists() and "confirmation" not in study.user_attrs


@pytest.mark.slow
def test_a_study_for_the_return_at_a_time_maximises_the_exported_policys_return_and_its_preset_keeps_the_budget(
        tmp_path, capsys):
    """``--objective return-at=T``: each run trains for T (``time_budget``) keeping its best evaluation, the trial is
    the mean of the returns its runs export, the study maximises it, and the preset carries the budget."""
    out = tmp_path / "study"
    args = ["tune", "dqn", "env=CartPole-v1", "--objective", "return-at=8s", "--budget", "20m", "--trials", "1",
            "--confirm-seeds", "0", "--out", str(out), "eval_interval=500", "num_eval_episodes=2", "log_interval=100"]
    done = tune(args, tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    study = load(out)
    assert study.direction == optuna.study.StudyDirection.MAXIMIZE
    assert [t.state.name for t in study.trials] == ["COMPLETE"]  # one trial: a second could be pruned, by timing
    for t in study.trials:
        returns = []
        for seed in (0, 1):
            run = out / "trials" / f"{t.number:04d}" / f"seed{seed}" / "run"
            summary = json.loads((run / "summary.json").read_text())
            assert summary["stopped_because"] == "time_budget", summary
            assert json.loads((run / "config.json").read_text())["config"]["keep_best"] is True  # return-at adds it
            # the exported policy's return: the kept best evaluation's, or the last's where none beat it
            best = summary["best_evaluation"]
            returns.append(best["average_return"] if best["exported"] else summary["final_average_return"])
            assert returns[-1] >= best["average_return"] - 1e-6
        assert t.user_attrs["returns"] == pytest.approx(returns)
        assert t.value == pytest.approx(sum(returns) / 2)
    results = json.loads((out / "results.json").read_text())
    assert results["objective"] == "return-at=8s" and results["best_return"] == study.best_value
    assert f"return {study.best_value:.1f} at 8s" in done.stdout
    capsys.readouterr()
    assert main(["train", results["preset"], "--keys"]) == 0
    keys = capsys.readouterr().out
    assert 'time_budget="8s"\n' in keys and "keep_best=true\n" in keys
    page = (out / "tune.html").read_text()
    assert "the return at 8s" in page

    # the same folder, asked for another objective: one line, the study untouched
    capsys.readouterr()
    assert main([*args[:3], "--target", "100", *args[5:]]) == 2
    assert "holds a study with target=None, not 100.0" in capsys.readouterr().err
    assert len(load(out).trials) == 1


def _finished(value: float, curve: dict[int, float]):
    return optuna.trial.create_trial(value=value, intermediate_values=curve, params={"x": 0.0},
                                     distributions={"x": optuna.distributions.FloatDistribution(0, 1)})


@pytest.mark.parametrize("reports, pruned", [
    ({10: 5.0, 20: 50.0}, True),     # at 20 s below the best's 100 there
    ({10: 5.0, 20: 150.0}, False),   # ahead of it
    ({10: -50.0}, False),            # before half the best's time (40 s): too early to say
    ({10: 5.0, 60: 150.0}, True),    # after the best had reached its target (its last point, 200, holds on)
])
def test_a_trial_behind_the_best_trials_curve_at_the_same_second_is_pruned(reports, pruned):
    study = optuna.create_study(direction="minimize", pruner=BehindBestPruner())
    study.add_trial(_finished(300.0, {0: -100.0, 10: 0.0, 30: 40.0}))  # a worse trial: not the reference
    study.add_trial(_finished(40.0, {0: 0.0, 10: 20.0, 20: 100.0, 40: 200.0}))
    trial = study.ask()
    for step, value in reports.items():
        trial.report(value, step)
    assert trial.should_prune() is pruned


@pytest.mark.parametrize("step, pruned", [(40, False), (60, True)])
def test_with_a_horizon_pruning_waits_for_half_of_it(step, pruned):
    """A return-at study: every trial runs the same time, so the wait before pruning is half of it (100 s here),
    not half of the best trial's value (a return)."""
    study = optuna.create_study(direction="maximize", pruner=BehindBestPruner(horizon_s=100))
    study.add_trial(_finished(500.0, {0: 0.0, 40: 200.0, 60: 300.0}))
    trial = study.ask()
    trial.report(-10.0, step)
    assert trial.should_prune() is pruned


def test_a_miss_counts_as_the_cap_plus_the_penalty_and_a_trial_is_the_mean_of_its_seeds():
    results = [{"reached": True, "seconds": 20.0}, {"reached": False, "seconds": None}]
    assert trial_value(results, 60.0, 30.0) == (20.0 + 90.0) / 2


@pytest.mark.parametrize("args, line", [
    (["tune", "foo", "env=Pendulum-v1", "--target", "-200"], "unknown algorithm 'foo'; expected one of"),
    (["tune", "td3", "--target", "-200"], "no env: expected env=ID"),
    (["tune", "td3", "env=Pendulum-v1", "--target", "-200", "--budget", "30x"],
     "--budget 30x: expected a positive duration such as 90s, 30m or 2h"),
    (["tune", "td3", "env=NoSuchEnv-v0", "--target", "1"], "unknown env id 'NoSuchEnv-v0'"),
    (["tune", "td3", "env=Pendulum-v1", "--target", "1", "--seeds", "1"], "--seeds=1: expected an integer of at least 2"),
    (["tune", "td3", "env=Pendulum-v1", "--target", "1", "bogus=3"], "unknown config key 'bogus'"),
    (["tune", "sac,dqn", "env=Pendulum-v1", "--target", "1"], "DQN needs a discrete action space; env 'Pendulum-v1'"),
    (["tune", "td3", "env=Pendulum-v1"], "no objective: expected --target R (the time to a return of R) or --objective "
                                         "return-at=DURATION"),
    (["tune", "td3", "env=Pendulum-v1", "--objective", "return-at=10x"], "--objective return-at=10x: expected a "
                                                                         "positive duration after return-at="),
    (["tune", "td3", "env=Pendulum-v1", "--objective", "best"], "--objective best: expected return-at=DURATION"),
    (["tune", "td3", "env=Pendulum-v1", "--target", "1", "--objective", "return-at=10m"], "two objectives"),
    (["tune", "td3", "env=Pendulum-v1", "--objective", "return-at=10m", "time_budget=5m"],
     "time_budget=5m with --objective return-at=10m: the objective sets each run's time budget"),
])
def test_bad_input_is_one_line_and_exit_2_with_nothing_written(tmp_path, capsys, args, line):
    out = tmp_path / "study"
    assert main([*args, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("rlpipe: error: ") and line in err[0], err
    assert not out.exists()
