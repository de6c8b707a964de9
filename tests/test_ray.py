"""Collectors as Ray actors (``collector.backend=ray``) on a real Ray: a two-node cluster on this machine
that a run joins, a local instance a run starts and stops, Ctrl-C on a Ray run.

Runs are real ``rlpipe train`` processes, each in its own session, so that what Ray processes a run
started can be found (and must be gone) after it exits.
"""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from rlpipe.pipelines import td3
from rlpipe.pipelines.config import apply_overrides
from rlpipe.pipelines.errors import InputError

ray = pytest.importorskip("ray", reason="Ray is not installed: `pip install -e '.[ray]'` (scripts/setup.sh does)")

MODULE = [sys.executable, "-m", "rlpipe.scripts.cli"]
# td3 on Pendulum: 100 random steps, then 300 iterations; updates start at learning_starts=256
TINY = ["num_iterations=300", "initial_collect_steps=100", "eval_interval=150", "num_eval_episodes=1",
        "log_interval=100", "checkpoint_interval=150", "policy_save_interval=150", "collector.backend=ray",
        "collector.workers=2", "num_threads=1"]
FRAMES, UPDATES = 400, 400 - 256
QUIET = {"RAY_USAGE_STATS_ENABLED": "0", "RAY_DEDUP_LOGS": "0"}


def train(args, cwd: Path, env: dict | None = None, timeout: float = 400) -> tuple[subprocess.CompletedProcess, int]:
    """``rlpipe train`` in a session of its own; returns the process and its session id."""
    proc = subprocess.Popen([*MODULE, "train", *map(str, args), "--no-progress"], cwd=cwd, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True,
                            env={**os.environ, **QUIET, **(env or {})})
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        pytest.fail(f"run did not finish in {timeout} s\n{err[-3000:]}")
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err), proc.pid


def session_processes(sid: int) -> list[str]:
    """Command lines of the processes in session ``sid``."""
    return [_cmdline(p) for p in Path("/proc").glob("[0-9]*") if _session(p) == sid]


