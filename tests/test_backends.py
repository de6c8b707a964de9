"""The collector-backend contract (``pipelines/workers/backend.py``), checked the same way on every backend:
started for N frames it gives exactly the blocks promised; weights pushed reach the workers; ``health``
names a worker killed from outside (kill -9 of its process) and ``kill`` ends them all; ``close`` leaves
no process behind. The local backend's two worker processes run in the default tier; the Ray backend's
actors, on a local Ray instance, in the slow tier.

Each backend is started twice in all (module fixtures share the runs): once collecting to its end,
once to be broken.
"""

from __future__ import annotations

import os
import signal
import time

import psutil
import pytest
import torch
from tensordict import TensorDict
from test_collectors import assert_frames_from_two_workers, descendants, left_behind, time_limit, wait_until

from rlpipe.pipelines import td3
from rlpipe.pipelines.config import apply_overrides
from rlpipe.pipelines.workers.backend import CollectorBackend, Health
from rlpipe.pipelines.workers.factory import backend_class
from rlpipe.pipelines.workers.supervision import WorkerFailure

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")

BLOCK, BLOCKS = 50, 8
PUSH_AFTER = 2  # blocks taken before the learner's weights change and are pushed
BUSY_S = 2.5  # the learner busy after each of those (an evaluation, a checkpoint): past TorchRL's 1-s hand-over timeout
EPISODE = 200  # Pendulum-v1's steps
IN_FLIGHT = 2  # blocks after a push that may predate it (one per worker)
BACKENDS = ["local", pytest.param("ray", marks=pytest.mark.slow)]


@pytest.fixture(scope="module")
def local_ray():
    """A local Ray instance in this process, as a run holds one; the backends use it and leave it up."""
    pytest.importorskip("ray", reason="Ray is not installed: `pip install -e '.[ray]'` (scripts/setup.sh does)")
    from rlpipe.pipelines.workers.ray import RayRuntime

    runtime = RayRuntime("", 3)  # two collector actors and an evaluator's
    try:
        yield
    finally:
        runtime.close()


def pipeline_for(kind: str, request) -> td3.TD3:
    """TD3 on Pendulum with two async workers on ``kind``, acting greedily (no exploration noise)."""
    if kind == "ray":
        request.getfixturevalue("local_ray")
    cfg = apply_overrides(td3.preset("td3"), [
        "actor_fc_layer_params=[32]", "critic_fc_layer_params=[32]", "exploration_noise=0",
        f"collector.backend={kind}", "collector.workers=2", "collector.sync=false",
        f"collector.frames_per_batch={BLOCK}", "num_threads=1",
    ])
    return td3.TD3(cfg)


def stale_frames(pipeline: td3.TD3, block) -> int:
    """Frames of ``block`` whose action is not what the learner's policy gives now."""
    block = block.reshape(-1)
    with torch.no_grad():
        now = pipeline.policy(TensorDict(observation=block["observation"], batch_size=block.batch_size))["action"]
    return int(((block["action"] - now).abs() > 1e-5).any(-1).sum())


@pytest.fixture(scope="module", params=BACKENDS)
def collected(request) -> dict:
    """A backend started for BLOCKS blocks; after PUSH_AFTER of them the learner's weights change and are pushed."""
    pipeline = pipeline_for(request.param, request)
    out = {"kind": request.param}
    backend = pipeline.make_backend()
    existing = {pid for pid, _ in descendants(os.getpid())}
    with time_limit(600):  # a hang fails this fixture, not the suite
        try:
            backend.start(BLOCKS * BLOCK, 0, seed=1)
            out["health"] = backend.health()
            out["blocks"] = taken_blocks = []  # each block's step counts and trajectory ids, in the order taken

            def taken():
                for block in backend:
                    taken_blocks.append(block.select("step_count", ("collector", "traj_ids")).reshape(-1).clone())
                    yield block

            blocks = taken()
            out["stale_before"] = []
            for _ in range(PUSH_AFTER):
                out["stale_before"].append(stale_frames(pipeline, next(blocks)))
                time.sleep(BUSY_S)  # the learner busy, the other worker's block waiting to be taken
            with torch.no_grad():  # an update, as far as the workers can tell
                for p in pipeline.policy.parameters():
                    p.add_(0.3 * torch.randn_like(p))
            next(blocks)  # in flight at the change: either weights (no promise either way, see below)
            backend.push_weights()
            out["stale_after"] = [stale_frames(pipeline, b) for b in blocks]
            out["metrics"] = backend.metrics()
            out["columns"] = backend.metric_columns
            out["pids"] = out["health"].pids
        finally:
            backend.close()
    wait_until(lambda: not any(_running(pid) for pid in out.get("pids", ())), 120)  # Ray reaps its actors after close
    out["left"] = left_behind(existing) if request.param == "local" else []
    out["running"] = [pid for pid in out.get("pids", ()) if _running(pid)]
    return out


