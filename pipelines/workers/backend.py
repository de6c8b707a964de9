"""The collector-backend interface: where a run's env steps are collected, behind one small class.

Tianshou's ``EnvWorker`` is the model: the loop and the supervisor hold a ``CollectorBackend`` and never
ask which one it is. Two implement it: ``local.LocalBackend`` (TorchRL's ``Collector`` in the learner's
process, or its ``MultiSyncCollector`` / ``MultiAsyncCollector`` over worker processes) and
``ray.RayBackend`` (TorchRL's ``RayCollector``, one actor per worker). ``factory.make_backend`` picks one from
``collector.backend``; it is the one place that reads that key. Another backend is one module with a
subclass, one line in ``_BACKENDS`` and one in ``config.COLLECTOR_BACKENDS`` (what it needs of a config).

A backend class also says what a run holds while its workers come and go (``hold``) and where
the background evaluator runs beside them (``start_evaluator``).

The life of one backend: ``start`` (for N frames) -> iterate its blocks, with ``push_weights`` between
them -> ``close``. ``health`` and ``kill`` are for a supervisor: a backend reports its workers (and
which died, and why) and ends a wait on them; it never restarts one itself. A lost worker surfaces as
``supervision.WorkerFailure`` from the blocks, from ``push_weights`` or in ``health().failure``;
``supervision.SupervisedCollector`` then closes the backend and starts a new one.
"""

from __future__ import annotations

import abc
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.envs import EnvBase

from rlpipe.pipelines.config import TrainConfig
from rlpipe.pipelines.workers.supervision import Watchdog, WorkerFailure, kill_new_children

if TYPE_CHECKING:
    from rlpipe.pipelines.workers.evaluation import AsyncEvaluator

__all__ = ["CollectorBackend", "Health"]


class Closeable(Protocol):
    def close(self) -> None: ...


@dataclass(frozen=True)
class Health:
    """A backend's workers as it sees them now."""

    total: int
    """workers started (0: the env steps in the learner's own process; nothing to watch)"""
    pids: tuple[int, ...] = ()
    """the live workers' processes (a Ray actor's is on its node)"""
    failure: WorkerFailure | None = None
    """the first worker found dead, saying which and why; None while every one runs"""

    @property
    def alive(self) -> int:
        return len(self.pids)


