"""Ray collectors against faults, on a real Ray: a node of a cluster removed mid-run, the learner
killed (kill -9, also inside a checkpoint's write) and resumed, and what Ray processes outlive a killed
learner; then SAC learning Pendulum with Ray collectors. (A stop signal on a cluster run and its resume:
tests/test_ray.py.)

Runs are real ``rlpipe train`` processes, each in a session of its own: what a run's local Ray
instance started is found by that session (other Ray instances may run on this machine at the
same time), and a joined cluster's actors by their node's raylet (the cluster, conftest's ``ray_cluster``, is
this file's own, used by its last test, which runs after the local-Ray ones).
Faults come at exact points (``RLPIPE_FAULT``): a node is removed while the learner holds itself
stopped (SIGSTOP) right after a block, never after a sleep.
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
from test_ray import _is_collector_actor  # Ray's title for a collector actor's process

from rlpipe.pipelines import sac
from rlpipe.pipelines.artifacts import checkpoint as ckpt
from rlpipe.pipelines.config import apply_overrides

ray = pytest.importorskip("ray", reason="Ray is not installed: `pip install -e '.[ray]'` (scripts/setup.sh does)")

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")

MODULE = [sys.executable, "-m", "rlpipe.scripts.cli"]
QUIET = {"RAY_USAGE_STATS_ENABLED": "0", "RAY_DEDUP_LOGS": "0", "PYTHONFAULTHANDLER": "1"}
N = 300
# td3 on Pendulum: 100 random frames, then 300 iterations; blocks of 50 frames end at iterations 0, 50, 100, ...
# (updates start at learning_starts=256 frames, so a run makes FRAMES - 256 of them)
RUN = ["td3", f"num_iterations={N}", "initial_collect_steps=100", "eval_interval=150", "num_eval_episodes=1",
       "log_interval=50", "checkpoint_interval=100", "policy_save_interval=150", "collector.backend=ray",
       "num_threads=1", "--no-progress"]
FRAMES, UPDATES = N + 100, N + 100 - 256
DEADLINE_S = 400  # generous: the machine is shared; nothing waits on time, only on events


# --- processes -----------------------------------------------------------------------------------------


def start(args, cwd: Path, fault: str = "") -> subprocess.Popen:
    """``rlpipe train ARGS`` in a session of its own (its id is its pid), with ``RLPIPE_FAULT=fault``."""
    return subprocess.Popen([*MODULE, "train", *map(str, args)], cwd=cwd, text=True, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, start_new_session=True,
                            env={**os.environ, **QUIET, "RLPIPE_FAULT": fault})


def finish(proc: subprocess.Popen, timeout: float = DEADLINE_S) -> tuple[int, str]:
    """Exit status and stderr; a run still going after ``timeout`` is a hang: dumped and killed."""
    try:
        _, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.kill(proc.pid, signal.SIGABRT)  # faulthandler prints where it waits
        _, err = proc.communicate(timeout=30)
        _kill_session(proc.pid)
        pytest.fail(f"the run hung (killed after {timeout} s):\n{err[-5000:]}")
    return proc.returncode, err


def train(args, cwd: Path, fault: str = "") -> tuple[int, str, int]:
    proc = start(args, cwd, fault)
    code, err = finish(proc)
    return code, err, proc.pid


def wait_stopped(proc: subprocess.Popen) -> None:
    """Until ``proc`` is stopped (SIGSTOP from its fault point): its state in /proc says so."""
    deadline = time.monotonic() + DEADLINE_S
    while _stat(Path(f"/proc/{proc.pid}"))[0] != "T":
        assert proc.poll() is None, f"the run ended before its fault point: {proc.communicate()[1][-3000:]}"
        assert time.monotonic() < deadline, "the run did not reach its fault point"
        time.sleep(0.05)


def poll_until(condition, what: str, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, what
        time.sleep(0.2)


def session_processes(sid: int) -> list[str]:
    """Command lines of the live processes in session ``sid`` (a run's, and its local Ray's)."""
    return [_cmdline(p) for p in _procs() if _stat(p)[4] == sid and _stat(p)[0] != "Z"]


def assert_no_leftovers(sid: int, timeout: float = 60.0) -> None:
    poll_until(lambda: not session_processes(sid), f"processes of the run are still there: {session_processes(sid)}",
               timeout)


def collector_actors(cluster) -> dict[int, object]:
    """The cluster's collector actor processes (pid -> node): each is a child of its node's raylet."""
    raylets = {node.all_processes["raylet"][0].process.pid: node for node in cluster.list_all_nodes()
               if node.all_processes.get("raylet")}
    found = {}
    for p in _procs():
        stat = _stat(p)
        if stat[0] != "Z" and stat[1] in raylets and _is_collector_actor(p):
            found[int(p.name)] = raylets[stat[1]]
    return found


def _procs():
    return Path("/proc").glob("[0-9]*")


def _cmdline(proc_dir: Path) -> str:
    try:
        return (proc_dir / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace").strip()
    except OSError:
        return ""


def _stat(proc_dir: Path) -> tuple:
    """(state, ppid, pgrp, session id) as /proc/PID/stat says, padded: ``[4]`` is the session."""
    try:
        fields = (proc_dir / "stat").read_text().rsplit(")", 1)[1].split()
        return fields[0], int(fields[1]), int(fields[2]), None, int(fields[3])
    except (OSError, IndexError, ValueError):
        return "", None, None, None, None


def _kill_session(sid: int) -> None:
    for p in _procs():
        if _stat(p)[4] == sid:
            try:
                os.kill(int(p.name), signal.SIGKILL)
            except OSError:
                pass


# --- the run directory ---------------------------------------------------------------------------------


def metrics_rows(run: Path) -> list[dict[str, str]]:
    with (run / "metrics.csv").open(newline="") as fh:
        return list(csv.DictReader(fh))


def assert_whole_run(run: Path) -> list[dict[str, str]]:
    """A finished run: its counters at their ends, every log and evaluation row once and in order,
    every row whole, every checkpoint loadable, nothing half-written left."""
    summary = json.loads((run / "summary.json").read_text())
    assert (summary["iterations"], summary["frames"], summary["updates"]) == (N, FRAMES, UPDATES), summary
    rows = metrics_rows(run)
    assert all(None not in r.values() and None not in r for r in rows), rows
    assert [int(r["step"]) for r in rows if r["steps_per_s"]] == list(range(50, N + 1, 50))
    assert [int(r["step"]) for r in rows if r["average_return"]] == [0, 150, 300]
    steps = sorted(int(p.name.split("_")[1]) for p in (run / "checkpoints").glob("step_*"))
    assert steps and steps[-1] == N, steps
    for step in steps:
        state = ckpt.load_checkpoint(run / "checkpoints" / f"step_{step:010d}", "td3", "Pendulum-v1")
        assert state["counters"]["iteration"] == step
    assert ckpt.latest_checkpoint(run / "checkpoints").name == f"step_{N:010d}"
    assert sorted(str(p.relative_to(run)) for p in run.rglob(".*") if p.name != ".mpl") == []
    assert (run / "policy" / "policy.json").exists()
    return rows


def log_rows(rows):
    return [r for r in rows if r["steps_per_s"]]


# --- clusters ------------------------------------------------------------------------------------------


@pytest.fixture
def spare_nodes():
    """A cluster whose head takes no actor (no CPU) and two worker nodes of one CPU each: a collector
    actor lands on one of them, and when that node goes the other can take its replacement."""
    from ray.cluster_utils import Cluster

    c = Cluster(initialize_head=True, head_node_args={"num_cpus": 0, "include_dashboard": False})
    try:
        nodes = [c.add_node(num_cpus=1) for _ in range(2)]
        c.wait_for_nodes()
        yield c, nodes
    finally:
        c.shutdown()


# --- a node lost -----------------------------------------------------------------------------------------


# collector.sync=true here (the learner finds the actor lost at its weight push); test_ray's killed actor
# takes the other path (sync=false: found at the next block)
@pytest.mark.parametrize("sync", ["true"])
@pytest.mark.slow
def test_a_node_removed_mid_run_its_actor_is_started_on_another_and_the_run_finishes(spare_nodes, tmp_path, sync):
    """The learner holds itself (SIGSTOP) right after the block of iteration 100; the node holding its
    collector actor is removed (its raylet and the actor's process with it); the learner goes on,
    finds the actor lost at its next block or weight push, and the supervisor starts the collector
    again on the node left. The run finishes, whole, with the restart counted."""
    c, _ = spare_nodes
    run = tmp_path / "run"
    proc = start([*RUN, "collector.workers=1", f"collector.sync={sync}", f"ray.address={c.address}",
                  "--out", "run"], tmp_path, fault="collected@100:SIGSTOP:self")
    try:
        wait_stopped(proc)
        actors = collector_actors(c)
        assert len(actors) == 1, actors
        ((pid, lost_node),) = actors.items()
        c.remove_node(lost_node)
        poll_until(lambda: _stat(Path(f"/proc/{pid}"))[0] in ("", "Z"), "the removed node's actor still runs")
        os.kill(proc.pid, signal.SIGCONT)
        code, err = finish(proc)
    finally:
        if proc.poll() is None:
            _kill_session(proc.pid)
            proc.communicate()
    assert code == 0, err[-3000:]
    assert "a Ray collector actor was lost" in err and "restarting the collector (restart 1 of" in err, err[-3000:]
    rows = assert_whole_run(run)
    logged = log_rows(rows)
    assert [r["collector_restarts"] for r in logged] == ["0", "0"] + ["1"] * 4, logged
    assert all(r["workers_alive"] == "1" for r in logged)
    assert_no_leftovers(proc.pid)
    poll_until(lambda: not collector_actors(c), f"the run's actors live on: {collector_actors(c)}")
    assert c.remaining_processes_alive()


@pytest.mark.slow
def test_an_actor_that_stops_answering_is_killed_at_the_deadline_and_replaced(tmp_path):
    """A collector actor frozen (SIGSTOP) while the learner holds itself after the block of iteration
    100: the learner's next block is not back within collector.timeout, so the actor is killed (the
    supervisor's deadline, ``RayBackend.kill``) and the collector started again."""
    run = tmp_path / "run"
    proc = start([*RUN, "collector.workers=1", "collector.sync=true", "collector.timeout=10", "--out", "run"],
                 tmp_path, fault="collected@100:SIGSTOP:self")
    try:
        wait_stopped(proc)
        actors = [int(p.name) for p in _procs() if _stat(p)[4] == proc.pid and _is_collector_actor(p)]
        assert len(actors) == 1, actors
        os.kill(actors[0], signal.SIGSTOP)
        os.kill(proc.pid, signal.SIGCONT)
        code, err = finish(proc)
    finally:
        if proc.poll() is None:
            _kill_session(proc.pid)
            proc.communicate()
    assert code == 0, err[-3000:]
    assert "a block of env steps was not back within 10 s; restarting the collector (restart 1 of" in err, err[-3000:]
    logged = log_rows(assert_whole_run(run))
    assert [r["collector_restarts"] for r in logged] == ["0", "0"] + ["1"] * 4, logged
    assert_no_leftovers(proc.pid)


# --- kill -9 of the learner, then --resume ----------------------------------------------------------------


@pytest.mark.slow
def test_kill_9_of_a_learner_with_a_local_ray_leaves_no_ray_process_and_resumes(tmp_path):
    """A learner that started its own Ray instance (ray.address empty), kill -9'd between two
    checkpoints: Ray's processes go with it, none stays behind. (Ray starts its GCS and raylet
    fate-sharing with the driver that started them: the kernel kills them with it. The actors see
    their raylet gone and exit within seconds; Ray's dashboard and runtime-env agents see it within
    2 s, then try to tell the dead GCS for 60 s, a timeout fixed in Ray 2.60, and exit.) The run
    resumes from its last checkpoint (one interval lost at most), whole, at once: with a new local
    Ray beside the old one's agents while they wait out their timeout."""
    run = tmp_path / "run"
    code, err, killed_sid = train([*RUN, "collector.workers=2", "collector.sync=false", "--out", "run"], tmp_path,
                                  fault="collected@250:SIGKILL:self")
    assert code == -signal.SIGKILL, err[-3000:]
    assert ckpt.latest_checkpoint(run / "checkpoints").name == "step_0000000200"
    assert int(log_rows(metrics_rows(run))[-1]["step"]) == 250  # rows past the checkpoint, dropped on resume

    code, err, sid = train(["td3", "--resume", "run", "--no-progress"], tmp_path)
    assert code == 0, err[-3000:]
    assert_whole_run(run)
    assert_no_leftovers(sid)
    assert_no_leftovers(killed_sid, timeout=180)


# --- it learns, with Ray collectors -----------------------------------------------------------------------

# The sac-pendulum preset to its target (-200), with the env stepped by one Ray actor (a local Ray instance) that
# gets the learner's weights before each block (collector.sync=true: the run's arithmetic does not depend on
# timing, so it is the same run every time on one CPU). Seen on this 2-core machine (seed 0, evaluations every
# 500): -1371, -921, -408, -87 (target), then -133 on its recheck: 2,200 iterations, ~60 s with Ray's start.
SAC_LEARN = ["seed=0", "target_return=-200", "eval_interval=500", "num_iterations=4000", "log_interval=500",
             "collector.backend=ray", "collector.workers=1", "collector.sync=true", "ray.address="]


@pytest.mark.slow
def test_learns_pendulum_with_ray_collectors(run_dir):
    result = sac.SAC(apply_overrides(sac.preset("sac-pendulum"), SAC_LEARN)).train(run_dir, progress=False)
    returns = [e["average_return"] for e in result.evaluations]
    print(f"sac on Ray: {returns}")
    assert returns[0] < -900, returns  # the first evaluation, 500 updates in: far from swinging up
    assert result.summary["stopped_because"] == "target", f"SAC did not learn Pendulum-v1 on Ray: {returns}"
    logged = [r for r in result.metrics if r.get("workers_alive")]
    assert logged and all(r["workers_alive"] == "1" and r["collector_restarts"] == "0" for r in logged), logged


# --- on conftest's ray_cluster: kill -9, then --resume -----------------------------------------------------------


@pytest.mark.slow
def test_kill_9_of_a_learner_inside_a_checkpoint_write_on_a_cluster_ends_its_actors_and_resumes(ray_cluster,
                                                                                                 tmp_path):
    """kill -9 of a learner that joined a cluster, halfway through writing the checkpoint of iteration
    200: Ray ends the dead driver's actors (they are not detached), the cluster stays up, and
    ``--resume`` there goes on from the checkpoint before (100) and finishes, whole: no corrupt file,
    no row lost or doubled."""
    run = tmp_path / "run"
    code, err, sid = train([*RUN, "collector.workers=2", "collector.sync=false", f"ray.address={ray_cluster.address}",
                            "--out", "run"], tmp_path, fault="checkpoint.write@200:SIGKILL:self")
    assert code == -signal.SIGKILL, err[-3000:]
    assert [p.name.split("-")[0] for p in (run / "checkpoints").glob(".tmp-*")] == [".tmp"], "the kill left no trace?"
    assert ckpt.latest_checkpoint(run / "checkpoints").name == "step_0000000100"
    assert_no_leftovers(sid)
    poll_until(lambda: not collector_actors(ray_cluster),
               f"the dead learner's actors live on: {collector_actors(ray_cluster)}", timeout=120)
    assert ray_cluster.remaining_processes_alive()

    code, err, sid = train(["td3", "--resume", "run", "--no-progress"], tmp_path)
    assert code == 0, err[-3000:]
    assert_whole_run(run)
    assert_no_leftovers(sid)
    assert ray_cluster.remaining_processes_alive()
