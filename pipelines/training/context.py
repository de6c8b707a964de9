"""The running loop as a trigger sees it (``LoopContext``): the run's parts, and what a trigger may ask of it.

A trigger is called with the ``Loop``; what it may use of it is this class: the ``Loop`` adds only its own
steps (collect, insert, pay the updates, run the triggers).
"""

from __future__ import annotations

import logging
import math
import sys
from collections import deque
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

from torchrl.record.loggers import Logger
from tqdm.auto import tqdm

from rlpipe.pipelines.artifacts.rundir import MetricsCSV, RunDir
from rlpipe.pipelines.system.runtime import DeferredInterrupt, dropping
from rlpipe.pipelines.training.divergence import check_finite
from rlpipe.pipelines.training.live_report import ReportPage
from rlpipe.pipelines.training.meters import Clock, IntervalStats
from rlpipe.pipelines.training.state import EVAL, EXPORT, SAVE
from rlpipe.pipelines.workers.supervision import SupervisedCollector, Supervisor, Watchdog

if TYPE_CHECKING:
    from rlpipe.pipelines.base import OffPolicyPipeline
    from rlpipe.pipelines.training.triggers import Trigger
    from rlpipe.pipelines.workers.backend import CollectorBackend

__all__ = ["LIVE_LOG", "LoopContext"]

LIVE_LOG = logging.getLogger("rlpipe.train")
"""The live log, the tutorials' printed lines (``step = 1000: AverageReturn = ...``), as INFO records.
``rlpipe train`` shows them on stdout; from Python, ``logging.basicConfig(level=logging.INFO,
format="%(message)s")`` does (a library leaves where its records go to the application)."""


class LoopContext:
    """One run of ``pipeline`` into ``run``, as its triggers see it.

    Attributes a trigger may use: ``pipeline``, ``config``, ``state`` (counters, ``training.state.RunState``),
    ``run_dir`` (the ``RunDir``), ``metrics`` (its ``MetricsCSV``), ``evaluations`` (results so far, oldest
    first), ``triggers`` (the run's triggers by name), ``clock`` (training and wall time), ``interval_stats``
    (losses and episodes since the last log row), ``supervisor`` (workers alive, restarts), ``page`` (the
    report page), ``bar`` (the progress bar), ``stop`` (``stop.check()`` at a safe point of a long trigger),
    ``recent_returns`` (this session's finished training episodes' returns, newest last) and
    ``first_block_unix`` (``time.time()`` when this session's first block of env steps arrived).
    """

    def __init__(self, pipeline: OffPolicyPipeline, run: RunDir, metrics: MetricsCSV, *, evaluations: list[dict],
                 triggers: Sequence[Trigger], logger: Logger, callbacks: Sequence[Callable[[dict], None]] = (),
                 progress: bool = True):
        self.pipeline, self.config, self.state = pipeline, pipeline.config, pipeline.state
        self.run_dir, self.metrics, self.evaluations = run, metrics, evaluations
        self.triggers = {t.name: t for t in triggers}
        self.logger, self.callbacks = logger, list(callbacks)
        self.clock = Clock(self.state.wall_time_s, self.state.train_time_s)  # a resumed run's earlier stretches
        self.interval_stats, self.stop = IntervalStats(), DeferredInterrupt()
        self.page = ReportPage(run.path, evaluations, title=f"{pipeline.algo} on {self.config.env}")
        self.supervisor = Supervisor(self.config.collector.max_restarts, self.config.collector.timeout)
        self.collection: SupervisedCollector | None = None
        self.watchdog: Watchdog | None = None
        self.recent_returns: deque[float] = deque(maxlen=1000)
        self.first_block_unix: float | None = None
        self.finished_early: str | None = None  # why a trigger ended the run before its last iteration
        self._counts_at_start = (self.state.frames, self.state.updates)  # this session's speeds
        # on stderr, dropped where no one can read it (a pipe's reader gone, the terminal closed): the run goes on
        self.bar = tqdm(total=self.config.num_iterations, initial=self.state.iteration, unit="it", disable=not progress,
                        desc=f"{pipeline.algo} {self.config.env}", dynamic_ncols=True, file=dropping(sys.stderr))

    @property
    def collector(self) -> CollectorBackend | None:
        """The collector backend collecting now (None outside ``collect``, or while one is replaced); its
        ``.collector`` is TorchRL's."""
        return None if self.collection is None else self.collection.collector

    @property
    def last_return(self) -> float:
        """The latest evaluation's average return (NaN before the first)."""
        return self.evaluations[-1]["average_return"] if self.evaluations else math.nan

    def log(self, row: dict[str, Any], at: dict[str, int] | None = None) -> None:
        """Write a metrics row (at the current position unless ``at``): CSV (where a key new to metrics.csv
        gets a column), logger, callbacks."""
        row = {**(at or self.state.position()), **row}
        self.metrics.append(row)
        for key, value in row.items():
            if key != "step" and isinstance(value, (int, float)) and not math.isnan(value):
                self.logger.log_scalar(key, value, step=row["step"])
        for callback in self.callbacks:
            callback(row)

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

    def finish_early(self, why: str) -> None:
        """End the run after this block's work, as if its last iteration had come: the triggers' final
        firing follows (the last evaluation, export and checkpoint)."""
        self.finished_early = why

    def check_finite(self) -> None:
        """``TrainingDiverged`` if a loss since the last log row or a parameter is NaN or infinite."""
        check_finite(self.interval_stats.loss_sums, self.pipeline.loss_module, self.state, self.run_dir)

    # The built-in triggers' work, for a user's trigger to ask for (the triggers own it).

    def evaluate(self) -> None:
        """Evaluate the policy as it is now: in the background if the run does so, else here."""
        self.triggers[EVAL](self)

    def export(self) -> None:
        """Export the deterministic policy now (``RUN/policy``)."""
        self.triggers[EXPORT](self)

    def save(self) -> None:
        """Save a checkpoint of where the run is now."""
        self.triggers[SAVE](self)
