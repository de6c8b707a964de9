"""`rlpipe ablate td3` as a user runs it: a tiny study (2 variants x 1 seed, 600 env steps each, both
runs in flight together) interrupted with Ctrl-C while its runs are in flight, rerun to completion, then
rerun again (nothing left to do); and bad input refused before anything is created. (Several seeds per
variant: tests/test_analysis.py's studies.)

``--steps 600`` is 50 start-up steps (a tenth, in whole 50-step blocks) + 550 iterations, evaluated
every 250 iterations and at the end.
"""

from __future__ import annotations

import csv
import importlib.util
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from rlpipe.scripts.cli import main

CLI = [sys.executable, "-m", "rlpipe.scripts.cli"]
VARIANTS = ("full", "no_clipped_double_q")
STUDY = ["ablate", "td3", "--envs", "Pendulum-v1", "--seeds", "1", "--steps", "600", "--evals", "2",
         "--eval-episodes", "1", "--variants", ",".join(VARIANTS), "--workers", "2"]
SMALL = ["actor_fc_layer_params=[32]", "critic_fc_layer_params=[32]", "batch_size=32"]  # the study is the subject
RUNS = [(variant, seed) for variant in VARIANTS for seed in (0,)]


def run_dir(out: Path, variant: str, seed: int) -> Path:
    return out / "Pendulum-v1" / variant / f"seed{seed}"


def checkpoint_step(run: Path) -> int:
    try:
        return int((run / "checkpoints" / "latest").read_text().strip().removeprefix("step_"))
    except (OSError, ValueError):
        return -1


def read_rows(run: Path) -> list[dict]:
    try:
        with (run / "metrics.csv").open(newline="") as fh:
            return list(csv.DictReader(fh))
    except OSError:
        return []


def eval_steps(rows: list[dict]) -> list[int]:
    return [int(r["step"]) for r in rows if r["average_return"]]


def group_members(pgid: int) -> list[str]:
    found = []
    for name in os.listdir("/proc"):
        if name.isdigit():
            try:
                with open(f"/proc/{name}/stat") as fh:
                    fields = fh.read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if fields[0] != "Z" and int(fields[2]) == pgid:
                found.append(name)
    return found


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    out = tmp_path_factory.mktemp("ablation") / "study"
    command = [*CLI, *STUDY, *SMALL, "--continue", "checkpoint", "--out", str(out)]
    info = {"out": out}

    # 1. Ctrl-C (SIGINT to the process group, as a terminal sends it) while runs are in flight: the
    #    moment the first run starts to evaluate iteration 250 (its log row written, its evaluation
    #    row not), by rlpipe's test hook; the other run is mid-way too.
    marker = out.parent / "pressed-by"
    first = subprocess.Popen(command, start_new_session=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True, env={**os.environ, "RLPIPE_FAULT": "evaluate@250", "RLPIPE_FAULT_ONCE": str(marker)})
    try:
        _, info["interrupt_stderr"] = first.communicate(timeout=180)  # the hook's Ctrl-C ends the study
        info["interrupt_exit"] = first.returncode
        pressed_by = Path(marker.read_text().split("--out", 1)[1].split()[0])
        evaluating = next((v, s) for v, s in RUNS if run_dir(out, v, s) == pressed_by)
        info["evaluating"] = evaluating
        info["in_flight"] = {f"{v}/seed{s}": checkpoint_step(run_dir(out, v, s)) for v, s in RUNS}
        info["done_before_interrupt"] = [f"{v}/seed{s}" for v, s in RUNS
                                         if (run_dir(out, v, s) / "summary.json").exists()]
        deadline = time.monotonic() + 60  # a run's processes may take a moment to be reaped
        while group_members(first.pid) and time.monotonic() < deadline:
            time.sleep(0.1)
        info["interrupt_left"] = group_members(first.pid)
        info["report_after_interrupt"] = (out / "ablation.csv").exists()
        info["rows_after_interrupt"] = {run: read_rows(run_dir(out, *run)) for run in RUNS}
    finally:
        if first.poll() is None:
            os.killpg(first.pid, signal.SIGKILL)
            first.wait()

    # 2. the same command again: resumes the interrupted runs, runs the others, writes the report
    info["resume"] = subprocess.run(command, capture_output=True, text=True, timeout=300)
    info["summary_mtimes"] = {run: (run_dir(out, *run) / "summary.json").stat().st_mtime_ns
                              for run in RUNS if (run_dir(out, *run) / "summary.json").exists()}
    info["run_files"] = {run: run_files(run_dir(out, *run)) for run in RUNS}

    # 3. and again: nothing left to run
    info["again"] = subprocess.run(command, capture_output=True, text=True, timeout=300)
    return info


def run_files(run: Path) -> dict[str, int]:
    """Every file of a run directory with its modification time."""
    return {str(p.relative_to(run)): p.stat().st_mtime_ns for p in run.rglob("*") if p.is_file()}


