"""The collect/learn loop: TF-Agents' ``Learner.run`` on TorchRL parts.

``Loop.run`` collects a block of env steps with a TorchRL collector, makes the updates that block
paid for (``updates_per_frame = 1 / collect_steps_per_iteration``, held by ``SampleToInsertRatio``),
then runs the triggers whose interval the block crossed (log, evaluate, export, checkpoint, and any
a user adds); at the end it fires the same triggers once more (their ``final``). Everything else is a
part with its own module: the run's lifecycle (``run``), the run's state (``state``), the triggers and
the work they do (``triggers``, ``evaluations``), Ctrl-C and worker start-up (``runtime``), speeds
and losses (``meters``), the run directory and checkpoints.

Ctrl-C, SIGTERM or SIGHUP stops at the next safe point (between two updates, two env steps of an
evaluation, or two triggers); the checkpoint saved then records what that iteration still owes, and
``--resume`` does exactly that first. Collector and evaluator processes never see those signals:
they start with them blocked, and the learner stops them. A second signal stops at once, unsaved.

Workers are supervised (``supervision``): a collector or evaluator process that dies or stops
answering is replaced, up to ``collector.max_restarts`` times; one more failure saves a checkpoint
and ends the run with ``NoRestartLeft``.
"""

from __future__ import annotations

import contextlib
import logging
import math
import sys
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from tensordict import TensorDictBase
from torch import nn
from torchrl.record.loggers import Logger
from tqdm.auto import tqdm
from tqdm.contrib.logging import logging_redirect_tqdm

from rlpipe.pipelines.artifacts.files import FileWriteError
from rlpipe.pipelines.artifacts.rundir import MetricsCSV, RunDir, notice
from rlpipe.pipelines.system.runtime import (
    DeferredInterrupt,
    Interrupted,
    Stopped,
    dropping,
    fault_point,
    gc_frozen,
    keep_freed_memory,
    stop_signals_blocked,
)
from rlpipe.pipelines.training.divergence import check_finite
from rlpipe.pipelines.training.meters import Clock, IntervalStats
from rlpipe.pipelines.training.nstep import n_step_transitions
from rlpipe.pipelines.training.page import ReportPage
from rlpipe.pipelines.training.sampling import sample
from rlpipe.pipelines.training.state import EVAL, EXPORT, SAVE
from rlpipe.pipelines.workers.snapshot import why_not_exact
from rlpipe.pipelines.workers.supervision import NoRestartLeft, SupervisedCollector, Supervisor, Watchdog

if TYPE_CHECKING:
    from rlpipe.pipelines.base import OffPolicyPipeline
    from rlpipe.pipelines.training.triggers import Trigger
    from rlpipe.pipelines.workers.backend import CollectorBackend

__all__ = ["LIVE_LOG", "Loop", "TrainResult"]

TRAJ_IDS = ("collector", "traj_ids")

LIVE_LOG = logging.getLogger("rlpipe.train")
"""The live log, the tutorials' printed lines (``step = 1000: AverageReturn = ...``), as INFO records.
``rlpipe train`` shows them on stdout; from Python, ``logging.basicConfig(level=logging.INFO,
format="%(message)s")`` does (a library leaves where its records go to the application)."""


@dataclass
class TrainResult:
    """What ``train`` hands back: the trained policy, the metrics rows and where the run lives."""

    policy: nn.Module
    run_dir: Path
    metrics: list[dict[str, str]]
    summary: dict[str, Any]
    evaluations: list[dict[str, Any]] = field(default_factory=list)


