"""Exact resume: the bookkeeping that lets a run stopped at any safe point and resumed equal, bit for bit,
an uninterrupted run of its seed, and the record of why a run no longer can.

A checkpoint's counters, replay buffer, networks and random generators are not all of it. The loop calls
``ExactResume`` at four points for the rest:

* when it starts: the log interval's losses and episodes so far go back into the meters, and the workers
  last seen alive into the supervisor (the rows a resumed run writes before its workers start say what an
  uninterrupted run's say);
* when it starts a collector (``collector_seed``, then ``collector_started``): the envs go on from their
  episodes where the last collector left them, trajectory ids go on above those stored, and the metrics
  the last backend had gathered for its next row carry over;
* when a block arrives (``number_trajectories``);
* when the collector closes and when a checkpoint is saved (``capture``): what the next collector, here
  or after a resume, goes on from.

What defeats exactness (a restarted worker, asynchronous collection, an env whose state cannot be
captured) is recorded once, in ``RunState.inexact``; summary.json says so.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
from tensordict import TensorDictBase

from rlpipe.pipelines.artifacts.rundir import notice
from rlpipe.pipelines.training.meters import IntervalStats
from rlpipe.pipelines.workers.snapshot_collector import why_not_exact
from rlpipe.pipelines.workers.supervision import SupervisedCollector, Supervisor

if TYPE_CHECKING:
    from rlpipe.pipelines.base import OffPolicyPipeline
    from rlpipe.pipelines.workers.backend import CollectorBackend

__all__ = ["TRAJ_IDS", "ExactResume"]

TRAJ_IDS = ("collector", "traj_ids")


class ExactResume:
    """``pipeline.state``'s part that is neither a counter nor owed work: see the module's docstring.

    Made when the loop starts; it restores ``interval_stats`` and ``supervisor`` from the state the
    checkpoint held, and ``capture`` writes them back into it.
    """

    def __init__(self, pipeline: OffPolicyPipeline, interval_stats: IntervalStats, supervisor: Supervisor):
        self.pipeline, self.config, self.state = pipeline, pipeline.config, pipeline.state
        self.interval_stats, self.supervisor = interval_stats, supervisor
        if self.state.interval is not None:
            interval_stats.load_state_dict(self.state.interval)
        if self.state.workers is not None:  # as last seen: the rows owed before the workers start again
            supervisor.alive.update({role: tuple(seen) for role, seen in self.state.workers.items()})

    def collector_seed(self, restarts: int) -> tuple[int, dict[str, Any] | None]:
        """The seed and the envs' snapshot (``state.envs``) for the next collector: it goes on from the envs'
        episodes where the last one left them, else is seeded; after a restart, with a seed stream no earlier
        collector of the run used and new episodes (its workers' episodes died with them)."""
        cfg, state = self.config, self.state
        if restarts:
            state.not_exact("a collector worker was restarted: the episodes in progress in its envs, and its "
                            "random generators, died with it")
            return int(np.random.SeedSequence([cfg.seed, state.frames, restarts]).generate_state(1)[0]), None
        if not cfg.collector.sync:
            state.not_exact("asynchronous collection (collector.sync=false): which weights act in a block, and "
                            "which worker's block comes first, depend on timing")
        return cfg.seed + state.frames, state.envs

    def collector_started(self, backend: CollectorBackend, snapshot: dict[str, Any] | None, restarts: int) -> None:
        """Carry over to a collector just started from ``snapshot`` (``collector_seed``'s) the trajectory
        numbering and the last collector's metrics; say so where its envs could not go on from it."""
        cfg, state = self.config, self.state
        if not backend.restored:  # it numbers trajectories from 0: above the ones stored (RunState.traj_offset)
            state.traj_offset = state.traj_next
        if state.backend_metrics and not restarts:  # what the last collector had gathered for its next row
            backend.load_metrics_state(state.backend_metrics)
        state.backend_metrics = None
        if snapshot is not None and not backend.restored:
            why = why_not_exact(self.pipeline.env) or "its state did not fit this collector"
            notice(f"{cfg.env}: the collector's env cannot be captured ({why}); its episode in progress restarts")
            state.not_exact(f"the env's episode in progress restarted at a resume ({why})")

    def number_trajectories(self, batch: TensorDictBase) -> None:
        """Make a block's trajectory ids unique across the run's collectors where the replay buffer stores
        them (``RunState.traj_offset``), and note the next free one."""
        keys, state = self.pipeline.replay_keys, self.state
        if keys is not None and TRAJ_IDS not in keys:
            return
        ids = batch.get(TRAJ_IDS, None)
        if ids is None or not ids.numel():
            return
        if state.traj_offset:
            ids = ids + state.traj_offset
            batch.set(TRAJ_IDS, ids)
        state.traj_next = max(state.traj_next, int(ids.max()) + 1)

    def capture(self, collection: SupervisedCollector | None) -> None:
        """Note for the next checkpoint the log interval so far, the workers alive, and the collector's envs in
        their episodes (``state.envs``), these when they are between two blocks and its workers are all alive
        (otherwise the last note stays)."""
        state = self.state
        state.interval = self.interval_stats.state_dict()
        state.workers = {role: list(seen) for role, seen in self.supervisor.alive.items()}
        backend = None if collection is None else collection.collector
        if backend is None:
            return
        state.backend_metrics = backend.metrics_state()  # the last block's too
        if state.frames >= self.config.total_frames:  # finished: nothing more to collect
            return
        if collection.failed or backend.health().failure is not None:
            state.envs = None  # a lost worker's envs are lost: the next collector starts new episodes
            return
        state.envs = backend.snapshot()
