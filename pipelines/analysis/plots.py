"""Figures of finished runs: learning curves and ECDFs of returns.

* :func:`plot_return_curves` (``rlpipe plot RUN_DIR...``), :func:`plot_ecdf`
  (``rlpipe eval RUN --ecdf``) and :func:`plot_training_returns` (a run's own ``returns.png``);
* the ablation report's figures (:func:`_plot_env_curves`, :func:`_plot_final_ecdfs`), drawn in
  the same styles per variant (:func:`_variant_styles`).

Figures are drawn on :class:`matplotlib.figure.Figure` objects with the Agg canvas, never through
``pyplot``: no display is needed, the global backend is left alone, and no figure is kept in
pyplot's registry, so hundreds of calls leak nothing. Every PNG is written through
:func:`rlpipe.pipelines.artifacts.files.atomic_path`, so a reader never sees a half-written image.
"""

from __future__ import annotations

import io
import math
import os
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib
import numpy as np
import pandas as pd
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from rlpipe.pipelines.analysis.runs import (
    RETURN_COL,
    STEP_COL,
    _metrics_path,
    _run_dir,
    read_metrics,
    read_run_info,
)
from rlpipe.pipelines.artifacts.files import atomic_path

__all__ = [
    "figure_svg", "plot_ecdf", "plot_return_curves", "plot_training_returns", "return_curves_figure",
    "run_returns_figure", "run_series_figure", "runs_returns_figure",
]

_DPI = 100
_REFERENCE_COLOR = "black"
_REFERENCE_LW = 2.8
_VARIANT_LW = 1.5


def _new_figure(figsize: tuple[float, float] = (7.0, 4.5)) -> Figure:
    """A pyplot-free figure on an Agg canvas (nothing to close, nothing registered)."""
    fig = Figure(figsize=figsize, dpi=_DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _save_figure(fig: Figure, out_png: str | os.PathLike) -> Path:
    """Write ``fig`` as PNG to ``out_png`` atomically and release it; returns the path.

    Parent folders are created; the image goes through :func:`atomic_path`.
    """
    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        with atomic_path(out) as tmp:
            fig.savefig(tmp, format="png", dpi=_DPI)
    finally:
        fig.clear()
    return out


def _variant_styles(variants: Iterable[str], reference: str | None) -> dict[str, dict[str, Any]]:
    """Colour, line width and z-order per variant: the reference black and thick, the others
    from a qualitative palette in name order (so colours agree across figures)."""
    others = sorted({str(v) for v in variants} - {reference})
    cmap = matplotlib.colormaps["tab10" if len(others) <= 10 else "tab20"]
    styles = {
        v: {"color": cmap(i % cmap.N), "linewidth": _VARIANT_LW, "zorder": 2}
        for i, v in enumerate(others)
    }
    if reference is not None:
        styles[reference] = {"color": _REFERENCE_COLOR, "linewidth": _REFERENCE_LW, "zorder": 3}
    return styles


def _long_labels(labels: Iterable[str]) -> bool:
    """Whether legend labels are too long to stand beside a plot without squeezing it."""
    return max((len(str(label)) for label in labels), default=0) > 32


def _side_legend(fig: Figure, ax) -> None:
    """The legend right of the axes, or below the figure when its labels are long (config differences)."""
    handles, labels = ax.get_legend_handles_labels()
    if _long_labels(labels):
        fig.legend(handles, labels, loc="outside lower center", fontsize="small", frameon=False)
    else:
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize="small", frameon=False)


def _xy(frame: pd.DataFrame, x: str = STEP_COL) -> tuple[np.ndarray, np.ndarray]:
    """Finite ``(x, average_return)`` pairs of a metrics table, sorted by x."""
    if x not in frame.columns or RETURN_COL not in frame.columns:
        return np.empty(0), np.empty(0)
    xs = pd.to_numeric(frame[x], errors="coerce").to_numpy(dtype=float)
    ys = pd.to_numeric(frame[RETURN_COL], errors="coerce").to_numpy(dtype=float)
    keep = np.isfinite(xs) & np.isfinite(ys)
    xs, ys = xs[keep], ys[keep]
    order = np.argsort(xs, kind="mergesort")
    return xs[order], ys[order]


def _marker(n_points: int) -> str | None:
    return "o" if n_points <= 30 else None


def _fmt(x: float) -> str:
    if x is None or not np.isfinite(x):
        return "n/a"
    return f"{x:.1f}" if abs(x) >= 10 else f"{x:.3f}"


