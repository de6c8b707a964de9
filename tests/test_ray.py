"""Collectors as Ray actors (``collector.backend=ray``) on a real Ray: a two-node cluster on this machine
that a run joins, a local instance a run starts and stops, Ctrl-C on a Ray run.

Runs are real ``rlpipe train`` processes, each in its own session, so that what Ray processes a run
started can be found (and must be gone) after it exits.
"""

from __future__ import annotations

import copy
import csv
import json
import math
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from test_collectors import wait_until
from test_resume_exact import _assert_same_run, _stopped_and_resumed, _train

from rlpipe.pipelines import td3
from rlpipe.pipelines.config import apply_overrides, eval_seed
from rlpipe.pipelines.errors import InputError
from rlpipe.pipelines.workers.evaluation import evaluate

ray = pytest.importorskip("ray", reason="Ray is not installed: `pip install -e '.[ray]'` (scripts/setup.sh does)")

MODULE = [sys.executable, "-m", "rlpipe.scripts.cli"]
# td3 on Pendulum: 100 random steps, then 300 iterations; updates start at learning_starts=256
TINY = ["num_iterations=300", "initial_collect_steps=100", "eval_interval=150", "num_eval_episodes=1",
        "log_interval=100", "checkpoint_interval=150", "policy_save_interval=150", "collector.backend=ray",
        "collector.workers=2", "num_threads=1"]
FRAMES, UPDATES = 400, 400 - 256
QUIET = {"RAY_USAGE_STATS_ENABLED": "0", "RAY_DEDUP_LOGS": "0"}


def train(args, cwd: Path, env: dict | None = None, timeout: float = 400,
          watch: Callable[[int], None] | None = None) -> tuple[subprocess.CompletedProcess, int]:
    """``rlpipe train`` in a session of its own; returns the process and its session id. ``watch``,
    if given, is called with the session id every 0.2 s while the run goes on."""
    with tempfile.TemporaryFile("w+") as out_fh, tempfile.TemporaryFile("w+") as err_fh:
        proc = subprocess.Popen([*MODULE, "train", *map(str, args), "--no-progress"], cwd=cwd, text=True,
                                stdout=out_fh, stderr=err_fh, start_new_session=True,
                                env={**os.environ, **QUIET, **(env or {})})
        deadline = time.monotonic() + timeout
        while proc.poll() is None and time.monotonic() < deadline:
            if watch is not None:
                watch(proc.pid)
            time.sleep(0.2)
        timed_out = proc.poll() is None
        if timed_out:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        out_fh.seek(0)
        err_fh.seek(0)
        out, err = out_fh.read(), err_fh.read()
    if timed_out:
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


@pytest.mark.slow
def test_default_starts_a_local_ray_instance_and_a_killed_evaluator_actor_is_replaced_and_asked_again(tmp_path):
    """No ray.address: the run starts a local Ray instance and shuts it down with itself. Its evaluation in the
    background runs on a Ray actor (a Ray worker process, not a child of the learner); kill -9 of that actor's
    process right after the evaluation at 150 was sent to it: the learner sees the actor dead, starts another
    (counted in metrics.csv), which makes that evaluation; each one asked for is recorded once, and the run ends
    as usual."""
    actors: dict[int, int] = {}  # pid -> parent pid of the evaluator actors seen while the run went on

    def watch(sid: int) -> None:
        for p in Path("/proc").glob("[0-9]*"):
            if _cmdline(p).startswith("ray::EvalActor") and _session(p) == sid:
                actors.setdefault(int(p.name), _parent(p))

    proc, sid = train(["td3", *TINY, "collector.sync=true", "ray.address=", "eval_in_background=true", "--out", "run"],
                      tmp_path, env={"RLPIPE_FAULT": "evaluator_worker@150:SIGKILL"}, watch=watch)
    rows = assert_finished(tmp_path / "run", proc)
    restarts = [line for line in proc.stderr.splitlines() if "restarting the evaluator" in line]
    assert len(restarts) == 1 and "the evaluator actor (pid" in restarts[0] and "restart 1 of" in restarts[0], \
        proc.stderr[-3000:]
    evaluated = [r for r in rows if r["average_return"]]
    assert [int(r["step"]) for r in evaluated] == [0, 150, 300]  # 0 in the learner, before training; the rest on Ray
    assert all(math.isfinite(float(r["average_return"])) and float(r["average_episode_length"]) == 200
               for r in evaluated), evaluated
    assert len(actors) == 2, actors  # the one killed and the one that replaced it
    assert sid not in actors.values(), actors  # Ray's workers, not the learner's child processes
    assert [int(r["evaluator_restarts"]) for r in rows if r["evaluator_restarts"]][-1] == 1, rows
    assert_no_leftovers(sid)