@pytest.mark.slow
def test_ctrl_c_stops_the_study_and_its_runs(study):
    assert study["evaluating"] is not None, "no run was caught evaluating iteration 250"
    assert study["done_before_interrupt"] == [], "the study finished a run before it was interrupted"
    assert study["interrupt_exit"] == 130, study["interrupt_stderr"][-2000:]
    assert "rerun the same command" in study["interrupt_stderr"]
    assert study["interrupt_left"] == []  # no run keeps going in the background
    assert not study["report_after_interrupt"]
    # the run caught evaluating has a checkpoint to resume from
    assert study["in_flight"]["{}/seed{}".format(*study["evaluating"])] >= 0


@pytest.mark.slow
def test_rerun_completes_every_run(study):
    second = study["resume"]
    assert second.returncode == 0, second.stderr[-3000:]
    out = study["out"]
    for variant, seed in RUNS:
        run = run_dir(out, variant, seed)
        summary = json.loads((run / "summary.json").read_text())
        assert summary["iterations"] == 550 and summary["frames"] == 600, (variant, seed, summary)
        assert summary["seed"] == seed
        config = json.loads((run / "config.json").read_text())["config"]
        assert config["clipped_double_q"] is (variant == "full")
        assert all(config[k] for k in ("deterministic_policy", "experience_replay", "target_networks",
                                       "target_policy_smoothing", "delayed_policy_updates"))
        # an interrupted run was continued, not started over: no evaluation twice, in order
        evals = eval_steps(read_rows(run))
        assert evals == sorted(set(evals)) and evals[0] == 0 and evals[-1] == 550, (variant, seed, evals)
        assert set(evals) <= {0, 250, 500, 550}
    # the runs that were in flight resumed from their checkpoint (their logs say so)
    variant, seed = study["evaluating"]
    log = (out / "Pendulum-v1" / variant / f"seed{seed}.log").read_text()
    assert "interrupted" in log, log[-2000:]
    kept = study["rows_after_interrupt"][(variant, seed)]
    assert read_rows(run_dir(out, variant, seed))[: len(kept)] == kept  # its rows before the interrupt


@pytest.mark.slow
def test_run_interrupted_while_evaluating_still_has_every_evaluation(study):
    run = study["evaluating"]
    rows = study["rows_after_interrupt"][run]
    assert (250, False) in [(int(r["step"]), bool(r["average_return"])) for r in rows]  # logged 250 ...
    assert 250 not in eval_steps(rows)  # ... and was stopped while evaluating it
    assert eval_steps(read_rows(run_dir(study["out"], *run))) == [0, 250, 500, 550]


