"""The learner's thread count and the rest of a run's arithmetic: decided by a rule, never by a timing; recorded
in the run, reused by ``--resume``, and a resume on a different arithmetic or with a changed key is not exact."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from test_resume_exact import TD3_ARGS, _assert_same_run, _rows

from rlpipe.pipelines.config import CollectorConfig
from rlpipe.pipelines.td3 import TD3Config
from rlpipe.pipelines.training.threads import MAX_LEARNER_THREADS, threads_rule

RLPIPE = [sys.executable, "-m", "rlpipe.scripts.cli"]
# the run chooses its own threads (num_threads=-1, the default): the suite's cap of one (conftest) is taken off
ARGS = [*TD3_ARGS, "seed=3", "num_threads=-1"]


def _train(command: list[str], cwd: Path) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "RLPIPE_FAULT")}
    return subprocess.run([*RLPIPE, "train", *command, "--no-progress"], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=600)


@pytest.fixture(scope="module")
def quiet_run(tmp_path_factory) -> Path:
    """The td3 run, alone on the machine (as alone as the suite leaves it)."""
    out = tmp_path_factory.mktemp("quiet") / "run"
    done = _train([*ARGS, "--out", str(out)], out.parent)
    assert done.returncode == 0, done.stderr[-3000:]
    return out


def test_the_rule_counts_cores_not_time(monkeypatch):
    monkeypatch.delenv("OMP_NUM_THREADS")
    cores = len(os.sched_getaffinity(0))
    in_learner = TD3Config(collector=CollectorConfig(workers=1, sync=True))
    beside = TD3Config(collector=CollectorConfig(workers=1, sync=False))
    assert threads_rule(in_learner)[0] == max(1, min(MAX_LEARNER_THREADS, cores // 2))
    assert threads_rule(beside)[0] == max(1, min(MAX_LEARNER_THREADS, (cores - 1) // 2))
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert threads_rule(in_learner)[0] == threads_rule(beside)[0] == 1


@pytest.mark.slow
def test_the_same_command_and_seed_is_the_same_run_beside_a_busy_process(quiet_run, tmp_path):
    """A CPU hog of ours beside the run (bounded: killed when the run ends, or after five minutes of its own):
    the run chooses the threads the quiet one chose and computes the same numbers."""
    hog = subprocess.Popen([sys.executable, "-c", "import time\nend = time.time() + 300\nwhile time.time() < end: pass"])
    try:
        busy = tmp_path / "run"
        done = _train([*ARGS, "--out", str(busy)], tmp_path)
    finally:
        hog.kill()
        hog.wait()
    assert done.returncode == 0, done.stderr[-3000:]
    threads = [json.loads((run / "config.json").read_text())["config"]["num_threads"] for run in (quiet_run, busy)]
    assert threads[0] == threads[1] >= 1
    _assert_same_run(quiet_run, busy)
    summary = json.loads((busy / "summary.json").read_text())
    assert summary["arithmetic"]["threads"] == threads[0] and summary["arithmetic"]["torch"]


def _resumed(quiet_run: Path, tmp_path: Path, *overrides: str) -> tuple[subprocess.CompletedProcess, dict]:
    run = tmp_path / "run"
    shutil.copytree(quiet_run, run)
    done = _train(["td3", "--resume", str(run), "num_iterations=300", *overrides], tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    return done, json.loads((run / "summary.json").read_text())


@pytest.mark.slow
def test_a_resume_that_only_trains_longer_stays_exact(quiet_run, tmp_path):
    done, summary = _resumed(quiet_run, tmp_path)
    assert summary["exact"] is True and "no longer exact" not in done.stderr
    assert summary["config_changes"] == [{"iteration": 200, "changed": {"num_iterations": [200, 300]}}]
    assert _rows(tmp_path / "run")[-1]["step"] == "300"


@pytest.mark.slow
@pytest.mark.parametrize("key", ["batch_size", "num_threads"])
def test_a_resume_that_changes_the_arithmetic_says_so_and_is_not_exact(quiet_run, tmp_path, key):
    before = json.loads((quiet_run / "config.json").read_text())["config"][key]
    if key == "num_threads" and before + 1 > len(os.sched_getaffinity(0)):
        pytest.skip("one more thread needs one more core")
    value = before // 2 if key == "batch_size" else before + 1
    said = f"batch_size={value} (was {before})" if key == "batch_size" else f"threads {before} -> {value}"
    done, summary = _resumed(quiet_run, tmp_path, f"{key}={value}")
    lines = [line for line in done.stderr.splitlines() if "no longer exact" in line]
    assert len(lines) == 1 and said in lines[0] and "iteration 200" in lines[0], done.stderr
    assert summary["exact"] is False and said in summary["why"]
    assert summary["config_changes"][0]["changed"][key] == [before, value]
    assert json.loads((tmp_path / "run" / "config.json").read_text())["config"][key] == value