class CollectorBackend(abc.ABC):
    """Blocks of env steps from ``collector.workers`` workers running the collect policy.

    Made by ``make_backend`` (not started); ``start`` makes its workers, and the backend is then
    iterable once, block by block (TensorDicts as TorchRL's collectors give them), until the frames
    it was started for are collected. ``close`` stops its workers, whatever state they are in.
    """

    metric_columns: ClassVar[tuple[str, ...]] = ()
    """what ``metrics`` adds to each log row (metrics.csv's columns past the losses and speeds)"""
    role: ClassVar[str] = "collector"

    def __init__(self, config: TrainConfig, *, policy: nn.Module, env_fn: Callable[[], EnvBase] | None,
                 env: EnvBase | None = None, device: torch.device | str = "cpu",
                 learner_version: Callable[[], int] = lambda: 0):
        self.config, self.policy, self.env_fn, self.env = config, policy, env_fn, env
        self.device = torch.device(device)
        self.learner_version = learner_version  # the learner's update count: the version of the weights it sends
        self.started = False

    @classmethod
    def preflight(cls, config: TrainConfig) -> None:
        """``InputError`` now if this backend cannot run at all with ``config`` (a run calls it before it
        writes anything, so such a command leaves nothing behind)."""
        return None  # a local backend has nothing to check that validation has not

    @classmethod
    def hold(cls, config: TrainConfig) -> Closeable | None:
        """What a run holds for its whole length while this backend's workers and its evaluator come and
        go (Ray: the run's hold on Ray, ``ray_eval.hold_ray``); ``close()`` it at the run's end. None: nothing."""
        return None

    @classmethod
    def starts_processes(cls, config: TrainConfig) -> bool:
        """Whether a run with ``config`` starts worker processes of its own on this machine (multiprocessing's
        children; here the background evaluator's): ``rlpipe train`` starts their fork server early for them
        (``runtime.start_fork_server``)."""
        return config.eval_in_background

    @classmethod
    def start_evaluator(cls, config: TrainConfig, *, env_fn: Callable[[], EnvBase], policy: nn.Module,
                        pending: deque, start_timeout: float, watchdog: Watchdog) -> AsyncEvaluator:
        """The background evaluator (``eval_in_background=true``) beside this backend's workers, started:
        here a child process (``evaluation.BackgroundEvaluator``), which must say it is ready within
        ``start_timeout`` seconds (``watchdog`` kills it too, should anything else hang there)."""
        from rlpipe.pipelines.workers.evaluation import BackgroundEvaluator

        with watchdog.limit(start_timeout, kill_new_children()):
            return BackgroundEvaluator(env_fn, policy, config.num_eval_episodes, pending, timeout=config.eval_timeout,
                                       seed=config.seed, start_timeout=start_timeout, direct=config.fast)

    def start(self, total_frames: int, init_random_frames: int, seed: int | None = None,
              restore: dict[str, Any] | None = None) -> CollectorBackend:
        """Start the workers for ``total_frames`` frames, the first ``init_random_frames`` of them from
        random actions (none with ``initial_collect_policy=collect``), seeded with ``seed`` (None: as
        TorchRL leaves them), or, with ``restore`` (a ``snapshot``), going on from where that left its
        envs, episodes and generators. Returns the backend, started; ``WorkerFailure`` if a worker is
        lost meanwhile."""
        if self.started:
            raise RuntimeError(f"{type(self).__name__} was started already; make another (make_backend)")
        if self.config.initial_collect_policy == "collect":  # the initial steps come from the exploring policy
            init_random_frames = 0
        self._start(total_frames, init_random_frames)
        self.started = True
        if restore is not None:
            self.restored = self._restore(restore)
        if not self.restored and seed is not None:  # new episodes, as a first start's
            self._seed(seed)
        return self

    restored: bool = False
    """whether ``start(restore=...)`` put back the envs' episodes in progress (False: they restarted)"""

    def snapshot(self) -> dict[str, Any] | None:
        """Between two blocks: what decides the next blocks (each worker's envs in their episodes, its
        in-flight observation and counters, its generators), as tensors for a checkpoint; None where
        the next blocks cannot be reproduced (asynchronous collection: the workers are mid-block)."""
        return None

    def _restore(self, snapshot: dict[str, Any]) -> bool:
        """Put ``snapshot`` into the workers just started; False if their envs' episodes could not be."""
        return False

    def __iter__(self) -> Iterator[TensorDictBase]:
        return self.blocks()

    @abc.abstractmethod
    def _start(self, total_frames: int, init_random_frames: int) -> None: ...

    @abc.abstractmethod
    def _seed(self, seed: int) -> None: ...

    @abc.abstractmethod
    def blocks(self) -> Iterator[TensorDictBase]:
        """The collected blocks until the frame budget is met; ``WorkerFailure`` when a worker is lost."""

    @abc.abstractmethod
    def push_weights(self) -> None:
        """Hand the workers the policy's weights as they are now (or arrange that their next blocks use
        them); ``WorkerFailure`` if a worker is dead or does not take them within ``collector.timeout``."""

    @abc.abstractmethod
    def health(self) -> Health:
        """The workers alive now, and the first one found dead with its reason."""

    @abc.abstractmethod
    def kill(self) -> None:
        """Kill every worker now (a supervisor ends a wait past its deadline so): a block or weight push
        being waited on then fails at once, as a lost worker's does."""

    @abc.abstractmethod
    def close(self) -> None:
        """Stop the workers (asked first, killed if they do not go) and free what the backend holds;
        safe to call again, and on a backend whose workers died."""

    def metrics(self) -> dict[str, Any]:
        """This backend's own figures for a log row, keyed by ``metric_columns``."""
        return {}

    def metrics_state(self) -> dict[str, Any]:
        """What ``metrics`` has gathered since its last call (plain numbers, for a checkpoint)."""
        return {}

    def load_metrics_state(self, state: dict[str, Any]) -> None:
        """Go on gathering from ``metrics_state``'s ``state`` (a resumed run's)."""
        return None  # a backend without figures of its own has nothing to go on from

    @classmethod
    def metrics_between(cls, state: dict[str, Any], learner_version: int) -> dict[str, Any]:
        """``metrics`` from ``metrics_state``'s ``state`` while no backend runs (the row a resumed run owes
        before its collector starts), workers alive aside (the supervisor's last report has them)."""
        return {}

    @property
    def collector(self):
        """What a loop of one's own iterates: a TorchRL collector (``shutdown`` when done; push weights
        with ``OffPolicyPipeline.push_weights``)."""
        return self