def plot_return_curves(
    run_dirs: Sequence[str | os.PathLike],
    out_png: str | os.PathLike,
    labels: Sequence[str] | None = None,
    *,
    x: str = STEP_COL,
    title: str | None = None,
) -> Path:
    """Average return vs iteration of one or more runs in one PNG (``rlpipe plot RUN_DIR...``): one axis
    per env (returns of different envs share no scale), runs of one env on the same axis.

    Args:
        run_dirs: run directories (or their ``metrics.csv`` paths).
        out_png: where to write the PNG.
        labels: legend labels, one per run; default: each run directory's name.
        x: ``"step"`` (x label "Iterations", the TF-Agents tutorials' plot) or ``"frames"``
            (x label "Environment steps").
        title: figure title; default: each axis is titled with its env id (from
            ``summary.json``/``config.json``).

    Raises:
        ValueError: if a run has no ``metrics.csv`` / no evaluation rows, no runs are given, or
            ``labels`` does not match ``run_dirs`` in length.
    """
    return _save_figure(return_curves_figure(run_dirs, labels, x=x, title=title), out_png)


def return_curves_figure(run_dirs: Sequence[str | os.PathLike], labels: Sequence[str] | None = None, *,
                         x: str = STEP_COL, title: str | None = None) -> Figure:
    """:func:`plot_return_curves`' figure: one axis per env, in the order the envs first come."""
    run_dirs = list(run_dirs)
    if not run_dirs:
        raise ValueError("plot_return_curves needs at least one run directory")
    if labels is not None and len(labels) != len(run_dirs):
        raise ValueError(f"{len(labels)} labels for {len(run_dirs)} runs")
    if x not in (STEP_COL, "frames"):
        raise ValueError(f"x must be 'step' or 'frames', not {x!r}")
    by_env: dict[str, list[tuple[str, Any, Any]]] = {}
    for i, run in enumerate(run_dirs):
        metrics = read_metrics(run)
        xs, ys = _xy(metrics, x)
        if xs.size == 0:
            raise ValueError(f"{_metrics_path(run)}: no evaluation rows with a '{x}' value")
        label = labels[i] if labels is not None else _run_dir(run).name
        env = str(read_run_info(run).get("env") or "env unknown")
        by_env.setdefault(env, []).append((label, xs, ys))
    fig = _new_figure((7.0, 1.0 + 3.5 * len(by_env)))
    axes = fig.subplots(len(by_env), 1, squeeze=False)[:, 0]
    for ax, (env, series) in zip(axes, by_env.items()):
        for label, xs, ys in series:
            ax.plot(xs, ys, marker=_marker(xs.size), markersize=3, linewidth=1.6, label=label)
        ax.set_xlabel("Iterations" if x == STEP_COL else "Environment steps")
        ax.set_ylabel("Average Return")
        ax.set_title(env if title is None or len(by_env) > 1 else title)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize="small")
    if title is not None and len(by_env) > 1:
        fig.suptitle(title)
    return fig


def plot_training_returns(
    metrics_df_or_rows: pd.DataFrame | Sequence[Mapping[str, Any]] | str | os.PathLike,
    out_png: str | os.PathLike,
    title: str,
) -> Path:
    """A run's own ``returns.png``: average return vs iteration (the tutorials' plot).

    Meant to be called by the training loop at every evaluation: it is cheap (well under 0.3 s)
    and draws whatever is there -- one point is drawn as a marker, no evaluation yet gives an
    empty plot saying so rather than an error.

    Args:
        metrics_df_or_rows: the metrics as a DataFrame, a list of row dicts (values may be
            numbers, numeric strings or ``""``/``None`` on log-only rows), or a run directory /
            ``metrics.csv`` path.
        out_png: where to write the PNG.
        title: figure title (e.g. ``"TD3 on Pendulum-v1, seed 0"``).
    """
    data = metrics_df_or_rows
    if isinstance(data, (str, os.PathLike)):
        data = read_metrics(data, eval_only=False)
    elif not isinstance(data, pd.DataFrame):
        data = pd.DataFrame(list(data))
    xs, ys = _xy(data)
    fig = _new_figure((6.4, 4.0))
    ax = fig.add_subplot()
    if xs.size:
        ax.plot(xs, ys, marker=_marker(xs.size), markersize=4, linewidth=1.8, color="tab:blue")
    else:
        ax.text(0.5, 0.5, "no evaluation yet", ha="center", va="center", transform=ax.transAxes)
    ax.set_xlabel("Iterations")
    ax.set_ylabel("Average Return")
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    return _save_figure(fig, out_png)


