"""The local collector backend (``collector.backend=local``): TorchRL's collectors on this machine.

One worker with ``collector.sync=true`` steps the env in the learner's process (TorchRL's ``Collector``,
no process to watch); otherwise ``collector.workers`` processes, stepping in lock-step
(``MultiSyncCollector``) or each at its own pace (``MultiAsyncCollector``). On one-copy envs made from
``config.env`` (``collector.direct``) each of those collectors is ``gym_collector.GymCollector``, TorchRL's
``Collector`` stepping the gymnasium env directly. Weights reach the processes
through TorchRL's shared-memory weight sync, with a deadline on the workers' acknowledgements
(``supervision.TimedSharedMemScheme``): a push to a dead worker is a ``WorkerFailure``, not a wait for good.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable, Iterator
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.collectors import Collector, MultiAsyncCollector, MultiSyncCollector
from torchrl.envs import EnvBase

from rlpipe.envs import make_env
from rlpipe.pipelines.compat.torchrl import COLLECTOR_KWARGS
from rlpipe.pipelines.config import ENV_KWARGS_RESERVED, TrainConfig, steps_in_learner
from rlpipe.pipelines.workers.backend import CollectorBackend, Health
from rlpipe.pipelines.workers.gym_collector import GymCollector, WorkerGymCollector, gym_env_of
from rlpipe.pipelines.workers.snapshot_collector import (
    SNAPSHOT,
    SnapshotCollector,
    WorkerSnapshotCollector,
    why_not_exact,
)
from rlpipe.pipelines.workers.supervision import (
    TimedSharedMemScheme,
    close_weight_sync_queues,
    dead_worker,
    is_running,
    kill_processes,
)

__all__ = ["AsyncCollector", "LocalBackend", "direct_collection", "local_collector", "push_weights"]


def direct_collection(config: TrainConfig, env_fn: Callable[[], EnvBase] | None, env: EnvBase | None) -> bool:
    """Whether the collectors step the gymnasium env directly (``GymCollector``, in this process or in each
    worker process): ``collector.direct`` and one-copy envs the pipeline makes from ``config.env`` (a user's
    own TorchRL env keeps TorchRL's ``Collector``: its transforms are its own); never with ``fast=false``."""
    c = config.collector
    made_here = (isinstance(env_fn, functools.partial) and env_fn.func is make_env and env_fn.args == (config.env,)
                 and set(env_fn.keywords) - set(config.env_kwargs) <= set(ENV_KWARGS_RESERVED)
                 and env_fn.keywords.get("num_envs", 1) == 1)
    return config.fast and c.direct and made_here and gym_env_of(env) is not None


class AsyncCollector(MultiAsyncCollector):
    """TorchRL's ``MultiAsyncCollector`` with room in its output queue for a block from every worker.

    TorchRL's queue holds one block (``_queue_len`` 1, TorchRL 0.14). A worker whose block finds it full for
    1 s (``_TIMEOUT``: the learner evaluating, checkpointing, or slower than the workers) collects another one
    over it in its shared buffer: that block is lost, its env steps thrown away and a hole left in its env's
    trajectory in the replay buffer: a td3 run with two workers and evaluations in the learner lost 1 block of
    18 on a 2-core machine (``tests/test_collectors.py`` checks that trajectories arrive whole). A worker has at
    most one block waiting (it collects again only when told to go on), so a queue of ``num_workers`` never turns
    one away."""

    @property
    def _queue_len(self) -> int:
        return self.num_workers


def local_collector(config: TrainConfig, *, policy: nn.Module, env_fn: Callable[[], EnvBase] | None,
                    env: EnvBase | None, device: torch.device, total_frames: int, init_random_frames: int):
    """The TorchRL collector ``config.collector`` describes, started, for ``total_frames`` frames."""
    c = config.collector
    common = dict(frames_per_batch=c.frames_per_batch, total_frames=total_frames,
                  init_random_frames=init_random_frames, **COLLECTOR_KWARGS,
                  # the env steps where it lives; its outputs go to the policy's device (a device other
                  # than the policy's own: TorchRL acts from a copy there), and the collected blocks to the
                  # learner's (where the replay buffer is)
                  policy_device=torch.device(c.policy_device) if c.policy_device else device,
                  storing_device=device)
    direct = direct_collection(config, env_fn, env)
    if steps_in_learner(c):
        # Its constructor runs the policy on a fake step (a draw of the exploring policy's): on the
        # learner's generators, that draw would make a run resumed mid-way (a collector more) differ.
        with torch.random.fork_rng(devices=[]):
            return (GymCollector if direct else SnapshotCollector)(env if env is not None else env_fn(), policy,
                                                                   **common)
    if not c.sync and init_random_frames > 0:
        # MultiAsyncCollector decides random-or-policy for a worker's next block when it hands
        # over that worker's last one, so the other workers' blocks in flight are random too:
        # ask for that many fewer, and exactly `init_random_frames` come out random (to a block).
        # (Each async worker's block is a whole `frames_per_batch`.)
        common["init_random_frames"] = max(1, init_random_frames - (c.workers - 1) * c.frames_per_batch)
    if c.policy_device == "cpu":
        # Worker processes acting from a CPU copy store their blocks on the CPU too (shared memory, as the
        # weights): the learner moves each block to its device (``LocalBackend.blocks``). Stored on a GPU,
        # each worker would start CUDA and hand its blocks over through CUDA's inter-process handles.
        common["storing_device"] = torch.device("cpu")
    cls = MultiSyncCollector if c.sync else AsyncCollector
    scheme = TimedSharedMemScheme(ack_timeout=c.timeout)
    return cls([env_fn] * c.workers, policy, weight_sync_schemes={"policy": scheme},
               collector_class=WorkerGymCollector if direct else WorkerSnapshotCollector, **common)


def push_weights(collector) -> None:
    """Send the policy's weights to a TorchRL collector's worker processes, or to its copy of the policy on
    another device (``collector.policy_device``); in-process collection on the learner's device shares the
    policy itself: nothing to send."""
    if not isinstance(collector, Collector) or collector.get_weights_fn is not None:
        collector.update_policy_weights_()


class LocalBackend(CollectorBackend):
    """TorchRL's ``Collector`` / ``MultiSyncCollector`` / ``MultiAsyncCollector`` as a ``CollectorBackend``."""

    _collector = None

    @classmethod
    def starts_processes(cls, config: TrainConfig) -> bool:
        return not steps_in_learner(config.collector) or super().starts_processes(config)

    def _start(self, total_frames: int, init_random_frames: int) -> None:
        self._collector = local_collector(self.config, policy=self.policy, env_fn=self.env_fn, env=self.env,
                                          device=self.device, total_frames=total_frames,
                                          init_random_frames=init_random_frames)

    def _seed(self, seed: int) -> None:
        self._collector.set_seed(seed)

    def snapshot(self) -> dict[str, Any] | None:
        collector = self._collector
        if isinstance(collector, SnapshotCollector):
            return {"workers": [collector.snapshot()]}
        if isinstance(collector, MultiSyncCollector):  # its workers wait for the next "continue": between blocks
            state = collector.state_dict()
            return {"workers": [state[f"worker{i}"][SNAPSHOT] for i in range(collector.num_workers)]}
        return None

    def _restore(self, snapshot: dict[str, Any]) -> bool:
        collector, workers = self._collector, snapshot["workers"]
        if isinstance(collector, SnapshotCollector) and len(workers) == 1:
            return collector.load_snapshot(workers[0])
        if isinstance(collector, MultiSyncCollector) and len(workers) == collector.num_workers:
            collector.load_state_dict({**{f"worker{i}": {SNAPSHOT: w} for i, w in enumerate(workers)},
                                       "frames": collector._frames, "iter": collector._iter})
            return why_not_exact(self.env) is None and all(bool(w["capturable"]) for w in workers)
        return False

    @property
    def collector(self):
        return self._collector

    @property
    def _procs(self) -> list:
        return list(getattr(self._collector, "procs", None) or [])

    def blocks(self) -> Iterator[TensorDictBase]:
        iterator = iter(self._collector)
        while True:
            try:
                batch = next(iterator)
            except StopIteration:
                return
            except (RuntimeError, ValueError, EOFError, OSError) as exc:
                # TorchRL's iterator saw a worker gone (RuntimeError "At least one process failed",
                # or ValueError from its close() of a process still running): say which one, and how.
                failure = dead_worker(self.role, self._procs)
                if failure is None:
                    raise
                raise failure from exc
            if batch.device != self.device:  # stored on the CPU by worker processes (collector.policy_device=cpu)
                batch = batch.to(self.device)
            yield batch

    def push_weights(self) -> None:
        failure = dead_worker(self.role, self._procs)
        if failure is not None:
            raise failure
        push_weights(self._collector)

    def health(self) -> Health:
        procs = self._procs
        return Health(len(procs), tuple(p.pid for p in procs if is_running(p)), dead_worker(self.role, procs))

    def kill(self) -> None:
        kill_processes(self._procs, timeout=0)  # TorchRL's loops then see them dead within ~1 s

    def close(self) -> None:
        collector, self._collector = self._collector, None
        if collector is None:
            return
        procs = list(getattr(collector, "procs", None) or [])
        if dead_worker(self.role, procs):
            kill_processes(procs)  # a failed collector's workers: nothing to wait for
        # TorchRL's shutdown asks each worker to close, then terminates and kills within the timeout.
        with contextlib.suppress(Exception):
            collector.shutdown(timeout=2.0, raise_on_error=False)
        kill_processes(procs)
        close_weight_sync_queues(collector)
