"""Collectors as Ray actors (``collector.backend=ray``): TorchRL's ``RayCollector`` and its weight sync.

Each of ``collector.workers`` actors runs a TorchRL ``Collector`` on its own env, placed by Ray on
whichever node has ``ray.num_cpus_per_worker`` CPUs free. The run starts a local Ray instance
(``ray.address`` empty) and shuts it down at its end, or joins a running cluster (``auto`` or
``HOST:PORT``) and leaves it up.

Weights go out through TorchRL's ``RayWeightSyncScheme`` (tensors over torch.distributed's Gloo,
Ray for the signalling). ``RayCollector`` sends the learner's weights to a worker each time it asks
it for a block (``update_after_each_batch``): the worker is idle then, so a push never waits for a
block in flight, and in async mode the others keep stepping. Each publication is stamped with the
learner's update count as its version, and every actor's env carries TorchRL's ``PolicyVersion``
transform (``track_policy_version``), so each collected frame says which weights collected it;
``metrics()`` turns that into staleness, in updates, for the log rows.

``RayBackend`` is this module's ``backend.CollectorBackend``. A lost actor (its process or node gone)
surfaces as a ``WorkerFailure`` of the collector when its block is asked for, whichever of Ray's
errors says so (``_lost_errors``); ``health()`` reads Ray's actor table (live actors' pids, a dead
one's cause), and ``kill()`` ends a wait on them that ran past its deadline. Restarting lost workers
is the supervisor's job (``supervision.SupervisedCollector``), not this module's.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Iterator
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.collectors.utils import _TrajectoryPool  # TorchRL 0.14's; StridedTrajectoryPool says why

from rlpipe.pipelines.compat.torchrl import COLLECTOR_KWARGS, ray_weight_sync_deadline, set_model_version
from rlpipe.pipelines.config import TrainConfig
from rlpipe.pipelines.errors import InputError
from rlpipe.pipelines.workers.backend import CollectorBackend, Health
from rlpipe.pipelines.workers.ray_runtime import RayRuntime, check_address, check_cpus
from rlpipe.pipelines.workers.snapshot_collector import SNAPSHOT, WorkerSnapshotCollector, why_not_exact
from rlpipe.pipelines.workers.supervision import MIN_START_TIMEOUT_S, WorkerFailure, first_line, start_timeout

__all__ = ["METRIC_COLUMNS", "RayBackend", "RayRuntime", "check_address", "check_cpus"]

METRIC_COLUMNS = ["workers_alive", "weight_version", "weight_staleness"]
"""what ``RayBackend.metrics`` adds to each log row of metrics.csv"""


def _lost_errors() -> tuple[type[BaseException], ...]:
    """Ray's errors that mean a collector actor, its node or the object it owed is gone: each is a
    ``WorkerFailure`` of the collector. Which one comes depends on where the loss is seen: a killed
    actor's block raises ``ActorDiedError``; a node gone, ``ActorDiedError`` (node died), ``ActorUnavailableError`` while
    Ray still tries to reach it, ``NodeDiedError``, ``ObjectLostError`` (``OwnerDiedError``, ...) for
    a block stored there; a wait with a deadline, ``GetTimeoutError``."""
    from ray import exceptions as e

    return (e.RayActorError, e.NodeDiedError, e.ObjectLostError, e.WorkerCrashedError, e.LocalRayletDiedError,
            e.GetTimeoutError, e.ActorUnschedulableError)


class RayBackend(CollectorBackend):
    """TorchRL's ``RayCollector`` as a ``CollectorBackend``, with the run's Ray and version stamps.

    Its blocks' frames each carry ``("next", "policy_version")``: the learner's update count whose
    weights collected it. ``health`` reads Ray's actor table (each live actor's pid on its node; a dead
    one's death cause); ``kill`` kills the actors; ``close`` kills them and lets go of Ray. A lost actor
    is a ``WorkerFailure`` of the collector from the blocks. Iterable, ``update_policy_weights_`` and
    ``shutdown`` as a TorchRL collector is, for a loop of one's own (``OffPolicyPipeline.make_collector``).
    """

    metric_columns = tuple(METRIC_COLUMNS)

    @classmethod
    def preflight(cls, config: TrainConfig) -> None:
        check_address(config.ray.address)  # no Ray at ray.address: one line, and nothing written

    @classmethod
    def hold(cls, config: TrainConfig) -> RayRuntime:
        from rlpipe.pipelines.workers.ray_eval import hold_ray

        return hold_ray(config)

    @classmethod
    def starts_processes(cls, config: TrainConfig) -> bool:
        return False  # its workers and its evaluator are Ray's actors

    @classmethod
    def start_evaluator(cls, config: TrainConfig, *, env_fn, policy, pending, start_timeout: float, watchdog):
        """On a Ray actor (``ray_eval.RayEvaluator``), on the Ray the run holds (``hold``); Ray's own
        deadline on placing it is ``start_timeout``."""
        from rlpipe.pipelines.workers.ray_eval import RayEvaluator

        return RayEvaluator(env_fn, policy, config.num_eval_episodes, pending, config=config,
                            timeout=config.eval_timeout, start_timeout=start_timeout)

    def _start(self, total_frames: int, init_random_frames: int) -> None:
        import ray
        from torchrl.weight_update import RayWeightSyncScheme

        if self.env_fn is None:
            raise InputError("collector.backend=ray: pass env as a function that makes the env (Ray actors make their own)")
        c, r = self.config.collector, self.config.ray
        self.num_workers = c.workers
        self._staleness_sum, self._staleness_frames = 0.0, 0
        self.runtime = RayRuntime(r.address, c.workers * r.num_cpus_per_worker)
        try:
            check_cpus(ray, self.config)
            ray_weight_sync_deadline(start_timeout(c.timeout))
            self.scheme = RayWeightSyncScheme()
            # The version the first weights carry (a resumed run's policy is already trained).
            set_model_version(self.scheme, self.learner_version())
            self._ray_collector = _ray_collector(self.env_fn, self.policy, self.config, total_frames,
                                                 init_random_frames, self.scheme)
            self._actors = list(self._ray_collector.remote_collectors)
            self._wait_placed(ray, start_timeout(c.timeout))
            self._ray_collector.update_policy_weights_()  # connects the weight sync (Gloo group) before collecting
        except _lost_errors() as exc:  # an actor (or its node) lost while starting: a restart may do
            self.runtime.close()
            raise _lost(f"a Ray collector actor was lost while starting ({first_line(exc)})") from exc
        except BaseException:
            self.runtime.close()
            raise

    def _wait_placed(self, ray, timeout: float) -> None:
        """Until Ray has placed and started every actor, at most ``timeout`` seconds: a cluster short of
        CPUs (a node gone since they were counted) would hold an actor pending for good."""
        refs = [a.__ray_ready__.remote() for a in self._actors]
        ready, _ = ray.wait(refs, num_returns=len(refs), timeout=timeout)
        if len(ready) < len(refs):
            free = ray.available_resources().get("CPU", 0.0)
            raise _lost(f"Ray placed {len(ready)} of {len(refs)} collector actors within {timeout:g} s "
                        f"(collector.timeout, at least {MIN_START_TIMEOUT_S:g}; {free:g} CPUs free in the "
                        "cluster); expected fewer collector.workers, a smaller ray.num_cpus_per_worker, "
                        "or more nodes")
        ray.get(ready)  # an actor that failed to start raises here, with its own error

    def _seed(self, seed: int) -> None:
        self.set_seed(seed)

    def set_seed(self, seed: int, static_seed: bool = False) -> int:
        """As a TorchRL collector's (a loop of one's own)."""
        try:
            return self._ray_collector.set_seed(seed, static_seed)
        except _lost_errors() as exc:
            raise _lost(f"a Ray collector actor was lost while starting ({first_line(exc)})") from exc

    def snapshot(self) -> dict[str, Any] | None:
        if not self.config.collector.sync:  # async actors are mid-block whenever the learner looks
            return None
        try:
            states = self._ray_collector.state_dict()
        except _lost_errors() as exc:
            raise _lost(f"a Ray collector actor was lost ({first_line(exc)})") from exc
        return {"workers": [state[SNAPSHOT] for state in states]}

    def _restore(self, snapshot: dict[str, Any]) -> bool:
        workers = snapshot["workers"]
        if not self.config.collector.sync or len(workers) != len(self._actors):
            return False
        try:
            self._ray_collector.load_state_dict([{SNAPSHOT: w} for w in workers])
        except _lost_errors() as exc:
            raise _lost(f"a Ray collector actor was lost while starting ({first_line(exc)})") from exc
        return why_not_exact(self.env) is None and all(bool(w["capturable"]) for w in workers)

    def blocks(self) -> Iterator[TensorDictBase]:
        lost_errors = _lost_errors()
        blocks = iter(self._ray_collector)
        while True:
            # The weights the collector sends with its next request are the learner's as of now.
            set_model_version(self.scheme, self.learner_version())
            try:
                batch = next(blocks)
            except StopIteration:
                return
            except Exception as exc:
                # Ray says so (the block of a dead actor), or the weight push finds its peer gone first
                # (Gloo's "Connection closed by peer"): then Ray's actor table says so within seconds.
                if not (isinstance(exc, lost_errors) or self._some_lost(within_s=10.0)):
                    raise
                raise _lost(f"a Ray collector actor was lost ({first_line(exc)}); "
                            f"{self.alive_workers()} of {self.num_workers} alive") from exc
            self._note_versions(batch)
            yield batch

    def push_weights(self) -> None:
        """Nothing to do here: each worker gets the learner's weights when it is asked for its next block."""

    update_policy_weights_ = push_weights

    def close(self) -> None:
        """Stop the actors (errors of dead ones are not raised), then a local Ray instance this run started."""
        self.shutdown(raise_on_error=False)

    def shutdown(self, timeout: float | None = None, raise_on_error: bool = True) -> None:
        """As a TorchRL collector's: stop the actors, then a local Ray instance this run started."""
        collector, self._ray_collector = getattr(self, "_ray_collector", None), None
        if collector is None:
            return
        try:
            collector.shutdown(timeout=timeout)
        except Exception:
            if raise_on_error:
                raise
        finally:
            self.runtime.close()

    # --- for the log rows and a supervisor --------------------------------------------------------

    def kill(self) -> None:
        import ray

        for actor in getattr(self, "_actors", ()):
            try:
                ray.kill(actor, no_restart=True)
            except Exception:  # gone already, or Ray itself is: the wait ends either way
                pass

    def health(self) -> Health:
        """From Ray's actor table (GCS), so a busy actor counts as alive. A ping (``__ray_ready__``)
        would queue behind a block in flight, and the public state API (ray.util.state) needs the
        dashboard, which the run does not start."""
        pids, failure = [], None
        for i, info in enumerate(map(_actor_info, getattr(self, "_actors", ()))):
            if info.get("State") in ("ALIVE", 2):
                pids.append(int(info.get("Pid") or 0))
            elif failure is None:
                cause = _death_cause(info)
                failure = WorkerFailure(self.role, f"collector worker {i} (Ray actor, pid {info.get('Pid') or '?'}) "
                                                   f"is {str(info.get('State') or 'gone').lower()}"
                                                   f"{': ' + cause if cause else ''}")
        return Health(self.num_workers if self.started else 0, tuple(pids), failure)

    def alive_workers(self) -> int:
        """Collector actors Ray holds alive now."""
        return self.health().alive

    def _some_lost(self, within_s: float) -> bool:
        deadline = time.monotonic() + within_s
        while self.alive_workers() == self.num_workers:
            if time.monotonic() > deadline:
                return False
            time.sleep(0.2)
        return True

    def _note_versions(self, batch: TensorDictBase) -> None:
        versions = batch.get(("next", "policy_version"), None)
        if versions is None:
            return
        staleness = self.learner_version() - versions.reshape(-1).to(torch.float64)
        self._staleness_sum += float(staleness.sum())
        self._staleness_frames += staleness.numel()

    def metrics(self) -> dict[str, Any]:
        """``workers_alive``; ``weight_version`` (the learner's update count now, the version it sends);
        ``weight_staleness``: mean updates the learner had made past the weights that collected each
        frame since the last call, at the time the frame reached it."""
        row: dict[str, Any] = {"workers_alive": self.alive_workers(), "weight_version": self.learner_version()}
        if self._staleness_frames:
            row["weight_staleness"] = self._staleness_sum / self._staleness_frames
        self._staleness_sum, self._staleness_frames = 0.0, 0
        return row


    def metrics_state(self) -> dict[str, Any]:
        return {"staleness_sum": float(self._staleness_sum), "staleness_frames": int(self._staleness_frames)}

    def load_metrics_state(self, state: dict[str, Any]) -> None:
        self._staleness_sum, self._staleness_frames = float(state["staleness_sum"]), int(state["staleness_frames"])

    @classmethod
    def metrics_between(cls, state: dict[str, Any], learner_version: int) -> dict[str, Any]:
        row: dict[str, Any] = {"weight_version": learner_version}
        if state.get("staleness_frames"):
            row["weight_staleness"] = state["staleness_sum"] / state["staleness_frames"]
        return row


