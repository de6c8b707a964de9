"""Analysis of finished training runs, by concern:

* :mod:`~rlpipe.pipelines.analysis.runs` reads run directories (``metrics.csv``,
  ``summary.json``, ``config.json``) into the ``records`` and ``curves`` tables;
* :mod:`~rlpipe.pipelines.analysis.stats` computes statistics over seeds (AUC, bootstrap CIs,
  IQM, mean curves with bands);
* :mod:`~rlpipe.pipelines.analysis.plots` draws the figures (``rlpipe plot``, ``rlpipe eval
  --ecdf``, a run's ``returns.png``);
* :mod:`~rlpipe.pipelines.analysis.aggregate` gives the across-env statistics (rliable's IQM with
  stratified-bootstrap CIs, performance profiles, probability of improvement) and
  :mod:`~rlpipe.pipelines.analysis.study` the ablation study's figures and sentences from them;
* :mod:`~rlpipe.pipelines.analysis.ablation_report` writes the ablation report;
* :mod:`~rlpipe.pipelines.analysis.report_pages` writes the HTML pages: a run's ``report.html`` and the
  comparison page of several runs (``rlpipe report``, the ablation's ``report.html``).
"""

from rlpipe.pipelines.analysis.ablation_report import safe_filename, write_ablation_report
from rlpipe.pipelines.analysis.aggregate import (
    aggregate_iqm,
    iqm,
    normalise_scores,
    performance_profile,
    probability_of_improvement,
    stratified_bootstrap_ci,
)
from rlpipe.pipelines.analysis.plots import (
    plot_ecdf,
    plot_return_curves,
    plot_training_returns,
)
from rlpipe.pipelines.analysis.report_pages import write_comparison_report, write_run_report
from rlpipe.pipelines.analysis.runs import (
    CURVE_COLUMNS,
    METRICS_FILE,
    RECORD_COLUMNS,
    collect_runs,
    eval_rows,
    read_metrics,
    read_run_info,
)
from rlpipe.pipelines.analysis.stats import (
    aggregate_curves,
    area_under_curve,
    bootstrap_ci,
    interquartile_mean,
    summarise_runs,
)

__all__ = [
    "METRICS_FILE",
    "RECORD_COLUMNS",
    "CURVE_COLUMNS",
    "read_metrics",
    "eval_rows",
    "read_run_info",
    "area_under_curve",
    "bootstrap_ci",
    "interquartile_mean",
    "iqm",
    "normalise_scores",
    "stratified_bootstrap_ci",
    "aggregate_iqm",
    "performance_profile",
    "probability_of_improvement",
    "collect_runs",
    "summarise_runs",
    "aggregate_curves",
    "safe_filename",
    "write_ablation_report",
    "write_comparison_report",
    "write_run_report",
    "plot_return_curves",
    "plot_ecdf",
    "plot_training_returns",
]