class Loop:
    """One run of ``pipeline`` into ``run``, from where ``pipeline.state`` says it is to its end.

    Triggers get this object; what they may use is listed in ``triggers``' docstring.
    """

    def __init__(self, pipeline: OffPolicyPipeline, run: RunDir, metrics: MetricsCSV, *, fresh: bool,
                 evaluations: list[dict], triggers: Sequence[Trigger], logger: Logger,
                 callbacks: Sequence[Callable[[dict], None]] = (), progress: bool = True):
        self.pipeline, self.config, self.state = pipeline, pipeline.config, pipeline.state
        self.run_dir, self.metrics, self.fresh, self.evaluations = run, metrics, fresh, evaluations
        self.triggers = {t.name: t for t in triggers}
        self.logger, self.callbacks = logger, list(callbacks)
        self.clock = Clock(self.state.wall_time_s, self.state.train_time_s)  # a resumed run's earlier stretches
        self.interval_stats, self.stop = IntervalStats(), DeferredInterrupt()
        self.page = ReportPage(run.path, evaluations, title=f"{pipeline.algo} on {self.config.env}")
        if self.state.interval is not None:
            self.interval_stats.load_state_dict(self.state.interval)
        self.supervisor = Supervisor(self.config.collector.max_restarts, self.config.collector.timeout)
        if self.state.workers is not None:  # as last seen: the rows owed before the workers start again
            self.supervisor.alive.update({role: tuple(seen) for role, seen in self.state.workers.items()})
        self.collection: SupervisedCollector | None = None
        self.watchdog: Watchdog | None = None
        self._counts_at_start = (self.state.frames, self.state.updates)  # this session's speeds
        self.recent_returns: deque[float] = deque(maxlen=1000)
        """returns of the training episodes finished in this session, newest last (for triggers)"""
        self.first_block_unix: float | None = None
        """``time.time()`` when this session's first block of env steps arrived"""
        self.finished_early: str | None = None
        """why a trigger ended the run before its last iteration (``finish_early``), else None"""
        # on stderr, dropped where no one can read it (a pipe's reader gone, the terminal closed): the run goes on
        self.bar = tqdm(total=self.config.num_iterations, initial=self.state.iteration, unit="it", disable=not progress,
                        desc=f"{pipeline.algo} {self.config.env}", dynamic_ncols=True, file=dropping(sys.stderr))

    @property
    def collector(self):
        """The collector backend collecting now (None outside ``collect``, or while one is replaced)."""
        return None if self.collection is None else self.collection.collector

    @property
    def last_return(self) -> float:
        return self.evaluations[-1]["average_return"] if self.evaluations else math.nan

    @contextlib.contextmanager
    def running(self):
        """What ``run`` and the run's last writes happen in: stop signals deferred to safe points,
        the garbage collector off what exists now, console log lines above the progress bar."""
        keep_freed_memory()
        # The deferred stop-signal handler stays on through the checkpoint saved on an interrupt: a
        # SIGINT delivered twice (the terminal's and a parent's) must not cut that save short.
        with self.stop, gc_frozen(), logging_redirect_tqdm([logging.root, LIVE_LOG.parent]):
            yield

    def run(self) -> None:
        """The run to its end (inside ``running``): start, then collect, update and run the triggers
        block by block, then the triggers' final firing."""
        with self._workers():
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
            hook = getattr(trigger, moment, None)  # None: a trigger made before these moments, not a ``Trigger``
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
        self.collection = SupervisedCollector(self._make_collector, self.supervisor, self.watchdog)
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
                fault_point("collected", state.iteration)  # the learner, once the block's work is done
                fault_point("collector_worker", state.iteration,
                            worker=lambda: next(iter(self.collection.pids()), None))
                if state.frames >= cfg.total_frames:
                    break
        finally:
            self.capture_envs()  # between two blocks: what a checkpoint at a stop goes on from
            self.collection.close()
            self.collection = None

    def capture_envs(self) -> None:
        """Note for the next checkpoint the log interval so far and the collector's envs in their episodes
        (``state.envs``), these when they are between two blocks and its workers are all alive (otherwise
        the last note stays)."""
        collection, state = self.collection, self.state
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

    def _make_collector(self, restarts: int) -> CollectorBackend:
        """A started collector backend for the frames still to collect, going on from the envs' episodes
        where the last one left them (``state.envs``), else seeded; after a restart, with a seed stream no
        earlier collector of the run used (its workers' episodes died with them)."""
        cfg, state = self.config, self.state
        seed, snapshot = cfg.seed + state.frames, state.envs
        if restarts:
            seed = int(np.random.SeedSequence([cfg.seed, state.frames, restarts]).generate_state(1)[0])
            snapshot = None
            self.not_exact("a collector worker was restarted: the episodes in progress in its envs, and its "
                           "random generators, died with it")
        elif not cfg.collector.sync:
            self.not_exact("asynchronous collection (collector.sync=false): which weights act in a block, and "
                           "which worker's block comes first, depend on timing")
        with stop_signals_blocked(), self.clock.paused():  # worker start-up is not training time
            backend = self.pipeline.make_backend().start(cfg.total_frames - state.frames,
                                                         max(0, cfg.initial_collect_steps - state.frames), seed,
                                                         restore=snapshot)
        if not backend.restored:  # it numbers trajectories from 0: above the ones stored (RunState.traj_offset)
            state.traj_offset = state.traj_next
        if state.backend_metrics and not restarts:  # what the last collector had gathered for its next row
            backend.load_metrics_state(state.backend_metrics)
        state.backend_metrics = None
        if snapshot is not None and not backend.restored:
            why = why_not_exact(self.pipeline.env) or "its state did not fit this collector"
            notice(f"{cfg.env}: the collector's env cannot be captured ({why}); its episode in progress restarts")
            self.not_exact(f"the env's episode in progress restarted at a resume ({why})")
        return backend

    def not_exact(self, why: str) -> None:
        """Record (once: the first reason) that this run no longer equals an uninterrupted one: summary.json says so."""
        if self.state.inexact is None:
            self.state.inexact = why

    def insert(self, batch: TensorDictBase) -> None:
        """Store a block in the replay buffer, count it, and note the triggers its iterations crossed."""
        cfg, pipeline = self.config, self.pipeline
        # Collectors round their budget up to whole blocks; the run stops at its own.
        batch = batch.reshape(-1)[: cfg.total_frames - self.state.frames]
        keys = pipeline.replay_keys
        if keys is None or TRAJ_IDS in keys:  # stored: unique across the run's collectors (RunState.traj_offset)
            ids = batch.get(TRAJ_IDS, None)
            if ids is not None and ids.numel():
                if self.state.traj_offset:
                    ids = ids + self.state.traj_offset
                    batch.set(TRAJ_IDS, ids)
                self.state.traj_next = max(self.state.traj_next, int(ids.max()) + 1)
        if cfg.n_step == 1:
            stored = batch if keys is None else batch.select(*keys)
        else:  # on the stored keys and what the windows read; the stats below read the steps as taken
            stored = batch if keys is None else batch.select(*keys, TRAJ_IDS, ("next", "done"), strict=False)
            # the loss's own discount (a user's loss_module may have its own)
            stored = n_step_transitions(stored, cfg.n_step, float(pipeline.loss_module.value_estimator.gamma))
            stored = stored if keys is None else stored.select(*keys)
        pipeline.replay_buffer.extend(stored)
        ended = self.interval_stats.add_frames(batch)
        if ended:
            self.recent_returns.extend(self.interval_stats.episode_returns[-ended:])
        self.state.episodes += ended
        pipeline.on_frames(batch.numel())
        before, now = self.state.insert(batch.numel(), cfg)
        self.state.owed = [t.name for t in self.triggers.values() if t.due(before, now, cfg.num_iterations)]
        self.bar.update(now - before)

    def pay_updates(self) -> None:
        """Make the updates the frames so far paid for; push the new weights to collector processes."""
        made = 0
        while self.state.limiter.owed:
            self.stop.check()
            losses = self.pipeline.update_step(sample(self.pipeline.replay_buffer), self.state.updates + 1)
            self.state.updated()
            if fault_point("update", self.state.updates):  # the test hook: a parameter turns NaN here
                next(self.pipeline.loss_module.parameters()).data.fill_(math.nan)
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

    # --- what triggers call ---------------------------------------------------------------------

    def log(self, row: dict[str, Any], at: dict[str, int] | None = None) -> None:
        """Write a metrics row (at the current position unless ``at``): CSV, logger, callbacks."""
        row = {**(at or self.state.position()), **row}
        self.metrics.append(row)
        for key, value in row.items():
            if key != "step" and isinstance(value, (int, float)) and not math.isnan(value):
                self.logger.log_scalar(key, value, step=row["step"])
        for callback in self.callbacks:
            callback(row)

    def finish_early(self, why: str) -> None:
        """End the run after this block's work, as if its last iteration had come: the triggers' final
        firing follows (the last evaluation, export and checkpoint)."""
        self.finished_early = why

    def echo(self, line: str) -> None:
        """A line of the live log (``LIVE_LOG``): above the progress bar when there is one."""
        LIVE_LOG.info(line)

    def speeds(self) -> tuple[float, float]:
        """Env steps and updates per second of training time in this session (evaluations and saving left out)."""
        seconds = self.clock.session_train_seconds()
        if seconds <= 0:
            return math.nan, math.nan
        frames, updates = self._counts_at_start
        return (self.state.frames - frames) / seconds, (self.state.updates - updates) / seconds

    # The built-in triggers' work, for a user's trigger to ask for (the triggers own it).

    def evaluate(self) -> None:
        """Evaluate the policy as it is now: in the background if the run does so, else here."""
        self.triggers[EVAL](self)

    def export(self) -> None:
        self.triggers[EXPORT](self)

    def save(self) -> None:
        self.triggers[SAVE](self)

    def check_finite(self) -> None:
        """``TrainingDiverged`` if a loss since the last log row or a parameter is NaN or infinite."""
        check_finite(self.interval_stats.loss_sums, self.pipeline.loss_module, self.state, self.run_dir)

    @contextlib.contextmanager
    def _workers(self):
        """Close the triggers (the eval trigger stops its evaluator process or Ray actor), the watchdog
        and the progress bar however the run ends (``collect`` stops the collector's processes)."""
        try:
            yield
        finally:
            self.fire("close")
            if self.watchdog is not None:
                self.watchdog.close()
            self.bar.close()