def assert_no_leftovers(sid: int, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while (left := session_processes(sid)) and time.monotonic() < deadline:
        time.sleep(0.5)
    assert not left, f"processes the run started are still there: {left}"


def metrics_rows(run: Path) -> list[dict[str, str]]:
    with (run / "metrics.csv").open(newline="") as fh:
        return list(csv.DictReader(fh))


def assert_finished(run: Path, proc: subprocess.CompletedProcess) -> list[dict[str, str]]:
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads((run / "summary.json").read_text())
    assert (summary["iterations"], summary["frames"], summary["updates"]) == (300, FRAMES, UPDATES)
    assert (run / "policy" / "policy.json").exists()
    rows = metrics_rows(run)
    logged = [r for r in rows if r["workers_alive"]]
    assert [int(r["step"]) for r in logged] == [100, 200, 300]
    assert all(int(r["workers_alive"]) == 2 for r in logged)
    # the version the learner sends is its update count; frames were collected with versions at most that
    assert [int(r["weight_version"]) for r in logged] == [int(r["updates"]) for r in logged]
    staleness = [float(r["weight_staleness"]) for r in logged]
    assert staleness[0] == 0 and all(0 <= s <= int(r["updates"]) for s, r in zip(staleness, logged))
    return rows


@pytest.fixture
def cluster():
    """A Ray cluster of two nodes on this machine: a head and one more, a CPU each."""
    from ray.cluster_utils import Cluster

    c = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
    try:
        c.add_node(num_cpus=1)
        c.wait_for_nodes()
        yield c
    finally:
        c.shutdown()


@pytest.mark.slow
def test_td3_on_a_two_node_ray_cluster_stopped_by_ctrl_c_then_resumed(cluster, tmp_path):
    """A run joins the cluster, is stopped by Ctrl-C (checkpoint, exit 130) and resumed there; the
    cluster stays up throughout, and neither run leaves a process behind."""
    run = tmp_path / "run"
    args = ["td3", *TINY, "collector.sync=false", f"ray.address={cluster.address}", "--out", "run"]
    proc, sid = train(args, tmp_path, env={"RLPIPE_FAULT": "evaluate@150"})
    assert proc.returncode == 130, proc.stderr[-3000:]
    assert (run / "checkpoints" / "step_0000000150").is_dir()
    assert_no_leftovers(sid)
    assert cluster.remaining_processes_alive()
    proc, sid = train(["td3", "--resume", "run"], tmp_path)
    assert_finished(run, proc)
    assert_no_leftovers(sid)
    assert cluster.remaining_processes_alive()
    assert json.loads((run / "config.json").read_text())["config"]["ray"]["address"] == cluster.address


@pytest.mark.slow
def test_default_starts_a_local_ray_instance_and_shuts_it_down(tmp_path):
    """Also with the evaluation in the background (its own process on the learner's machine)."""
    proc, sid = train(["td3", *TINY, "collector.sync=true", "ray.address=", "eval_in_background=true", "--out", "run"],
                      tmp_path)
    rows = assert_finished(tmp_path / "run", proc)
    assert [int(r["step"]) for r in rows if r["average_return"]] == [0, 150, 300]
    assert_no_leftovers(sid)


@pytest.mark.slow
def test_ctrl_c_on_a_local_ray_run_saves_exits_130_and_stops_its_ray(tmp_path):
    run = tmp_path / "run"
    proc, sid = train(["td3", *TINY, "collector.sync=false", "--out", "run"], tmp_path,
                      env={"RLPIPE_FAULT": "evaluate@150"})
    assert proc.returncode == 130, proc.stderr[-3000:]
    assert "--resume" in proc.stderr
    assert (run / "checkpoints" / "step_0000000150").is_dir()
    assert_no_leftovers(sid)


@pytest.mark.parametrize("sync", ["false", "true"])
@pytest.mark.slow
def test_a_lost_actor_is_replaced_and_the_run_finishes(tmp_path, sync):
    """kill -9 of one collector actor once the run has logged: the learner learns of it at its next
    block (WorkerLost, a WorkerFailure of the collector), the supervisor starts the Ray collectors
    again, counted in metrics.csv, and the run finishes; the local Ray instance goes with it."""
    run = tmp_path / "run"
    args = [*MODULE, "train", "td3", *TINY, f"collector.sync={sync}", "num_iterations=600", "--out", "run",
            "--no-progress"]
    proc = subprocess.Popen(args, cwd=tmp_path, text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True, env={**os.environ, **QUIET})
    try:
        deadline = time.monotonic() + 300
        while not ((run / "metrics.csv").exists() and any(r["workers_alive"] for r in metrics_rows(run))):
            assert proc.poll() is None and time.monotonic() < deadline, "the run ended or stalled before logging"
            time.sleep(0.2)
        actors = [p for p in Path("/proc").glob("[0-9]*") if _cmdline(p).startswith("ray::Collector")
                  and _session(p) == proc.pid]
        assert len(actors) == 2, [_cmdline(p) for p in actors]
        os.kill(int(actors[0].name), signal.SIGKILL)
        _, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert proc.returncode == 0, err[-3000:]
    assert "a Ray collector actor was lost" in err and "restarting the collector (restart 1 of" in err, err[-3000:]
    rows = metrics_rows(run)
    assert int(rows[-1]["step"]) == 600, rows[-1]
    logged = [r for r in rows if r["collector_restarts"]]  # log rows (evaluation rows leave it blank)
    assert logged[-1]["collector_restarts"] == "1", logged[-1]
    assert_no_leftovers(proc.pid)


def _cmdline(proc_dir: Path) -> str:
    try:
        return (proc_dir / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def _session(proc_dir: Path) -> int | None:
    try:
        return int((proc_dir / "stat").read_text().rsplit(")", 1)[1].split()[3])
    except (OSError, IndexError, ValueError):
        return None


# --- configuration, no Ray started --------------------------------------------------------------------


@pytest.mark.unit
@pytest.mark.parametrize("override, words", [
    ("collector.backend=slurm", ["collector.backend='slurm'", "'ray'"]),
    ("ray.num_cpus_per_worker=0", ["ray.num_cpus_per_worker=0", "positive"]),
])
def test_bad_ray_keys_are_one_clear_error(override, words):
    with pytest.raises(InputError) as err:
        apply_overrides(td3.preset("td3"), [override])
    for word in words:
        assert word in str(err.value)


@pytest.mark.unit
def test_sync_ray_blocks_must_split_over_the_actors():
    with pytest.raises(InputError, match="multiple of 3"):
        apply_overrides(td3.preset("td3"), ["collector.backend=ray", "collector.workers=3", "collector.sync=true",
                                            "collector.frames_per_batch=50"])


@pytest.mark.unit
def test_an_empty_ray_address_means_a_local_instance():
    assert apply_overrides(td3.preset("td3"), ["ray.address="]).ray.address == ""
    assert apply_overrides(td3.preset("td3"), ["ray.address=auto"]).ray.address == "auto"


def test_an_address_where_no_ray_listens_is_one_clear_error(tmp_path):
    proc, sid = train(["td3", *TINY, "ray.address=127.0.0.1:9", "--out", "run"], tmp_path, timeout=120)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr[-3000:]
    assert lines[0].startswith("rlpipe: error: ray.address='127.0.0.1:9': no Ray cluster answers there"), lines[0]
    assert_no_leftovers(sid)
