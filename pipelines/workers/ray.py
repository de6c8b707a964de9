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

A lost actor (its process or node gone) surfaces as ``WorkerLost`` when its block is asked for,
whichever of Ray's errors says so (``_lost_errors``); ``alive_workers()`` counts the actors Ray
still holds alive, and ``kill_workers()`` ends a wait on them that ran past its deadline.
Restarting lost workers is the supervisor's job (issue 10, "Surviving failures"), not this module's.
"""

from __future__ import annotations

import math
import os
import time
import warnings
from collections.abc import Callable, Iterator
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.envs import EnvBase

from rlpipe.pipelines.compat.ray import check_reachable, stop_signals_kept
from rlpipe.pipelines.compat.torchrl import set_model_version
from rlpipe.pipelines.config import TrainConfig
from rlpipe.pipelines.errors import InputError
from rlpipe.pipelines.system.runtime import STOP_SIGNALS
from rlpipe.pipelines.workers.supervision import WorkerFailure

__all__ = ["METRIC_COLUMNS", "RayCollectors", "RayRuntime", "WorkerLost", "check_address"]

METRIC_COLUMNS = ["workers_alive", "weight_version", "weight_staleness"]
"""what ``RayCollectors.metrics`` adds to each log row of metrics.csv"""

MIN_START_TIMEOUT_S = 120.0
"""placing and starting the actors waits ``collector.timeout`` seconds, at least this long (each
actor imports torch and TorchRL and makes its env: most of a minute on a loaded 2-core machine)"""


def _lost_errors() -> tuple[type[BaseException], ...]:
    """Ray's errors that mean a collector actor, its node or the object it owed is gone: each is a
    ``WorkerLost``. Which one comes depends on where the loss is seen: a killed actor's block raises
    ``ActorDiedError``; a node gone, ``ActorDiedError`` (node died), ``ActorUnavailableError`` while
    Ray still tries to reach it, ``NodeDiedError``, ``ObjectLostError`` (``OwnerDiedError``, ...) for
    a block stored there; a wait with a deadline, ``GetTimeoutError``."""
    from ray import exceptions as e

    return (e.RayActorError, e.NodeDiedError, e.ObjectLostError, e.WorkerCrashedError, e.LocalRayletDiedError,
            e.GetTimeoutError, e.ActorUnschedulableError)


class WorkerLost(WorkerFailure):
    """A collector worker (here a Ray actor) died or its node went away; says which and how many are left.

    A ``supervision.WorkerFailure`` of the collector: the loop's supervisor tears the Ray collectors
    down and starts them again (``collector.max_restarts``), as it does local collector processes."""

    def __init__(self, message: str):
        super().__init__("collector", message)


class RayRuntime:
    """This run's hold on Ray: joins ``address`` or starts a local instance; ``close`` leaves a joined cluster up.

    A Ray already initialised in this process (a user's own program) is used as it is and left as it was.
    """

    def __init__(self, address: str, cpus_needed: float):
        import ray

        self.address = address
        self.started = False
        if ray.is_initialized():
            return
        # log_to_driver=False: Ray would print each actor's multi-line repr into the run's output; an
        # actor's failure still reaches the learner, as the exception of the block it owed.
        common = dict(include_dashboard=False, logging_level="error", configure_logging=True, log_to_driver=False)
        try:
            with stop_signals_kept(STOP_SIGNALS):
                if address:
                    check_reachable(address)
                    ray.init(address=address, **common)
                else:
                    # "local" rather than None: None would join whichever cluster was started last on this
                    # machine. Ray's CPUs are logical: as many as the workers ask for, at least the cores.
                    ray.init(address="local", num_cpus=max(os.cpu_count() or 1, math.ceil(cpus_needed)), **common)
        except ConnectionError as exc:
            raise _address_error(address, exc) from exc
        self.started = True

    def close(self) -> None:
        """Disconnect; a local instance this run started is shut down with its processes."""
        import ray

        if self.started and ray.is_initialized():
            ray.shutdown()
        self.started = False


class RayCollectors:
    """TorchRL's ``RayCollector`` as the loop uses a collector, with the run's Ray and version stamps.

    Iterating yields the collected blocks (each frame's ``("next", "policy_version")`` is the
    learner's update count whose weights collected it). ``shutdown`` kills the actors and lets go
    of Ray. For a supervisor: ``num_workers``, ``alive_workers()``, and ``WorkerLost`` from the
    iterator when an actor is gone.
    """

    def __init__(self, env_fn: Callable[[], EnvBase], policy: nn.Module, config: TrainConfig, *, total_frames: int,
                 init_random_frames: int, learner_version: Callable[[], int]):
        import ray
        from torchrl.weight_update import RayWeightSyncScheme

        c, r = config.collector, config.ray
        self.num_workers = c.workers
        self._learner_version = learner_version
        self._staleness_sum, self._staleness_frames = 0.0, 0
        self.runtime = RayRuntime(r.address, c.workers * r.num_cpus_per_worker)
        try:
            _check_cpus(ray, c.workers, r.num_cpus_per_worker, r.address)
            self.scheme = RayWeightSyncScheme()
            # The version the first weights carry (a resumed run's policy is already trained).
            set_model_version(self.scheme, learner_version())
            self.collector = _ray_collector(env_fn, policy, config, total_frames, init_random_frames, self.scheme)
            self._actors = list(self.collector.remote_collectors)
            self._wait_placed(ray, max(c.timeout, MIN_START_TIMEOUT_S))
            self.collector.update_policy_weights_()  # connects the weight sync (Gloo group) before collecting
        except _lost_errors() as exc:  # an actor (or its node) lost while starting: a restart may do
            self.runtime.close()
            raise WorkerLost(f"a Ray collector actor was lost while starting ({_first_line(exc)})") from exc
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
            raise WorkerLost(f"Ray placed {len(ready)} of {len(refs)} collector actors within {timeout:g} s "
                             f"(collector.timeout, at least {MIN_START_TIMEOUT_S:g}; {free:g} CPUs free in the "
                             "cluster); expected fewer collector.workers, a smaller ray.num_cpus_per_worker, "
                             "or more nodes")
        ray.get(ready)  # an actor that failed to start raises here, with its own error

    # --- what the loop uses of a collector -------------------------------------------------------

    def set_seed(self, seed: int, static_seed: bool = False) -> int:
        try:
            return self.collector.set_seed(seed, static_seed)
        except _lost_errors() as exc:
            raise WorkerLost(f"a Ray collector actor was lost while starting ({_first_line(exc)})") from exc

    def __iter__(self) -> Iterator[TensorDictBase]:
        lost_errors = _lost_errors()
        blocks = iter(self.collector)
        while True:
            # The weights the collector sends with its next request are the learner's as of now.
            set_model_version(self.scheme, self._learner_version())
            try:
                batch = next(blocks)
            except StopIteration:
                return
            except Exception as exc:
                # Ray says so (the block of a dead actor), or the weight push finds its peer gone first
                # (Gloo's "Connection closed by peer"): then Ray's actor table says so within seconds.
                if not (isinstance(exc, lost_errors) or self._some_lost(within_s=10.0)):
                    raise
                raise WorkerLost(f"a Ray collector actor was lost ({_first_line(exc)}); "
                                 f"{self.alive_workers()} of {self.num_workers} alive") from exc
            self._note_versions(batch)
            yield batch

    def update_policy_weights_(self) -> None:
        """Nothing to do here: each worker gets the learner's weights when it is asked for its next block."""

    def shutdown(self, timeout: float | None = None, raise_on_error: bool = True) -> None:
        """Stop the actors, then a local Ray instance this run started (``raise_on_error=False``, as
        the supervisor tears a failed collector down: errors of dead actors are not raised)."""
        try:
            self.collector.shutdown(timeout=timeout)
        except Exception:
            if raise_on_error:
                raise
        finally:
            self.runtime.close()

    # --- for the log rows and a supervisor --------------------------------------------------------

    def kill_workers(self) -> None:
        """Kill the actors (the supervisor's action on a wait past collector.timeout): the block or
        weight push waited on then fails at once, as a lost actor's does."""
        import ray

        for actor in self._actors:
            try:
                ray.kill(actor, no_restart=True)
            except Exception:  # gone already, or Ray itself is: the wait ends either way
                pass

    def alive_workers(self) -> int:
        """Collector actors Ray holds alive now (from Ray's actor table, so a busy actor counts as alive)."""
        import ray

        if not ray.is_initialized():
            return 0
        # Ray's actor table (GCS). A ping (`__ray_ready__`) would queue behind a block in flight, and the
        # public state API (ray.util.state) needs the dashboard, which the run does not start.
        from ray._private.state import actors

        alive = 0
        for actor in self._actors:
            try:
                alive += actors(actor_id=actor._actor_id.hex()).get("State") in ("ALIVE", 2)
            except Exception:  # an actor the GCS no longer knows is not alive
                pass
        return alive

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
        staleness = self._learner_version() - versions.reshape(-1).to(torch.float64)
        self._staleness_sum += float(staleness.sum())
        self._staleness_frames += staleness.numel()

    def metrics(self) -> dict[str, Any]:
        """``workers_alive``; ``weight_version`` (the learner's update count now, the version it sends);
        ``weight_staleness``: mean updates the learner had made past the weights that collected each
        frame since the last call, at the time the frame reached it."""
        row: dict[str, Any] = {"workers_alive": self.alive_workers(), "weight_version": self._learner_version()}
        if self._staleness_frames:
            row["weight_staleness"] = self._staleness_sum / self._staleness_frames
        self._staleness_sum, self._staleness_frames = 0.0, 0
        return row


def _ray_collector(env_fn, policy, config: TrainConfig, total_frames: int, init_random_frames: int, scheme):
    """TorchRL's ``RayCollector``: one single-env ``Collector`` per actor, frames tagged with their weights' version."""
    from torchrl.collectors import Collector
    from torchrl.collectors.distributed import RayCollector

    c, r = config.collector, config.ray
    with warnings.catch_warnings():
        # On init_random_frames with async collection: each actor takes its share of the random
        # frames (RayCollector splits them over the actors), which is what is meant here.
        warnings.filterwarnings("ignore", message="async distributed data collection with init_random_frames")
        return RayCollector(
            [env_fn] * c.workers, policy,
            collector_class=Collector,
            collector_kwargs={"track_policy_version": True, "auto_register_policy_transforms": True},
            frames_per_batch=c.frames_per_batch, total_frames=total_frames, init_random_frames=init_random_frames,
            # the learner's device is not the actors' business: they step and act on CPU
            device="cpu", storing_device="cpu",
            sync=c.sync, update_after_each_batch=True,
            # TorchRL's default reserves 2 GiB of memory per actor; a CPU collector needs far less
            remote_configs={"num_cpus": r.num_cpus_per_worker, "num_gpus": None, "memory": None},
            weight_sync_schemes={"policy": scheme},
        )


def _check_cpus(ray, workers: int, per_worker: float, address: str) -> None:
    total = ray.cluster_resources().get("CPU", 0.0)
    if total < workers * per_worker:
        where = f"the Ray cluster at {address!r}" if address else "the local Ray instance"
        raise InputError(f"collector.workers={workers} x ray.num_cpus_per_worker={per_worker:g} needs "
                         f"{workers * per_worker:g} CPUs; {where} has {total:g}: expected fewer workers, a smaller "
                         "ray.num_cpus_per_worker, or more nodes")


def check_address(address: str) -> None:
    """``InputError`` at once if nothing answers at ``address`` (empty: a local instance, nothing to
    check); the run calls it before it writes anything, so such a command leaves nothing behind."""
    if not address:
        return
    try:
        check_reachable(address)
    except ConnectionError as exc:
        raise _address_error(address, exc) from exc


def _address_error(address: str, exc: BaseException) -> InputError:
    return InputError(f"ray.address={address!r}: no Ray cluster answers there ({_first_line(exc)}); "
                      "expected the address `ray start --head` printed, 'auto' on one of its nodes, "
                      "or empty to start a local Ray instance")


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0][:200] if text else type(exc).__name__