@pytest.mark.slow
def test_report_lists_every_run(study):
    assert study["resume"].returncode == 0, study["resume"].stderr[-3000:]
    out = study["out"]
    with (out / "ablation.csv").open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == len(RUNS)
    assert set(rows[0]) >= {"env", "variant", "seed", "final_return", "auc"}
    assert sorted((r["variant"], int(float(r["seed"]))) for r in rows) == sorted(RUNS)
    assert {r["env"] for r in rows} == {"Pendulum-v1"}
    for r in rows:
        final = float(r["final_return"])
        assert -2000 < final <= 0 and float(r["auc"]) == float(r["auc"])  # a number, not NaN
        summary = json.loads((run_dir(out, r["variant"], int(float(r["seed"]))) / "summary.json").read_text())
        assert final == pytest.approx(summary["final_average_return"], rel=1e-4)

    md = (out / "ablation.md").read_text()
    for variant in VARIANTS:
        assert variant in md
    full_line = next(line for line in md.splitlines() if "full" in line and "|" in line)
    assert "**" in full_line or "★" in full_line, full_line  # the full agent is marked
    for name in ("curves_Pendulum-v1.png", "ecdf_final_returns.png"):
        data = (out / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000, name
    # the command prints where the report is
    for name in ("ablation.csv", "ablation.md", "curves_Pendulum-v1.png", "ecdf_final_returns.png"):
        assert name in study["resume"].stdout


@pytest.mark.slow
def test_rerun_of_a_finished_study_skips_every_run(study):
    again = study["again"]
    assert again.returncode == 0, again.stderr[-3000:]
    mtimes = {run: (run_dir(study["out"], *run) / "summary.json").stat().st_mtime_ns for run in RUNS}
    assert mtimes == study["summary_mtimes"]
    # no run was started again: not one file of a run directory was written, none was added
    assert {run: run_files(run_dir(study["out"], *run)) for run in RUNS} == study["run_files"]
    assert "ablation.md" in again.stdout


# --- bad input ---------------------------------------------------------------------------------------


BAD = {
    "zero seeds": (["--seeds", "0"], "--seeds"),
    "unknown variant": (["--variants", "full,no_target_nets"], "no_target_nets"),
    "unknown ingredient": (["--variants", "full,clipped_double_qq"], "clipped_double_qq"),
    # --steps 600 with 600 random start-up steps leaves no step to learn from
    "no steps beyond the random ones": (["initial_collect_steps=600"], "random start-up steps"),
    "a key the study sets": (["num_iterations=100"], "--steps"),
    "unknown env": (["--envs", "Pendulum-v9"], "Pendulum-v9"),
    "key typo": (["lerning_rate=1e-3"], "lerning_rate"),
    # every env is checked before any run starts (the discrete one is the second)
    "discrete env": (["--envs", "Pendulum-v1,CartPole-v1"], "CartPole-v1"),
    "extra not installed": (["--envs", "Pendulum-v1,ALE/Pong-v5"], "rlpipe[atari]"),
    "memory": (["replay_buffer_capacity=1000000000000"], "replay_buffer_capacity"),
    "absurd workers": (["--workers", "100000"], "--workers=100000"),
    "out under a file": (["--out", "FILE/study"], "is a file"),
}


def _args(out: Path, change: list[str]) -> list[str]:
    args = [*STUDY, "--out", str(out)]
    if change[0] == "--out":
        (out.parent / "FILE").write_text("a file")
        args[-1] = str(out.parent / change[1])
    elif change[0].startswith("--"):
        i = args.index(change[0])
        args[i + 1] = change[1]
    else:
        args += change
    return args


@pytest.mark.parametrize("name", [n for n in BAD if not (n == "extra not installed" and importlib.util.find_spec("ale_py"))])
def test_bad_input_is_one_line_and_creates_nothing(name, tmp_path, capsys):
    change, word = BAD[name]
    out = tmp_path / "study"
    code = main(_args(out, change))
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and err[0].startswith("rlpipe: error:") and word in err[0], err
    assert not out.exists()


def test_bad_input_in_a_real_process(tmp_path):
    out = tmp_path / "study"
    proc = subprocess.run([*CLI, *_args(out, BAD["key typo"][0])], capture_output=True, text=True, timeout=120)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2
    assert len(lines) == 1 and lines[0].startswith("rlpipe: error:") and "lerning_rate" in lines[0], proc.stderr
    assert "learning_rate" in lines[0]  # the closest valid key is suggested
    assert not out.exists()


def test_every_env_is_checked_before_a_run_starts_and_box2d_envs_pass(tmp_path):
    from rlpipe.scripts.ablate import plan
    from rlpipe.scripts.cli import _parser

    args = _parser().parse_args([*_args(tmp_path / "study", ["--envs", "LunarLanderContinuous-v3,BipedalWalker-v3"])])
    jobs = plan(args)
    assert {j.env for j in jobs} == {"LunarLanderContinuous-v3", "BipedalWalker-v3"} and len(jobs) == 2 * len(RUNS)
    assert not (tmp_path / "study").exists()


# --- a study killed through the fault hook and run again ends as an uninterrupted one ---------------

TINY = ["ablate", "td3", "--envs", "Pendulum-v1", "--seeds", "1", "--steps", "300", "--evals", "1",
        "--eval-episodes", "1", "--variants", "full,target_policy_smoothing", "--workers", "2",  # an ingredient names its no_ variant
        "actor_fc_layer_params=[32]", "critic_fc_layer_params=[32]", "batch_size=32"]
TINY_RUNS = [(variant, 0) for variant in ("full", "no_target_policy_smoothing")]  # in flight together (--workers 2)


@pytest.mark.slow
def test_killed_study_continues_to_the_results_of_an_uninterrupted_one(tmp_path):
    reference, stopped = tmp_path / "reference", tmp_path / "stopped"
    done = subprocess.run([*CLI, *TINY, "--out", str(reference)], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]

    # The first run to finish the block of iteration 150 SIGKILLs the study's whole process group
    # (the study and every run in flight): nothing is saved, as after `kill -9` or a power cut.
    marker = tmp_path / "killed-by"
    killed = subprocess.run([*CLI, *TINY, "--out", str(stopped)], capture_output=True, text=True, timeout=600,
                            start_new_session=True,
                            env={**os.environ, "RLPIPE_FAULT": "collected@150:SIGKILL", "RLPIPE_FAULT_ONCE": str(marker)})
    assert killed.returncode == -signal.SIGKILL and marker.exists()
    assert not (stopped / "ablation.csv").exists()
    assert not all((run_dir(stopped, *run) / "summary.json").exists() for run in TINY_RUNS)

    again = subprocess.run([*CLI, *TINY, "--out", str(stopped)], capture_output=True, text=True, timeout=600)
    assert again.returncode == 0, again.stderr[-3000:]
    assert "aggregate_iqm.png" in again.stdout
    # The same table, and every run the same evaluations, as the uninterrupted study's.
    assert (stopped / "ablation.csv").read_text() == (reference / "ablation.csv").read_text()
    for run in TINY_RUNS:
        assert [(r["step"], r["average_return"]) for r in read_rows(run_dir(stopped, *run))] == \
               [(r["step"], r["average_return"]) for r in read_rows(run_dir(reference, *run))], run
    aggregate = (stopped / "aggregate.csv").read_text()
    assert aggregate == (reference / "aggregate.csv").read_text() and "no_target_policy_smoothing" in aggregate