def _running(pid: int) -> bool:
    try:
        return psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
    except psutil.Error:
        return False


def test_started_for_n_frames_it_gives_exactly_the_blocks_promised(collected):
    blocks = PUSH_AFTER + 1 + len(collected["stale_after"])
    assert blocks == BLOCKS, (collected["kind"], blocks)
    health = collected["health"]
    assert isinstance(health, Health) and health.total == 2 and health.failure is None, health
    assert len(set(health.pids)) == 2 and os.getpid() not in health.pids, health  # workers of their own


def test_a_learner_slower_than_its_workers_loses_no_block(collected):
    """TorchRL's MultiAsyncCollector has room in its queue for one block: a worker whose block waits there over 1 s
    collects another over it and the first is lost (rlpipe's ``AsyncCollector`` has room for every worker's; Ray's
    actors hand each block over on request). Each worker's env steps must arrive whole: its episodes' steps run
    0, 1, 2, ... with none missing, however the blocks were shared between the two workers."""
    steps = sorted(torch.cat([b["step_count"] for b in collected["blocks"]]).flatten().tolist())

    def whole(frames: int) -> list[int]:  # one worker's step counts over `frames` frames of whole episodes
        return [i % EPISODE for i in range(frames)]

    assert len(steps) == BLOCKS * BLOCK
    assert any(sorted(whole(a * BLOCK) + whole((BLOCKS - a) * BLOCK)) == steps for a in range(BLOCKS + 1)), \
        (collected["kind"], [(int(b["step_count"][0]), int(b["step_count"][-1])) for b in collected["blocks"]])


def test_each_trajectory_id_is_one_episode_of_one_worker(collected):
    """TorchRL's key for sampling by trajectory (``SliceSampler(traj_key=("collector", "traj_ids"))``): two workers'
    episodes never share an id (each Ray actor numbered its own from 1 until ``ray.StridedTrajectoryPool``)."""
    assert_frames_from_two_workers(torch.cat(collected["blocks"]))


def test_pushed_weights_reach_the_workers(collected):
    # What the contract promises is that pushed weights are acted with from the next blocks on. Before a
    # push a worker may already see a change: TorchRL's multi-process collectors put the learner's policy
    # in shared memory (its parameters are is_shared() once they start), and Ray's actors get the learner's
    # weights with each request; so how the block in flight at the change was collected is left unchecked.
    assert collected["stale_before"] == [0] * PUSH_AFTER  # the workers started with the learner's weights
    after = collected["stale_after"]
    assert after[IN_FLIGHT:] == [0] * (len(after) - IN_FLIGHT), after


def test_metrics_are_the_backends_columns(collected):
    assert set(collected["metrics"]) <= set(collected["columns"]), (collected["metrics"], collected["columns"])


def test_close_leaves_no_process_behind(collected):
    assert collected["left"] == [], collected["left"]
    assert collected["running"] == [], collected["running"]