@pytest.mark.slow
def test_ctrl_c_with_an_evaluation_on_the_ray_actor_saves_it_as_owed(tmp_path):
    """Ctrl-C to the whole process group of a run on a local Ray instance, just after the evaluation at 150 was
    sent to the actor: exit 130 saying how to resume, and the local Ray stopped with the run; the actor, deaf
    to it, is not lost (no restart); the checkpoint owes that evaluation unless it was back in time, and
    --resume records it once."""
    run = tmp_path / "run"
    proc, sid = train(["td3", *TINY, "collector.sync=false", "eval_in_background=true", "--out", "run"], tmp_path,
                      env={"RLPIPE_FAULT": "collected@150"})
    assert proc.returncode == 130, proc.stderr[-3000:]
    assert "--resume" in proc.stderr
    assert "restarting" not in proc.stderr and "died" not in proc.stderr, proc.stderr[-3000:]
    assert (run / "checkpoints" / "step_0000000150").is_dir()
    assert_no_leftovers(sid)
    proc, sid = train(["td3", "--resume", "run"], tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    # (not assert_finished: a log row the stop left owed is written before the resumed run's collectors
    # start, so it has no workers_alive)
    assert json.loads((run / "summary.json").read_text())["frames"] == FRAMES
    assert [int(r["step"]) for r in metrics_rows(run) if r["average_return"]] == [0, 150, 300]
    assert_no_leftovers(sid)


# collector.sync=false: the learner finds the actor lost at its next block (test_ray_faults' removed node
# takes the weight push's path, sync=true)
@pytest.mark.parametrize("sync", ["false"])
@pytest.mark.slow
def test_a_lost_actor_is_replaced_and_the_run_finishes(tmp_path, sync):
    """kill -9 of one collector actor once the run has logged: the learner learns of it at its next
    block (a WorkerFailure of the collector), the supervisor starts the Ray collectors
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
        actors = [p for p in Path("/proc").glob("[0-9]*") if _is_collector_actor(p)
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


RESUME_ARGS = ["td3", "num_iterations=200", "initial_collect_steps=100", "eval_interval=100", "num_eval_episodes=1",
               "log_interval=50", "checkpoint_interval=100", "collector.backend=ray", "collector.workers=2",
               "collector.sync=true", "eval_in_background=false", "batch_size=64", "num_threads=1"]


@pytest.mark.slow
def test_ray_collectors_on_a_two_node_cluster_stopped_by_ctrl_c_and_resumed_there_equal_the_uninterrupted_run(
        ray_cluster, tmp_path):
    """A run joins the cluster, is stopped by Ctrl-C (a checkpoint, no summary) and resumed there (the address kept in
    its config); it equals the uninterrupted run (tests/test_resume_exact.py does the processes): the actors'
    generators are seeded (TorchRL's Ray set_seed seeds the env alone) and their envs' episodes go through
    checkpoints as the processes' do. The cluster stays up throughout and keeps no actor of the runs."""
    args = [*RESUME_ARGS, f"ray.address={ray_cluster.address}"]
    reference = tmp_path / "uninterrupted" / "run"
    reference.parent.mkdir()
    done = _train(args, reference)
    assert done.returncode == 0, done.stderr[-3000:]
    run = _stopped_and_resumed(args, "SIGINT", 150, tmp_path)
    _assert_same_run(reference, run)
    assert json.loads((run / "config.json").read_text())["config"]["ray"]["address"] == ray_cluster.address
    assert ray_cluster.remaining_processes_alive()
    def actors() -> list[str]:
        return [_cmdline(p) for p in Path("/proc").glob("[0-9]*") if _is_collector_actor(p)]

    assert wait_until(lambda: not actors(), 60), actors()  # the runs' actors end with their drivers (not detached)


def _is_collector_actor(proc_dir: Path) -> bool:
    """A Ray collector actor's process: Ray titles it ``ray::CLASS[.method]``, the class being the collector
    class the backend gives TorchRL's RayCollector (``WorkerSnapshotCollector``) or TorchRL's ``Collector``."""
    return re.match(r"ray::\w*Collector\b", _cmdline(proc_dir)) is not None


def _cmdline(proc_dir: Path) -> str:
    try:
        return (proc_dir / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def _parent(proc_dir: Path) -> int | None:
    try:
        return int((proc_dir / "stat").read_text().rsplit(")", 1)[1].split()[1])
    except (OSError, IndexError, ValueError):
        return None


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
    """Checked before the run writes anything: a refused command leaves nothing behind."""
    proc, sid = train(["td3", *TINY, "ray.address=127.0.0.1:9", "--out", "run"], tmp_path, timeout=120)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr[-3000:]
    assert lines[0].startswith("rlpipe: error: ray.address='127.0.0.1:9': no Ray cluster answers there"), lines[0]
    assert list(tmp_path.iterdir()) == []  # no run directory (--out run), nor a default one under runs/
    assert_no_leftovers(sid)


# --- the evaluator's Ray actor, driven from this process -----------------------------------------------


@pytest.fixture(scope="module")
def local_ray():
    """A local Ray instance in this process, as a run holds one (``ray_eval.hold_ray``)."""
    from rlpipe.pipelines.workers.ray import RayRuntime

    runtime = RayRuntime("", 2)
    try:
        yield
    finally:
        runtime.close()


def _ray_eval_setup():
    from rlpipe.pipelines.workers.ray_eval import RayEvaluator

    cfg = apply_overrides(td3.preset("td3"), ["actor_fc_layer_params=[32]", "critic_fc_layer_params=[32]",
                                              "collector.backend=ray", "collector.workers=1"])
    return cfg, td3.TD3(cfg), RayEvaluator


@pytest.mark.slow
def test_an_evaluation_on_the_ray_actor_is_the_one_the_learner_makes(local_ray):
    """The same weights on the same seed (the eval env's, seed + 10000) give the same episodes on the
    actor as in the learner's process; the actor is Ray's worker, not a child of the learner."""
    import psutil

    cfg, pipeline, RayEvaluator = _ray_eval_setup()
    pending = deque()
    evaluator = RayEvaluator(pipeline.eval_env_fn, pipeline.policy, 3, pending, config=cfg)
    try:
        assert psutil.Process(evaluator.worker_pid).ppid() != os.getpid()
        weights = evaluator.snapshot(pipeline.policy)
        evaluator.ask({"step": 7, "frames": 7, "updates": 0}, weights)
        with torch.no_grad():  # the learner goes on: the snapshot is what is evaluated
            for p in pipeline.policy.parameters():
                p.add_(0.5)
        (at, result, evaluated), = list(evaluator.results(block=True))
    finally:
        evaluator.close()
    assert evaluated is weights  # what keep_best keeps when this evaluation is the best
    policy = copy.deepcopy(pipeline.policy)
    weights.to_module(policy)
    # each evaluation's episodes come from the run's seed and that evaluation's step (issue 23)
    pipeline.eval_env.set_seed(eval_seed(cfg.seed, 7))
    local = evaluate(pipeline.eval_env, policy, 3)
    assert at["step"] == 7 and not pending
    assert result["returns"] == pytest.approx(local["returns"], rel=1e-6)
    assert result["average_episode_length"] == local["average_episode_length"] == 200


@pytest.mark.slow
def test_a_dead_or_late_evaluator_actor_is_a_worker_failure(local_ray):
    """kill -9 of the actor with an evaluation in flight: a WorkerFailure (not a wait until eval_timeout);
    an evaluation not back within eval_timeout: a WorkerFailure; close() leaves no actor process."""
    import psutil

    from rlpipe.pipelines.workers.supervision import WorkerFailure

    cfg, pipeline, RayEvaluator = _ray_eval_setup()
    pending = deque()
    long = 50  # episodes of 200 steps: seconds of work
    evaluator = RayEvaluator(pipeline.eval_env_fn, pipeline.policy, long, pending, config=cfg, timeout=300)
    try:
        evaluator.ask({"step": 1, "frames": 1, "updates": 0}, evaluator.snapshot(pipeline.policy))
        os.kill(evaluator.worker_pid, signal.SIGKILL)
        with pytest.raises(WorkerFailure, match=r"the evaluator actor \(pid \d+\) died") as failure:
            list(evaluator.results(block=True))
        assert failure.value.role == "evaluator"
    finally:
        evaluator.close()
    assert len(pending) == 1  # still owed: the next evaluator asks again
    evaluator = RayEvaluator(pipeline.eval_env_fn, pipeline.policy, long, pending, config=cfg, timeout=0.5)
    worker = psutil.Process(evaluator.worker_pid)
    # Frozen before it is asked (results() sends the request): its evaluation cannot be back within
    # eval_timeout, however fast evaluations get (50 episodes took "seconds" until they were played on the
    # gymnasium env directly, ~0.6 s now, and the test then raced the timeout).
    worker.suspend()
    try:
        with pytest.raises(WorkerFailure, match=r"evaluation at step 1 was not back within eval_timeout=0.5 s"):
            list(evaluator.results(block=True))
    finally:
        evaluator.close()
    assert len(pending) == 1
    deadline = time.monotonic() + 30  # Ray reaps the killed worker
    while worker.is_running() and worker.status() != psutil.STATUS_ZOMBIE and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not worker.is_running() or worker.status() == psutil.STATUS_ZOMBIE