def plot_ecdf(returns: Iterable[float], out_png: str | os.PathLike, title: str = "") -> Path:
    """ECDF of the episode returns of one trained policy (``rlpipe eval RUN --ecdf``).

    Drawn with matplotlib's ``Axes.ecdf``; the mean return is marked by a dashed vertical line.
    Non-finite returns are dropped.

    Raises:
        ValueError: if there is no finite return.
    """
    x = np.asarray(list(returns) if not isinstance(returns, np.ndarray) else returns, float)
    x = x.ravel()
    x = x[np.isfinite(x)]
    if x.size == 0:
        raise ValueError("plot_ecdf: no finite episode returns to plot")
    fig = _new_figure((6.4, 4.2))
    ax = fig.add_subplot()
    ax.ecdf(x, linewidth=2.0, color="tab:blue", label=f"episodes (n={x.size})")
    ax.axvline(x.mean(), color="tab:red", linestyle="--", linewidth=1.2,
               label=f"mean = {_fmt(float(x.mean()))}")
    ax.set_xlabel("Episode return")
    ax.set_ylabel("Proportion of episodes")
    ax.set_ylim(0.0, 1.02)
    ax.set_title(title or "ECDF of episode returns")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize="small", loc="upper left")
    return _save_figure(fig, out_png)


def _plot_env_curves(
    agg: pd.DataFrame,
    env: str,
    order: Sequence[str],
    styles: Mapping[str, Mapping[str, Any]],
    reference: str | None,
    out_png: Path,
) -> Path:
    return _save_figure(_env_curves_figure(agg, env, order, styles, reference), out_png)


def _env_curves_figure(
    agg: pd.DataFrame,
    env: str,
    order: Sequence[str],
    styles: Mapping[str, Mapping[str, Any]],
    reference: str | None,
) -> Figure:
    """Mean return over seeds per variant on ``env``, with the 95% bootstrap band where n > 1."""
    fig = _new_figure((9.0, 5.0))
    ax = fig.add_subplot()
    for variant in order:
        c = agg[agg["variant"] == variant]
        if c.empty:
            continue
        style = styles[variant]
        n = int(c["n"].iloc[0])
        label = f"{variant} (n={n})" + (" ★" if variant == reference else "")
        ax.plot(c["step"], c["mean"], label=label, marker=_marker(len(c)), markersize=3, **style)
        if n > 1:
            ax.fill_between(
                c["step"], c["ci_low"], c["ci_high"], color=style["color"], alpha=0.18,
                linewidth=0, zorder=style["zorder"] - 1,
            )
    ax.set_xlabel("Iterations")
    ax.set_ylabel("Average Return")
    ax.set_title(f"{env}: mean over seeds, band = 95% bootstrap CI of the mean")
    ax.grid(True, alpha=0.3)
    _side_legend(fig, ax)
    return fig


def _plot_final_ecdfs(
    records: pd.DataFrame,
    envs: Sequence[str],
    orders: Mapping[str, Sequence[str]],
    styles: Mapping[str, Mapping[str, Any]],
    reference: str | None,
    out_png: Path,
) -> Path:
    return _save_figure(_final_ecdfs_figure(records, envs, orders, styles, reference), out_png)


def _final_ecdfs_figure(
    records: pd.DataFrame,
    envs: Sequence[str],
    orders: Mapping[str, Sequence[str]],
    styles: Mapping[str, Mapping[str, Any]],
    reference: str | None,
) -> Figure:
    """One panel per env: the ECDF of final returns over seeds, one line per variant."""
    ncols = min(len(envs), 3)
    nrows = math.ceil(len(envs) / ncols)
    fig = _new_figure((4.8 * ncols + 2.2, 3.8 * nrows))
    axes = fig.subplots(nrows, ncols, squeeze=False).ravel()
    handles: dict[str, Any] = {}
    for ax, env in zip(axes, envs):
        sub = records[records["env"] == env]
        for variant in orders[env]:
            vals = pd.to_numeric(sub.loc[sub["variant"] == variant, "final_return"],
                                 errors="coerce").to_numpy(dtype=float)
            vals = vals[np.isfinite(vals)]
            if vals.size == 0:
                continue
            label = variant + (" ★" if variant == reference else "")
            handles.setdefault(label, ax.ecdf(vals, label=label, **styles[variant]))
        ax.set_title(env)
        ax.set_xlabel("Final return")
        ax.set_ylabel("Proportion of seeds")
        ax.set_ylim(0.0, 1.02)
        ax.grid(True, alpha=0.3)
    for ax in axes[len(envs):]:
        ax.set_visible(False)
    fig.suptitle("ECDF of final returns over seeds")
    below = _long_labels(handles)
    fig.legend(list(handles.values()), list(handles.keys()), loc="outside lower center" if below else "outside right upper",
               fontsize="small", frameon=False)
    return fig


