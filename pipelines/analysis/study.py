"""The ablation study's across-env part: aggregate figures and the sentence per ingredient.

:func:`study_statistics` turns the runs' ``records`` (and each env's random-agent return) into the
tables of :mod:`rlpipe.pipelines.analysis.aggregate`; :func:`write_study_figures` draws them
(``aggregate_iqm.png``, ``performance_profile.png``, ``probability_of_improvement.png``) and
:func:`ingredient_sentences` says, per left-out ingredient, what the data shows and where the
intervals overlap.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from rlpipe.pipelines.analysis.aggregate import (
    aggregate_iqm,
    compare_to_reference,
    performance_profile,
    score_matrices,
)
from rlpipe.pipelines.analysis.plots import _fmt, _new_figure, _save_figure, _variant_styles
from rlpipe.pipelines.analysis.stats import summarise_runs

__all__ = ["StudyStatistics", "random_scores_of", "study_statistics", "write_study_figures", "ingredient_sentences"]

TAUS = np.linspace(-0.25, 1.5, 71)


@dataclass
class StudyStatistics:
    envs: list[str]
    random: dict[str, float]
    matrices: dict[str, np.ndarray]
    iqm: pd.DataFrame
    improvement: pd.DataFrame
    summary: pd.DataFrame


def random_scores_of(records: pd.DataFrame) -> dict[str, float]:
    """Per env, the mean random-agent return of its runs (each run's ``baseline.json``, played
    before training with ``baseline_episodes`` episodes); envs whose runs have none are left out."""
    found: dict[str, list[float]] = {}
    for row in records.itertuples(index=False):
        run_dir = getattr(row, "run_dir", None)
        if not run_dir:
            continue
        try:
            value = float(json.loads((Path(run_dir) / "baseline.json").read_text())["average_return"])
        except (OSError, ValueError, KeyError, TypeError):
            continue
        if np.isfinite(value):
            found.setdefault(str(row.env), []).append(value)
    return {env: float(np.mean(v)) for env, v in found.items()}


def study_statistics(records: pd.DataFrame, random_scores: dict[str, float], reference: str = "full") -> StudyStatistics:
    table = records.copy()
    table["env"], table["variant"] = table["env"].astype(str), table["variant"].astype(str)
    matrices, envs = score_matrices(table, random_scores, reference)
    return StudyStatistics(envs=envs, random={e: random_scores[e] for e in envs}, matrices=matrices,
                           iqm=aggregate_iqm(matrices), improvement=compare_to_reference(matrices, reference),
                           summary=summarise_runs(table))


def write_study_figures(st: StudyStatistics, out_dir: str | os.PathLike, reference: str = "full") -> list[Path]:
    """``aggregate_iqm.png`` (IQM of normalised scores per variant, 95% CI), ``performance_profile.png``
    and ``probability_of_improvement.png`` (P(reference > variant), 95% CI) in ``out_dir``."""
    out = Path(out_dir)
    styles = _variant_styles(st.matrices, reference)
    envs = ", ".join(st.envs)
    written = []

    fig = _new_figure((7.0, 0.45 * len(st.iqm) + 1.6))
    ax = fig.add_subplot()
    rows = st.iqm.iloc[::-1]
    for i, r in enumerate(rows.itertuples(index=False)):
        color = styles[r.variant]["color"]
        ax.plot([r.ci_low, r.ci_high], [i, i], color=color, linewidth=6, alpha=0.45, solid_capstyle="butt")
        ax.plot([r.iqm], [i], "|", color=color, markersize=14, markeredgewidth=2.5)
    ax.set_yticks(range(len(rows)), list(rows["variant"]))
    ax.axvline(1.0, color="grey", linewidth=0.8, linestyle=":")
    ax.axvline(0.0, color="grey", linewidth=0.8, linestyle=":")
    ax.set_xlabel("IQM of normalised final return (random 0, full 1); bar: 95% CI")
    ax.set_title(f"Aggregate over {envs}", fontsize="medium")
    written.append(_save_figure(fig, out / "aggregate_iqm.png"))

    fig = _new_figure()
    ax = fig.add_subplot()
    for variant, scores in st.matrices.items():
        prof, low, high = performance_profile(scores, TAUS)
        style = styles[variant]
        ax.plot(TAUS, prof, label=variant, color=style["color"], linewidth=style["linewidth"], zorder=style["zorder"])
        ax.fill_between(TAUS, low, high, color=style["color"], alpha=0.15, linewidth=0)
    ax.set_xlabel(r"normalised final return $\tau$")
    ax.set_ylabel(r"fraction of runs with score > $\tau$")
    ax.set_ylim(-0.02, 1.02)
    ax.set_title(f"Performance profiles over {envs}", fontsize="medium")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize="small", frameon=False)
    written.append(_save_figure(fig, out / "performance_profile.png"))

    fig = _new_figure((7.0, 0.45 * max(1, len(st.improvement)) + 1.6))
    ax = fig.add_subplot()
    rows = st.improvement.iloc[::-1]
    for i, r in enumerate(rows.itertuples(index=False)):
        color = styles[r.variant]["color"]
        ax.plot([r.ci_low, r.ci_high], [i, i], color=color, linewidth=6, alpha=0.45, solid_capstyle="butt")
        ax.plot([r.p], [i], "|", color=color, markersize=14, markeredgewidth=2.5)
    ax.set_yticks(range(len(rows)), [f"{reference} > {v}" for v in rows["variant"]])
    ax.axvline(0.5, color="grey", linewidth=0.8, linestyle=":")
    ax.set_xlim(0, 1)
    ax.set_xlabel("probability of improvement P(X > Y); bar: 95% CI")
    ax.set_title(f"Does the full agent beat each ablation? ({envs})", fontsize="medium")
    written.append(_save_figure(fig, out / "probability_of_improvement.png"))
    return written


def _overlap(a: tuple[float, float], b: tuple[float, float]) -> bool:
    return not (a[1] < b[0] or b[1] < a[0])


def ingredient_sentences(st: StudyStatistics, reference: str = "full") -> dict[str, str]:
    """Per variant other than ``reference``, one sentence from the data: on which envs its 95% CI
    of the mean final return lies below or above the full agent's, on which the two overlap, and
    the aggregate IQM and P(full > it) with their intervals."""
    s = st.summary
    iqm = st.iqm.set_index("variant")
    improvement = st.improvement.set_index("variant")
    out = {}
    for variant in sorted(set(s["variant"]) - {reference}):
        worse, better, overlap = [], [], []
        for env in sorted(set(s["env"])):
            ref = s[(s["env"] == env) & (s["variant"] == reference)]
            row = s[(s["env"] == env) & (s["variant"] == variant)]
            if ref.empty or row.empty:
                continue
            r, v = ref.iloc[0], row.iloc[0]
            text = (f"{env} ({_fmt(v['mean'])} [{_fmt(v['ci_low'])}, {_fmt(v['ci_high'])}] against "
                    f"{_fmt(r['mean'])} [{_fmt(r['ci_low'])}, {_fmt(r['ci_high'])}])")
            if _overlap((r["ci_low"], r["ci_high"]), (v["ci_low"], v["ci_high"])):
                overlap.append(env)
            elif v["ci_high"] < r["ci_low"]:
                worse.append(text)
            else:
                better.append(text)
        parts = []
        if worse:
            parts.append("scores lower than the full agent, intervals apart, on " + "; ".join(worse))
        if better:
            parts.append("scores higher than the full agent, intervals apart, on " + "; ".join(better))
        if overlap:
            parts.append("its interval overlaps the full agent's on " + ", ".join(overlap)
                         + " (no difference shown there at this budget and seed count)")
        sentence = f"Leaving out {variant.removeprefix('no_').replace('_', ' ')} (`{variant}`): " + "; ".join(parts)
        if variant in iqm.index and reference in iqm.index and np.isfinite(iqm.loc[variant, "iqm"]):
            a, f = iqm.loc[variant], iqm.loc[reference]
            apart = not _overlap((a["ci_low"], a["ci_high"]), (f["ci_low"], f["ci_high"]))
            sentence += (f". Across envs its normalised IQM is {a['iqm']:.2f} [{a['ci_low']:.2f}, {a['ci_high']:.2f}] "
                         f"against the full agent's {f['iqm']:.2f} [{f['ci_low']:.2f}, {f['ci_high']:.2f}] "
                         f"({'intervals apart' if apart else 'intervals overlap'})")
        if variant in improvement.index:
            p = improvement.loc[variant]
            verdict = ("the full agent is better" if p["ci_low"] > 0.5 else
                       "the ablation is better" if p["ci_high"] < 0.5 else "the interval includes 0.5: no winner shown")
            sentence += f"; P({reference} > {variant}) = {p['p']:.2f} [{p['ci_low']:.2f}, {p['ci_high']:.2f}], {verdict}"
        out[variant] = sentence + "."
    return out