@pytest.fixture(scope="module", params=BACKENDS)
def broken(request) -> dict:
    """A backend whose first worker is killed (kill -9 of its process) after the first block."""
    pipeline = pipeline_for(request.param, request)
    out = {"kind": request.param}
    backend = pipeline.make_backend()
    existing = {pid for pid, _ in descendants(os.getpid())}
    with time_limit(600):
        try:
            backend.start(10**6, 0, seed=2)
            blocks = iter(backend)
            next(blocks)
            out["before"] = before = backend.health()
            out["victim"] = victim = before.pids[0]
            os.kill(victim, signal.SIGKILL)
            wait_until(lambda: backend.health().failure is not None, 120)
            out["after"] = backend.health()
            try:
                for _ in range(10**6 // BLOCK):
                    next(blocks)
            except WorkerFailure as exc:
                out["raised"] = exc
            backend.kill()
            wait_until(lambda: backend.health().alive == 0, 120)
            out["killed"] = backend.health()
        finally:
            backend.close()
    wait_until(lambda: not any(_running(pid) for pid in out.get("before", Health(0)).pids), 120)
    out["running"] = [pid for pid in out.get("before", Health(0)).pids if _running(pid)]
    out["left"] = left_behind(existing) if request.param == "local" else []
    return out


def test_health_names_a_killed_worker_and_why(broken):
    after = broken["after"]
    assert broken["victim"] not in after.pids and after.total == 2, after
    failure = after.failure
    assert isinstance(failure, WorkerFailure) and failure.role == "collector"
    assert f"pid {broken['victim']}" in str(failure), str(failure)
    if broken["kind"] == "local":  # a process of ours: its exit status says how it ended
        assert "killed by SIGKILL" in str(failure), str(failure)


def test_a_killed_worker_fails_the_blocks_with_a_worker_failure(broken):
    assert isinstance(broken.get("raised"), WorkerFailure), broken.get("raised")
    assert broken["raised"].role == "collector"


def test_kill_ends_every_worker_and_close_leaves_none(broken):
    assert broken["killed"].alive == 0 and broken["killed"].failure is not None, broken["killed"]
    assert broken["running"] == [] and broken["left"] == [], (broken["running"], broken["left"])


# --- the background evaluator beside the backend's workers ---------------------------------------------


@pytest.mark.parametrize("kind", BACKENDS)
def test_the_background_evaluator_beside_the_backend_evaluates_the_snapshot_it_is_sent(kind, request):
    """Where it runs is the backend's business (a child process; a Ray actor): an evaluation asked of it
    comes back once, for the step it was asked at, and closing it leaves its worker gone."""
    from collections import deque

    from rlpipe.pipelines.workers.supervision import Watchdog

    pipeline = pipeline_for(kind, request)
    backend, pending, watchdog = backend_class(pipeline.config), deque(), Watchdog()
    held = backend.hold(pipeline.config)
    try:
        evaluator = backend.start_evaluator(pipeline.config, env_fn=pipeline.eval_env_fn, policy=pipeline.policy,
                                            pending=pending, start_timeout=300, watchdog=watchdog)
        try:
            worker = evaluator.worker_pid
            sent = evaluator.snapshot(pipeline.policy)
            evaluator.ask({"step": 1, "frames": 1, "updates": 0}, sent)
            with time_limit(600):
                (at, result, evaluated), = list(evaluator.results(block=True))
        finally:
            evaluator.close()
    finally:
        watchdog.close()
        if held is not None:
            held.close()
    assert at["step"] == 1 and not pending and evaluated is sent
    assert result["average_episode_length"] == 200 and -2000 < result["average_return"] <= 0, result  # Pendulum's
    assert worker != os.getpid() and wait_until(lambda: not _running(worker), 120)


# --- the factory ----------------------------------------------------------------------------------------


@pytest.mark.unit
def test_the_factory_picks_the_backend_the_config_names():
    from rlpipe.pipelines.workers.local import LocalBackend

    assert backend_class(td3.preset("td3")) is LocalBackend
    assert issubclass(LocalBackend, CollectorBackend) and LocalBackend.metric_columns == ()
    if pytest.importorskip("ray", reason="Ray is not installed"):
        from rlpipe.pipelines.workers.ray import METRIC_COLUMNS, RayBackend

        ray_cfg = apply_overrides(td3.preset("td3"), ["collector.backend=ray"])
        assert backend_class(ray_cfg) is RayBackend and list(RayBackend.metric_columns) == METRIC_COLUMNS

