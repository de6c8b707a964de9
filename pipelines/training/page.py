"""The run's ``report.html`` as the run writes it: at every evaluation, with the log rows at a bounded cost,
and once more when the run stops early (saying so, and how to continue).

A page costs about 0.9 s to write on this 2-core machine (three SVG figures and the tables; 1.7 s with
10,000 log rows, measured with ``write_run_report`` on a DQN run directory), too much for every log row
of a fast run: the first log row of a run (or of its resumed stretch) refreshes it, so that its losses and
speeds show from the start; a later one only when ``MIN_INTERVAL_S`` have passed since it was last written
and at least ``COST_RATIO`` times the last write's cost, so the page never takes more than about 2% of
the run's time.
"""

from __future__ import annotations

import time
from pathlib import Path

__all__ = ["ReportPage"]

MIN_INTERVAL_S = 30.0
COST_RATIO = 50.0


class ReportPage:
    """``RUN/report.html`` of the run in ``path``, written by the run."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.written_at: float | None = None  # time.monotonic() of the last write
        self.cost_s = 0.0  # how long the last write took
        self.log_shown = False  # whether a log row has refreshed it yet

    def write(self, running: bool = True) -> None:
        """The page from what the run directory holds now; ``running=False``: the run is stopping early."""
        from rlpipe.pipelines.analysis.pages import write_run_report  # matplotlib: imported when first needed

        start = time.monotonic()
        write_run_report(self.path, running=running)
        self.written_at = time.monotonic()
        self.cost_s = self.written_at - start

    def refresh(self) -> bool:
        """After a log row: write the page if it is due (see the module's docstring); whether it was written."""
        if self.log_shown and time.monotonic() - self.written_at < max(MIN_INTERVAL_S, COST_RATIO * self.cost_s):
            return False
        self.write()
        self.log_shown = True
        return True