def _lost(message: str) -> WorkerFailure:
    return WorkerFailure("collector", message)


def _actor_info(actor) -> dict:
    """The actor's row in Ray's actor table ({} if Ray, or its table, no longer knows it)."""
    import ray

    if not ray.is_initialized():
        return {}
    from ray._private.state import actors

    try:
        return actors(actor_id=actor._actor_id.hex()) or {}
    except Exception:
        return {}


def _death_cause(info: dict) -> str:
    cause = info.get("DeathCause")
    if not cause:
        return ""
    text = " ".join(str(cause).split())  # a protobuf message: its fields on one line
    return text[:200]


class StridedTrajectoryPool(_TrajectoryPool):
    """Trajectory ids ``index, index + stride, index + 2 * stride, ...``: actor ``index`` of ``stride``.

    Why: each of ``RayCollector``'s actors numbers its trajectories with a pool of its own (TorchRL's
    multi-process collectors share one across processes), so two actors' first trajectories were both 1 and a
    user's ``SliceSampler`` on ``("collector", "traj_ids")`` merged them (two actors' 10 blocks came
    out as trajectories 1, 1, 1, 1, 1, 2, 2). Its state (``state_dict``) is the actor's own count, as TorchRL's.
    It can go when TorchRL's ``RayCollector`` numbers trajectories across its actors itself (here, not in
    ``compat.torchrl``: that module is imported where TorchRL is not, and this class needs TorchRL's at import)."""

    def __init__(self, index: int, stride: int):
        super().__init__()
        self.index, self.stride = index, stride

    def get_traj_and_increment(self, n=1, device=None):
        return super().get_traj_and_increment(n, device) * self.stride + self.index


