"""The ablation report: ``ablation.csv``, ``ablation.md`` and its figures, from run tables.

:func:`write_ablation_report` takes the ``records`` and ``curves`` tables of
:func:`rlpipe.pipelines.analysis.runs.collect_runs` (the TD3 leave-one-out ablation: variants
``full``, ``no_clipped_double_q``, ...) and writes a table per env with the statistics of
:mod:`rlpipe.pipelines.analysis.stats`, learning curves and ECDFs of the final returns.
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import pandas as pd

from rlpipe.pipelines.analysis.aggregate import AGG_RESAMPLES
from rlpipe.pipelines.analysis.plots import (
    _fmt,
    _plot_env_curves,
    _plot_final_ecdfs,
    _variant_styles,
)
from rlpipe.pipelines.analysis.report_pages import REPORT_FILE, write_comparison_page
from rlpipe.pipelines.analysis.runs import RECORD_COLUMNS
from rlpipe.pipelines.analysis.stats import (
    BOOTSTRAP_SEED,
    N_RESAMPLES,
    N_RESAMPLES_BAND,
    aggregate_curves,
    summarise_runs,
)
from rlpipe.pipelines.analysis.study import (
    ingredient_sentences,
    random_scores_of,
    study_statistics,
    write_study_figures,
)
from rlpipe.pipelines.artifacts.files import write_text_atomic

__all__ = ["safe_filename", "write_ablation_report"]


def safe_filename(name: Any) -> str:
    """A file-name-safe form of ``name``: runs of characters other than letters, digits, ``.``,
    ``_`` and ``-`` become ``_``; leading dots/underscores are stripped (``rlpipe/MinitaurBullet-v0``
    -> ``rlpipe_MinitaurBullet-v0``)."""
    safe = re.sub(r"[^A-Za-z0-9._-]+", "_", str(name)).strip("._")
    return safe or "unnamed"


def _markdown_report(
    summary: pd.DataFrame,
    envs: Sequence[str],
    curve_files: Mapping[str, str],
    reference: str | None,
    n_runs: int,
) -> str:
    lines = [
        "# Ablation report",
        "",
        f"{n_runs} runs, {len(envs)} env(s), {summary['variant'].nunique()} variant(s). "
        f"Reference variant: `{reference}` (bold, ★).",
        "",
        "How the numbers were made:",
        "",
        "- **final return**: the average return of a run's last evaluation (the last row of "
        "its `metrics.csv` with a non-empty `average_return`).",
        "- **n**: runs (seeds) of the variant; **mean**: mean final return over those seeds.",
        f"- **95% CI**: 95% percentile bootstrap confidence interval of the mean over seeds "
        f"(`scipy.stats.bootstrap`, {N_RESAMPLES} resamples, seed {BOOTSTRAP_SEED}); for "
        "n = 1 it is the value itself.",
        "- **IQM**: interquartile mean of the final returns over seeds (`scipy.stats.trim_mean`, "
        "25% cut from each end; the plain mean when n < 4).",
        "- **AUC**: normalised area under the learning curve (trapezoid over iterations divided "
        "by the iteration span, i.e. the mean evaluation return over training), averaged over "
        "seeds.",
        "- Rows are sorted by mean final return, best first.",
        "- Learning curves (`curves_<env>.png`): mean over seeds per variant vs iteration; seeds "
        "are linearly interpolated onto the union of their evaluation steps within the range "
        "all seeds cover; the shaded band is the 95% percentile bootstrap CI of the mean "
        f"({N_RESAMPLES_BAND} resamples) at each step. `ecdf_final_returns.png`: ECDF of the "
        "final returns per variant.",
        "",
    ]
    for env in envs:
        lines += [f"## {env}", ""]
        if env in curve_files:
            lines += [f"![learning curves on {env}]({curve_files[env]})", ""]
        lines += [
            "| variant | n | mean final return | 95% CI | IQM | AUC |",
            "|:--|--:|--:|:-:|--:|--:|",
        ]
        for row in summary[summary["env"] == env].itertuples(index=False):
            name = f"`{row.variant}`"
            if row.variant == reference:
                name = f"**{row.variant}** ★"
            ci = f"[{_fmt(row.ci_low)}, {_fmt(row.ci_high)}]"
            lines.append(
                f"| {name} | {row.n} | {_fmt(row.mean)} | {ci} | {_fmt(row.iqm)} "
                f"| {_fmt(row.auc_mean)} |"
            )
        lines.append("")
    return "\n".join(lines)


def write_ablation_report(
    records: pd.DataFrame,
    curves: pd.DataFrame | Mapping | None,
    out_dir: str | os.PathLike,
    reference_variant: str = "full",
    random_scores: Mapping[str, float] | None = None,
) -> list[Path]:
    """Write the ablation study's tables and figures into ``out_dir``.

    Args:
        records: one row per run with columns ``env``, ``variant``, ``seed``, ``final_return``,
            ``auc`` (see :func:`collect_runs`).
        curves: learning curves, in any form :func:`aggregate_curves` takes (long DataFrame with
            ``env``, ``variant``, ``seed``, ``step``, ``average_return``, or a dict keyed by
            ``(env, variant, seed)``); ``None`` skips the curve figures.
        out_dir: output folder (created).
        reference_variant: the full agent, marked in the table and drawn black and thick.
        random_scores: each env's random-agent return (normalised score 0; default: the runs'
            ``baseline.json``, see :func:`~rlpipe.pipelines.analysis.study.random_scores_of`).
            With it and the reference variant, the across-env statistics are written too.

    Writes:
        * ``ablation.csv`` -- ``env, variant, seed, final_return, auc``, one row per run;
        * ``ablation.md`` -- per env a Markdown table (variant, n, mean final return, 95% CI,
          IQM, AUC) sorted by mean, the reference variant in bold with a ★, under a header
          saying how the numbers were made (see :func:`summarise_runs`);
        * ``curves_<env>.png`` per env with curve data (env id made safe by
          :func:`safe_filename`) -- mean over seeds per variant with a shaded 95% percentile
          bootstrap band (see :func:`aggregate_curves` for the step alignment);
        * ``ecdf_final_returns.png`` -- one panel per env, one ECDF per variant;
        * across envs (where the reference and a random score exist for some env):
          ``aggregate.csv`` (per variant the IQM of normalised final returns with its stratified-
          bootstrap 95% CI and P(reference > variant) with its CI), ``aggregate_iqm.png``,
          ``performance_profile.png``, ``probability_of_improvement.png``, and in ``ablation.md``
          and on the page one sentence per ingredient (:func:`~rlpipe.pipelines.analysis.study.ingredient_sentences`);
        * ``report.html`` -- the same tables and figures on one page that opens from disk, with a
          table of the runs linking to each run's own ``report.html`` (see
          :func:`~rlpipe.pipelines.analysis.report_pages.write_comparison_page`).

    Returns:
        the paths written: csv, md, the curve PNGs (env order), the ECDF PNG, the HTML page.
    """
    missing = [c for c in RECORD_COLUMNS if c not in records.columns]
    if missing:
        raise ValueError(f"records lack column(s) {missing}; have {list(records.columns)}")
    if records.empty:
        raise ValueError("write_ablation_report: no runs in records")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    table = records[RECORD_COLUMNS].copy()
    table["env"] = table["env"].astype(str)
    table["variant"] = table["variant"].astype(str)
    table = table.sort_values(["env", "variant", "seed"], kind="mergesort").reset_index(drop=True)
    summary = summarise_runs(table)
    envs = sorted(table["env"].unique())
    orders = {env: list(summary.loc[summary["env"] == env, "variant"]) for env in envs}
    reference = reference_variant if reference_variant in set(table["variant"]) else None

    agg = aggregate_curves(curves) if curves is not None else aggregate_curves(None)
    if not agg.empty:
        agg["env"] = agg["env"].astype(str)
        agg["variant"] = agg["variant"].astype(str)
    styles = _variant_styles(set(table["variant"]) | set(agg["variant"]), reference_variant)

    curve_files: dict[str, str] = {}
    used: set[str] = set()
    for env in envs:
        stem = base = f"curves_{safe_filename(env)}"
        i = 2
        while stem in used:  # two env ids that sanitise to the same name
            stem, i = f"{base}_{i}", i + 1
        used.add(stem)
        curve_files[env] = f"{stem}.png"

    written: list[Path] = []
    csv_path = out / "ablation.csv"
    write_text_atomic(csv_path, table.to_csv(index=False))
    written.append(csv_path)

    curve_paths = []
    for env in envs:
        env_agg = agg[agg["env"] == env]
        if env_agg.empty:
            curve_files.pop(env)
            continue
        order = orders[env] + sorted(set(env_agg["variant"]) - set(orders[env]))
        curve_paths.append(
            _plot_env_curves(env_agg, env, order, styles, reference, out / curve_files[env])
        )

    scores = dict(random_scores) if random_scores is not None else random_scores_of(records)
    study = study_statistics(table, scores, reference) if reference is not None else None
    if study is not None and not study.envs:
        study = None
    sentences = ingredient_sentences(study, reference) if study is not None else {}
    md = _markdown_report(summary, envs, curve_files, reference, len(table))
    aggregate_paths = []
    if study is not None:
        md += _markdown_aggregate(study, reference, sentences)
        aggregate = study.iqm.merge(study.improvement.rename(
            columns={"p": f"p_{reference}_better", "ci_low": "p_ci_low", "ci_high": "p_ci_high"}), on="variant", how="left")
        csv_agg = out / "aggregate.csv"
        write_text_atomic(csv_agg, aggregate.to_csv(index=False))
        aggregate_paths = [csv_agg, *write_study_figures(study, out, reference)]
    md_path = out / "ablation.md"
    write_text_atomic(md_path, md)
    written.append(md_path)
    written += curve_paths
    written.append(
        _plot_final_ecdfs(table, envs, orders, styles, reference, out / "ecdf_final_returns.png")
    )
    written += aggregate_paths
    notes = ["Each variant leaves one ingredient out of the full agent (the TD3 tutorial's exercise)."] \
        if reference == "full" else []
    if study is not None:
        notes.append("Across envs (normalised: random agent 0, full agent's mean final return 1; IQM with "
                     "stratified-bootstrap 95% CIs): " + ", ".join(
                         f"{r.variant} {r.iqm:.2f} [{r.ci_low:.2f}, {r.ci_high:.2f}]" for r in study.iqm.itertuples())
                     + ". Figures beside this page: aggregate_iqm.png, performance_profile.png, "
                     "probability_of_improvement.png.")
    notes += list(sentences.values())
    written.append(write_comparison_page(
        records, curves, out / REPORT_FILE,
        reference=reference_variant, title="Ablation report", notes=notes))
    return written


def _markdown_aggregate(study, reference: str, sentences: Mapping[str, str]) -> str:
    improvement = study.improvement.set_index("variant")
    lines = [
        "## Across envs",
        "",
        f"Scores normalised per env: the random agent's return (its runs' `baseline.json`) is 0, the mean "
        f"final return of `{reference}` is 1. Random returns: "
        + ", ".join(f"{env} {_fmt(v)}" for env, v in study.random.items()) + ".",
        "IQM = interquartile mean of all runs of all envs; 95% CIs from a stratified bootstrap (each env's "
        f"seeds resampled on their own, {AGG_RESAMPLES} resamples; rliable's method). P({reference} > X) = the "
        "probability that a run of the full agent beats a run of X on an env, averaged over envs (1,000 resamples).",
        "",
        "![aggregate IQM](aggregate_iqm.png) ![performance profiles](performance_profile.png) "
        "![probability of improvement](probability_of_improvement.png)",
        "",
        f"| variant | runs | IQM (normalised) | 95% CI | P({reference} > variant) | 95% CI |",
        "|:--|--:|--:|:-:|--:|:-:|",
    ]
    for r in study.iqm.itertuples(index=False):
        name = f"**{r.variant}** ★" if r.variant == reference else f"`{r.variant}`"
        p = improvement.loc[r.variant] if r.variant in improvement.index else None
        pcol = f"{p['p']:.2f} | [{p['ci_low']:.2f}, {p['ci_high']:.2f}]" if p is not None else "— | —"
        lines.append(f"| {name} | {r.n} | {r.iqm:.2f} | [{r.ci_low:.2f}, {r.ci_high:.2f}] | {pcol} |")
    lines += ["", "### What each ingredient does here", ""]
    lines += [f"- {s}" for s in sentences.values()]
    return "\n".join(lines) + "\n"
