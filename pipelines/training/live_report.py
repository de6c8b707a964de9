"""The run's ``report.html`` and ``returns.png`` as the run writes them: at evaluations and log rows at a bounded
cost, at the end, and when the run stops early (saying so, and how to continue).

A page costs about 0.55 s to write on a 2-core machine and ``returns.png`` 0.13 s more (three SVG figures
and the tables; 1.7 s with 10,000 log rows, measured with ``write_run_report`` on a DQN run directory): too much
for every log row of a fast run, and for every evaluation of one (the DQN tutorial evaluates 21 times in a
~30-s run, and drawing at each would take ~14 s more: BENCHMARKS.md, "Evaluations on the same path"). With ``live_report`` the first log row and the first
evaluation of a run (or of its resumed stretch) write them at once, so that its losses, speeds and first
return show from the start; a later one only when ``MIN_INTERVAL_S`` have passed since they were last written
and at least ``COST_RATIO`` times the last write's cost, so they never take more than about 2% of the run's
time. The run's end (``write(running=False)``) always writes both.
"""

from __future__ import annotations

import time
from pathlib import Path

from rlpipe.pipelines.artifacts.rundir import RunDir

__all__ = ["ReportPage"]

MIN_INTERVAL_S = 30.0
COST_RATIO = 50.0


class ReportPage:
    """``RUN/report.html`` and ``RUN/returns.png`` of the run in ``path``, written by the run.

    ``evaluations`` is the run's list of evaluation results (the loop appends to it); ``title`` the plot's."""

    def __init__(self, path: Path, evaluations: list[dict] | None = None, title: str = ""):
        self.path = Path(path)
        self.evaluations = evaluations if evaluations is not None else []
        self.title = title
        self.written_at: float | None = None  # time.monotonic() of the last write
        self.cost_s = 0.0  # how long the last write took
        self.log_shown = False  # whether a log row has refreshed it yet
        self.evaluation_shown = False  # whether an evaluation has refreshed it yet
        self._plotted = -1  # how many evaluations returns.png shows (-1: not drawn by this run yet)

    def write(self, running: bool = True) -> None:
        """``returns.png`` (where evaluations came since it was drawn) and the page from what the run directory
        holds now; ``running=False``: the run is finishing or stopping early."""
        from rlpipe.pipelines.analysis import plot_training_returns  # matplotlib: imported when first needed
        from rlpipe.pipelines.analysis.report_pages import write_run_report

        start = time.monotonic()
        if len(self.evaluations) != self._plotted:
            plot_training_returns(self.evaluations, RunDir(self.path).returns_png, title=self.title)
            self._plotted = len(self.evaluations)
        write_run_report(self.path, running=running)
        self.written_at = time.monotonic()
        self.cost_s = self.written_at - start

    def due(self) -> bool:
        """Whether a write now keeps within the bound (see the module's docstring)."""
        return (self.written_at is None
                or time.monotonic() - self.written_at >= max(MIN_INTERVAL_S, COST_RATIO * self.cost_s))

    def refresh(self) -> bool:
        """After a log row: write if it is due (the first log row at once); whether it was written."""
        return self._write_if_due("log_shown")

    def evaluated(self) -> bool:
        """After an evaluation: write if it is due (the first evaluation at once); whether it was written."""
        return self._write_if_due("evaluation_shown")

    def _write_if_due(self, shown: str) -> bool:
        if getattr(self, shown) and not self.due():
            return False
        self.write()
        setattr(self, shown, True)
        return True