# --- figures for the HTML pages (inline SVG) ----------------------------------------------------


def figure_svg(fig: Figure) -> str:
    """``fig`` as an SVG document (text glyphs drawn as paths: no font needed to view it); releases it."""
    buf = io.StringIO()
    try:
        fig.savefig(buf, format="svg")
    finally:
        fig.clear()
    return buf.getvalue()


def run_returns_figure(evaluations: pd.DataFrame, title: str, baseline: float | None = None,
                       baseline_label: str = "random agent", best: tuple[float, float] | None = None) -> Figure:
    """A run's return curve (the tutorials' plot), with the random agent's return as a dashed line and, where
    ``best`` (step, return) is given, the evaluation whose policy the run exported marked with a star."""
    xs, ys = _xy(evaluations)
    fig = _new_figure((7.0, 4.0))
    ax = fig.add_subplot()
    if xs.size:
        ax.plot(xs, ys, marker=_marker(xs.size), markersize=4, linewidth=1.8, color="tab:blue",
                label="trained policy (AverageReturn)")
    if best is not None:
        ax.plot([best[0]], [best[1]], marker="*", markersize=14, linestyle="none", color="tab:orange",
                label=f"exported policy: the best evaluation (step {best[0]:,.0f})")
    else:
        ax.text(0.5, 0.5, "no evaluation yet", ha="center", va="center", transform=ax.transAxes)
    if baseline is not None and math.isfinite(baseline):
        ax.axhline(baseline, color="tab:gray", linestyle="--", linewidth=1.4,
                   label=f"{baseline_label}: {_fmt(baseline)}")
    ax.set_xlabel("Iterations")
    ax.set_ylabel("Average Return")
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize="small", loc="best")
    return fig


def run_series_figure(metrics: pd.DataFrame, columns: Sequence[str], title: str,
                      labels: Mapping[str, str] | None = None) -> Figure:
    """One small panel per column of ``metrics`` against ``step`` (losses, speeds); empty cells skipped."""
    labels = labels or {}
    present = [c for c in columns if c in metrics.columns and pd.to_numeric(metrics[c], errors="coerce").notna().any()]
    ncols = min(max(len(present), 1), 3)
    nrows = max(1, math.ceil(len(present) / ncols))
    fig = _new_figure((3.6 * ncols + 0.6, 2.7 * nrows + 0.5))
    axes = fig.subplots(nrows, ncols, squeeze=False).ravel()
    if not present:
        axes[0].text(0.5, 0.5, "nothing logged yet", ha="center", va="center", transform=axes[0].transAxes)
        axes[0].set_axis_off()
    steps = pd.to_numeric(metrics.get(STEP_COL, pd.Series(dtype=float)), errors="coerce")
    for ax, col in zip(axes, present):
        ys = pd.to_numeric(metrics[col], errors="coerce")
        keep = steps.notna() & ys.notna()
        xs_, ys_ = steps[keep].to_numpy(float), ys[keep].to_numpy(float)
        ax.plot(xs_, ys_, marker=_marker(xs_.size), markersize=3, linewidth=1.4)
        ax.set_title(labels.get(col, col), fontsize="medium")
        ax.set_xlabel("Iterations", fontsize="small")
        ax.grid(True, alpha=0.3)
    for ax in axes[len(present):]:
        ax.set_visible(False)
    fig.suptitle(title)
    return fig


def runs_returns_figure(series: Sequence[tuple[str, np.ndarray, np.ndarray]], title: str) -> Figure:
    """Each run's own return curve, one line per ``(label, steps, returns)`` (``rlpipe plot`` as a figure)."""
    fig = _new_figure((8.0, 4.5))
    ax = fig.add_subplot()
    many = len(series) > _MAX_LEGEND
    for label, xs, ys in series:
        ax.plot(xs, ys, marker=None if many else _marker(xs.size), markersize=3, linewidth=1.0 if many else 1.6,
                alpha=0.6 if many else 1.0, label=label)
    ax.set_xlabel("Iterations")
    ax.set_ylabel("Average Return")
    ax.set_title(title if not many else f"{title} ({len(series)} runs; the table below names them)")
    ax.grid(True, alpha=0.3)
    if series and not many:
        _side_legend(fig, ax)
    return fig


_MAX_LEGEND = 12
"""more runs than this in one figure: no legend (it would crowd out the plot)"""
