"""The collect/learn loop: TF-Agents' ``Learner.run`` on TorchRL parts.

``Loop.run`` collects a block of env steps with a TorchRL collector, makes the updates that block
paid for (``updates_per_frame = 1 / collect_steps_per_iteration``, held by ``SampleToInsertRatio``),
then runs the triggers whose interval the block crossed (log, evaluate, export, checkpoint, and any
a user adds); at the end it fires the same triggers once more (their ``final``). Everything else is a
part with its own module: what triggers see of the loop (``context``), the run's lifecycle (``run``),
the run's state (``state``), the triggers and
the work they do (``triggers``, ``evaluations``), what a checkpoint needs for an exact resume
(``resume``), speeds and losses (``meters``), Ctrl-C and worker start-up (``system.runtime``), the run
directory and checkpoints.

Ctrl-C, SIGTERM or SIGHUP stops at the next safe point (between two updates, two env steps of an
evaluation, or two triggers); the checkpoint saved then records what that iteration still owes, and
``--resume`` does exactly that first. Collector and evaluator processes never see those signals:
they start with them blocked, and the learner stops them. A second signal stops at once, unsaved.

Workers are supervised (``workers.supervision``): a collector or evaluator process that dies or stops
answering is replaced, up to ``collector.max_restarts`` times; one more failure saves a checkpoint
and ends the run with ``NoRestartLeft``.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from tensordict import TensorDictBase
from torch import nn
from torchrl.record.loggers import Logger

from rlpipe.pipelines.artifacts.files import FileWriteError
from rlpipe.pipelines.artifacts.rundir import MetricsCSV, RunDir
from rlpipe.pipelines.system.runtime import Interrupted, Stopped, stop_signals_blocked
from rlpipe.pipelines.training.context import LIVE_LOG, LoopContext
from rlpipe.pipelines.training.nstep import n_step_transitions
from rlpipe.pipelines.training.resume import TRAJ_IDS, ExactResume
from rlpipe.pipelines.workers.supervision import NoRestartLeft, SupervisedCollector, Watchdog

if TYPE_CHECKING:
    from rlpipe.pipelines.base import OffPolicyPipeline
    from rlpipe.pipelines.training.triggers import Trigger
    from rlpipe.pipelines.workers.backend import CollectorBackend

__all__ = ["LIVE_LOG", "Loop", "TrainResult"]


@dataclass
class TrainResult:
    """What ``train`` hands back: the trained policy, the metrics rows and where the run lives."""

    policy: nn.Module
    run_dir: Path
    metrics: list[dict[str, str]]
    summary: dict[str, Any]
    evaluations: list[dict[str, Any]] = field(default_factory=list)


class Loop(LoopContext):
    """One run of ``pipeline`` into ``run``, from where ``pipeline.state`` says it is to its end.

    Triggers get this object; what they may use of it is ``LoopContext``.
    """

    def __init__(self, pipeline: OffPolicyPipeline, run: RunDir, metrics: MetricsCSV, *, fresh: bool,
                 evaluations: list[dict], triggers: Sequence[Trigger], logger: Logger,
                 callbacks: Sequence[Callable[[dict], None]] = (), progress: bool = True):
        super().__init__(pipeline, run, metrics, evaluations=evaluations, triggers=triggers, logger=logger,
                         callbacks=callbacks, progress=progress)
        self.fresh = fresh
        self.resume = ExactResume(pipeline, self.interval_stats, self.supervisor)

    def run(self) -> None:
        """The run to its end (inside ``run.running``): start, then collect, update and run the triggers
        block by block, then the triggers' final firing."""
        with self.closed_at_end():
            try:
                self.start()
                self.pay_updates()  # owed by a run stopped in the middle of a block ...
                self.run_triggers()  # ... and what its iteration still had to do
                with contextlib.closing(self.collect()) as blocks:
                    for batch in blocks:
                        self.insert(batch)
                        self.pay_updates()
                        self.run_triggers()
                        self.fire("poll")
                self.fire("final")
            except Stopped as stop:
                self.fire("stopped")  # the checkpoint trigger saves what this iteration still owes
                self.page_stopped()
                raise Interrupted(stop.signum) from None
            except NoRestartLeft as lost:
                self.fire("stopped", lost)  # the collector's blocks handed out so far are in the replay buffer
                lost.saved_at = self.state.iteration
                self.page_stopped()
                raise

    # --- the steps of a run ---------------------------------------------------------------------

    def start(self) -> None:
        """A fresh run's checkpoint at iteration 0 (a resumed run's line saying where it is), the watchdog,
        the triggers' ``start``; training time counts from here."""
        her = self.pipeline.hindsight
        if her is not None:
            self.echo(f"hindsight experience replay: {her['her_ratio']:.0%} of each batch relabelled with a goal its "
                      f"episode reached later (the 'future' strategy; her=false turns it off)")
        if self.fresh:
            self.save()  # iteration 0: a run stopped at any point from here on can be resumed
        else:
            state = self.state
            self.echo(f"resumed at iteration {state.iteration:,} of {self.config.num_iterations:,} "
                      f"({state.frames:,} env steps, {state.updates:,} updates, {self.clock.wall():.1f} s so far)")
        self.watchdog = Watchdog()
        self.fire("start")
        self.clock.start()

    def page_stopped(self) -> None:
        """The report page of a run stopping early: it says so, and how to continue (its checkpoint is saved)."""
        try:
            with self.clock.paused():
                self.page.write(running=False)
        except (OSError, FileWriteError) as exc:  # the checkpoint is what counts; the stop goes on
            LIVE_LOG.warning(f"report.html not rewritten: {exc}")

    def fire(self, moment: str, *args) -> None:
        """Every trigger's ``moment`` (``start``, ``poll``, ``final``, ``stopped``, ``close``), in order."""
        for trigger in self.triggers.values():
            hook = getattr(trigger, moment, None)  # None: a trigger not made from ``Trigger`` may lack it
            if hook is not None:
                hook(self, *args)

    def collect(self) -> Iterator[TensorDictBase]:
        """Blocks of env steps from a TorchRL collector, until the run's frame budget is met.

        The collector is supervised (``SupervisedCollector``): one whose worker fails is replaced by a
        new one for the frames still to collect. Closed (``contextlib.closing``) however the run leaves
        it, so that TorchRL's iterator is closed while its workers still run, and the workers are then
        shut down (within seconds: one that does not stop when asked is killed).
        """
        cfg, state = self.config, self.state
        if cfg.total_frames - state.frames <= 0:
            return
        self.collection = SupervisedCollector(self.start_collector, self.supervisor, self.watchdog)
        # held here: the for loop's own reference goes (and the generator closes its backend) as an
        # exception leaves it, before `finally` has captured the envs
        blocks = iter(self.collection)
        try:
            for batch in blocks:
                if self.first_block_unix is None:
                    self.first_block_unix = time.time()
                yield batch
                if self.finished_early is not None:
                    break
                if state.frames >= cfg.total_frames:
                    break
        finally:
            self.resume.capture(self.collection)  # between two blocks: what a checkpoint at a stop goes on from
            self.collection.close()
            self.collection = None

    def start_collector(self, restarts: int) -> CollectorBackend:
        """A started collector backend for the frames still to collect (``SupervisedCollector``'s ``make``):
        seeded, and going on from the envs' episodes, as ``resume`` says."""
        cfg, state = self.config, self.state
        seed, snapshot = self.resume.collector_seed(restarts)
        with stop_signals_blocked(), self.clock.paused():  # worker start-up is not training time
            backend = self.pipeline.make_backend().start(cfg.total_frames - state.frames,
                                                         max(0, cfg.initial_collect_steps - state.frames), seed,
                                                         restore=snapshot)
        self.resume.collector_started(backend, snapshot, restarts)
        return backend

    def insert(self, batch: TensorDictBase) -> None:
        """Store a block in the replay buffer, count it, and note the triggers its iterations crossed."""
        batch = batch.reshape(-1)[: self.config.total_frames - self.state.frames]  # collectors round up to whole blocks
        self.resume.number_trajectories(batch)
        self.pipeline.on_block(batch)
        self.store(batch)
        self.count(batch)

    def store(self, batch: TensorDictBase) -> None:
        """Put a block's transitions in the replay buffer: the keys it stores, n-step ones where ``n_step > 1``."""
        n, keys = self.config.n_step, self.pipeline.replay_keys
        if n > 1:  # the windows read the ids and done flags; discounted by the loss's own gamma
            window = batch if keys is None else batch.select(*keys, TRAJ_IDS, ("next", "done"), strict=False)
            batch = n_step_transitions(window, n, float(self.pipeline.loss_module.value_estimator.gamma))
        self.pipeline.replay_buffer.extend(batch if keys is None else batch.select(*keys))

    def count(self, batch: TensorDictBase) -> None:
        """Count a block as taken: its finished episodes, its frames (exploration schedules follow them), the
        iterations they make, and the triggers whose interval those crossed (``state.owed``)."""
        ended = self.interval_stats.add_frames(batch)
        if ended:
            self.recent_returns.extend(self.interval_stats.episode_returns[-ended:])
        self.state.episodes += ended
        self.pipeline.on_frames(batch.numel())
        before, now = self.state.insert(batch.numel(), self.config)
        self.state.owed = [t.name for t in self.triggers.values() if t.due(before, now, self.config.num_iterations)]
        self.bar.update(now - before)

    def pay_updates(self) -> None:
        """Make the updates the frames so far paid for; push the new weights to collector processes."""
        update, made = self.pipeline.update_step, 0
        while self.state.limiter.owed:
            self.stop.check()
            losses = update(self.pipeline.sample(), self.state.updates + 1)
            self.state.updated()
            made += 1
            self.interval_stats.add_losses(losses)
        if made:
            self.check_finite()  # once per block: a few scalars, before the collectors get the weights
        if made and self.collection is not None and self.state.updates % self.config.collector.weight_sync_interval < made:
            self.collection.push_weights()

    def run_triggers(self) -> None:
        """Run what the current iteration owes, in order; each is crossed off once done."""
        owed = self.state.owed
        while owed:
            self.stop.check()
            trigger = self.triggers.get(owed[0])
            if trigger is None or trigger.crossed_off_first:  # None: a trigger of an earlier session, not passed now
                owed.pop(0)
            if trigger is not None:
                trigger(self)
                if not trigger.crossed_off_first:
                    owed.pop(0)

    @contextlib.contextmanager
    def closed_at_end(self):
        """However the run ends: the triggers' ``close`` (the eval trigger stops its evaluator process or Ray
        actor), then the watchdog and the progress bar closed (``collect`` stops the collector's workers)."""
        try:
            yield
        finally:
            self.fire("close")
            if self.watchdog is not None:
                self.watchdog.close()
            self.bar.close()