def _ray_collector(env_fn, policy, config: TrainConfig, total_frames: int, init_random_frames: int, scheme):
    """TorchRL's ``RayCollector``: one single-env ``Collector`` per actor, frames tagged with their weights' version,
    trajectory ids unique across the actors (``StridedTrajectoryPool``)."""
    from torchrl.collectors.distributed import RayCollector

    c, r = config.collector, config.ray
    with warnings.catch_warnings():
        # On init_random_frames with async collection: each actor takes its share of the random
        # frames (RayCollector splits them over the actors), which is what is meant here.
        warnings.filterwarnings("ignore", message="async distributed data collection with init_random_frames")
        return RayCollector(
            [env_fn] * c.workers, policy,
            # its state_dict carries the actor's envs, episodes and generators (workers.snapshot_collector), and its
            # set_seed seeds the actor's torch and NumPy generators too (TorchRL's seeds the env alone, so
            # the exploration noise of two runs of one seed differed)
            collector_class=WorkerSnapshotCollector,
            collector_kwargs=[{"track_policy_version": True, "traj_pool": StridedTrajectoryPool(i, c.workers),
                               "weight_sync_deadline": start_timeout(c.timeout), **COLLECTOR_KWARGS}
                              for i in range(c.workers)],
            frames_per_batch=c.frames_per_batch, total_frames=total_frames, init_random_frames=init_random_frames,
            # the learner's device is not the actors' business: they step and act on CPU
            device="cpu", storing_device="cpu",
            sync=c.sync, update_after_each_batch=True,
            # TorchRL's default reserves 2 GiB of memory per actor; a CPU collector needs far less
            remote_configs={"num_cpus": r.num_cpus_per_worker, "num_gpus": None, "memory": None},
            weight_sync_schemes={"policy": scheme},
        )
