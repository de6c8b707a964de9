"""Analysis of finished training runs: metrics, summary statistics, ablation reports, plots.

Every training run writes a run directory with

* ``metrics.csv`` -- one row per log point; columns ``step`` (iteration), ``frames``,
  ``average_return``, ``average_episode_length``, ``loss_*``, ``steps_per_s``, ... Rows whose
  ``average_return`` is empty are log-only rows; the others are *evaluation rows*.
* ``summary.json`` -- ``{"algo", "env", "seed", "final_average_return", "frames", ...}``.
* ``config.json`` -- the resolved config (keys include ``"env"`` and ``"seed"``).

This module turns such directories into numbers and figures:

* :func:`read_metrics`, :func:`eval_rows`, :func:`read_run_info` read one run;
* :func:`area_under_curve` is the normalised area under a learning curve;
* :func:`collect_runs` turns many run directories into the ``records`` and ``curves`` tables
  that :func:`summarise_runs`, :func:`aggregate_curves` and :func:`write_ablation_report` take
  (the TD3 leave-one-out ablation: variants ``full``, ``no_clipped_double_q``, ...);
* :func:`plot_return_curves` (``rlpipe plot RUN_DIR...``), :func:`plot_ecdf`
  (``rlpipe eval RUN --ecdf``) and :func:`plot_training_returns` (a run's own ``returns.png``).

Statistics come from SciPy: 95% confidence intervals are percentile bootstraps of the mean
(:func:`scipy.stats.bootstrap`, fixed seed, so every report is reproducible) and the
interquartile mean is :func:`scipy.stats.trim_mean` with 25% cut from each end.

Figures are drawn on :class:`matplotlib.figure.Figure` objects with the Agg canvas, never through
``pyplot``: no display is needed, the global backend is left alone, and no figure is kept in
pyplot's registry, so hundreds of calls leak nothing. Every PNG is written to a temporary file in
the destination folder and moved into place with :func:`os.replace`, so a reader never sees a
half-written image.
"""

from __future__ import annotations

import contextlib
import inspect
import json
import math
import os
import re
import tempfile
import warnings
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib
import numpy as np
import pandas as pd
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from scipy import stats

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
    "collect_runs",
    "summarise_runs",
    "aggregate_curves",
    "safe_filename",
    "write_ablation_report",
    "plot_return_curves",
    "plot_ecdf",
    "plot_training_returns",
]

METRICS_FILE = "metrics.csv"
SUMMARY_FILE = "summary.json"
CONFIG_FILE = "config.json"
RETURN_COL = "average_return"
STEP_COL = "step"

#: Columns of the per-run table (``records``) and of ``ablation.csv``.
RECORD_COLUMNS = ["env", "variant", "seed", "final_return", "auc"]
#: Columns of the long learning-curve table (``curves``).
CURVE_COLUMNS = ["env", "variant", "seed", "step", "average_return"]

CONFIDENCE_LEVEL = 0.95
N_RESAMPLES = 9999  # for the per-variant table
N_RESAMPLES_BAND = 2000  # for the learning-curve bands (one CI per plotted step)
BOOTSTRAP_SEED = 0
IQM_CUT = 0.25

_NUMERIC_COLUMNS = ("step", "frames", "average_return", "average_episode_length")
_DPI = 100
_REFERENCE_COLOR = "black"
_REFERENCE_LW = 2.8
_VARIANT_LW = 1.5


# --------------------------------------------------------------------------- reading runs


def _metrics_path(run_dir: str | os.PathLike) -> Path:
    """``run_dir/metrics.csv``; a path that already names a ``.csv`` file is taken as is."""
    path = Path(run_dir)
    return path if path.suffix == ".csv" else path / METRICS_FILE


def _run_dir(run_dir: str | os.PathLike) -> Path:
    path = Path(run_dir)
    return path.parent if path.suffix == ".csv" else path


def eval_rows(metrics: pd.DataFrame) -> pd.DataFrame:
    """The evaluation rows of a metrics table: ``step`` and ``average_return`` both present.

    Log-only rows (empty ``average_return``) are dropped and the rest is sorted by step
    (stable, so repeated steps keep their file order). The index is reset.
    """
    missing = [c for c in (STEP_COL, RETURN_COL) if c not in metrics.columns]
    if missing:
        raise ValueError(f"metrics table has no column(s) {missing}")
    df = metrics.copy()
    for col in (STEP_COL, RETURN_COL):
        df[col] = pd.to_numeric(df[col], errors="coerce")
    df = df[df[STEP_COL].notna() & df[RETURN_COL].notna()]
    return df.sort_values(STEP_COL, kind="mergesort").reset_index(drop=True)


def read_metrics(run_dir: str | os.PathLike, eval_only: bool = True) -> pd.DataFrame:
    """Read ``run_dir/metrics.csv`` into a DataFrame.

    Args:
        run_dir: a run directory, or the path of a metrics CSV file itself.
        eval_only: keep only evaluation rows (see :func:`eval_rows`); with ``False`` every row is
            returned in file order (log-only rows have NaN in ``average_return``).

    Empty cells become NaN and the columns ``step``, ``frames``, ``average_return`` and
    ``average_episode_length`` (where present) are numeric.

    Raises:
        ValueError: naming the path, if the file is missing or empty, lacks the ``step`` or
            ``average_return`` column, or (with ``eval_only``) has no evaluation rows.
    """
    path = _metrics_path(run_dir)
    if not path.is_file():
        raise ValueError(f"{path}: no {path.name} here (the run wrote no metrics)")
    try:
        df = pd.read_csv(path)
    except pd.errors.EmptyDataError:
        raise ValueError(f"{path}: file is empty (no header and no rows)") from None
    missing = [c for c in (STEP_COL, RETURN_COL) if c not in df.columns]
    if missing:
        raise ValueError(f"{path}: missing column(s) {missing}; header is {list(df.columns)}")
    for col in _NUMERIC_COLUMNS:
        if col in df.columns:
            df[col] = pd.to_numeric(df[col], errors="coerce")
    if not eval_only:
        return df
    df = eval_rows(df)
    if df.empty:
        raise ValueError(
            f"{path}: no evaluation rows ('{RETURN_COL}' is empty in every row; "
            "the run was stopped before its first evaluation?)"
        )
    return df


def read_run_info(run_dir: str | os.PathLike) -> dict[str, Any]:
    """``config.json`` updated with ``summary.json`` of a run (either may be missing: ``{}``).

    Files that are absent or not valid JSON objects are ignored.
    """
    base = _run_dir(run_dir)
    info: dict[str, Any] = {}
    for name in (CONFIG_FILE, SUMMARY_FILE):
        try:
            data = json.loads((base / name).read_text())
        except (OSError, ValueError):
            continue
        if isinstance(data, dict):
            info.update(data)
    return info


# --------------------------------------------------------------------------- statistics


def area_under_curve(steps: Sequence[float], returns: Sequence[float]) -> float:
    """Normalised area under a learning curve: the mean return over training.

    The trapezoid integral of ``returns`` over ``steps`` divided by the step span
    (last step - first step). Points are sorted by step and non-finite pairs dropped first. A
    single point (or a zero span) gives the mean of the returns; no points gives NaN.
    """
    x = np.asarray(steps, dtype=float).ravel()
    y = np.asarray(returns, dtype=float).ravel()
    if x.shape != y.shape:
        raise ValueError(f"steps and returns differ in length ({x.size} vs {y.size})")
    keep = np.isfinite(x) & np.isfinite(y)
    x, y = x[keep], y[keep]
    if x.size == 0:
        return float("nan")
    order = np.argsort(x, kind="mergesort")
    x, y = x[order], y[order]
    span = x[-1] - x[0]
    if x.size == 1 or span <= 0:
        return float(np.mean(y))
    return float(np.trapezoid(y, x) / span)


def _rng_kwargs(seed: int) -> dict[str, Any]:
    """Seed argument for :func:`scipy.stats.bootstrap` (``rng`` in SciPy >= 1.15, else
    ``random_state``)."""
    rng = np.random.default_rng(seed)
    params = inspect.signature(stats.bootstrap).parameters
    return {"rng": rng} if "rng" in params else {"random_state": rng}


def bootstrap_ci(
    values: Iterable[float],
    confidence_level: float = CONFIDENCE_LEVEL,
    n_resamples: int = N_RESAMPLES,
    seed: int = BOOTSTRAP_SEED,
) -> tuple[float, float]:
    """Percentile-bootstrap confidence interval of the mean of ``values``.

    Uses :func:`scipy.stats.bootstrap` (``method="percentile"``) with a fixed seed, so the
    same values always give the same interval. Non-finite values are dropped. With one value (or
    all values equal) the interval is that value; with none it is ``(nan, nan)``.
    """
    x = np.asarray(list(values) if not isinstance(values, np.ndarray) else values, dtype=float)
    x = x.ravel()
    x = x[np.isfinite(x)]
    if x.size == 0:
        return (float("nan"), float("nan"))
    if x.size == 1 or np.all(x == x[0]):
        return (float(x[0]), float(x[0]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", getattr(stats, "DegenerateDataWarning", RuntimeWarning))
        res = stats.bootstrap(
            (x,),
            np.mean,
            confidence_level=confidence_level,
            n_resamples=n_resamples,
            method="percentile",
            vectorized=True,
            **_rng_kwargs(seed),
        )
    return (float(res.confidence_interval.low), float(res.confidence_interval.high))


def interquartile_mean(values: Iterable[float]) -> float:
    """Interquartile mean: :func:`scipy.stats.trim_mean` cutting 25% from each end.

    Non-finite values are dropped; NaN if none is left. With fewer than 4 values nothing is cut
    and this is the plain mean.
    """
    x = np.asarray(list(values) if not isinstance(values, np.ndarray) else values, dtype=float)
    x = x.ravel()
    x = x[np.isfinite(x)]
    if x.size == 0:
        return float("nan")
    return float(stats.trim_mean(x, IQM_CUT))


def summarise_runs(
    records: pd.DataFrame,
    confidence_level: float = CONFIDENCE_LEVEL,
    n_resamples: int = N_RESAMPLES,
    seed: int = BOOTSTRAP_SEED,
) -> pd.DataFrame:
    """Per (env, variant) statistics of the final returns over seeds.

    Args:
        records: one row per run with columns ``env``, ``variant``, ``seed``, ``final_return``,
            ``auc`` (as made by :func:`collect_runs`); extra columns are ignored.

    Returns:
        columns ``env``, ``variant``, ``n`` (runs with a finite final return), ``mean``, ``std``
        (sample std, NaN for n=1), ``ci_low``/``ci_high`` (95% percentile bootstrap CI of the
        mean, see :func:`bootstrap_ci`; equal to the value for n=1), ``iqm``
        (:func:`interquartile_mean`) and ``auc_mean`` (mean AUC over seeds). Envs are sorted by
        name and, within an env, variants by ``mean`` descending (NaN last, ties by name).
    """
    missing = [c for c in RECORD_COLUMNS if c not in records.columns]
    if missing:
        raise ValueError(f"records lack column(s) {missing}; have {list(records.columns)}")
    rows = []
    for (env, variant), group in records.groupby(["env", "variant"], sort=True):
        final = pd.to_numeric(group["final_return"], errors="coerce").to_numpy(dtype=float)
        final = final[np.isfinite(final)]
        auc = pd.to_numeric(group["auc"], errors="coerce").to_numpy(dtype=float)
        auc = auc[np.isfinite(auc)]
        low, high = bootstrap_ci(final, confidence_level, n_resamples, seed)
        rows.append(
            {
                "env": env,
                "variant": variant,
                "n": int(final.size),
                "mean": float(final.mean()) if final.size else float("nan"),
                "std": float(final.std(ddof=1)) if final.size > 1 else float("nan"),
                "ci_low": low,
                "ci_high": high,
                "iqm": interquartile_mean(final),
                "auc_mean": float(auc.mean()) if auc.size else float("nan"),
            }
        )
    columns = ["env", "variant", "n", "mean", "std", "ci_low", "ci_high", "iqm", "auc_mean"]
    out = pd.DataFrame(rows, columns=columns)
    if out.empty:
        return out
    out = out.sort_values(
        ["env", "mean", "variant"], ascending=[True, False, True], na_position="last"
    )
    return out.reset_index(drop=True)


# --------------------------------------------------------------------------- many runs


def _variant_of(
    run_dir: Path, info: Mapping[str, Any], variant: Mapping | Callable | str | None
) -> str:
    if isinstance(variant, str):
        return variant
    if callable(variant):
        return str(variant(run_dir))
    if isinstance(variant, Mapping):
        for key in (run_dir, str(run_dir), run_dir.name):
            if key in variant:
                return str(variant[key])
    for key in ("variant", "ablation"):
        if isinstance(info.get(key), str) and info[key]:
            return info[key]
    return run_dir.name


def collect_runs(
    run_dirs: Iterable[str | os.PathLike],
    variant: Mapping | Callable[[Path], str] | str | None = None,
    skip_invalid: bool = False,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Read many run directories into the ``records`` and ``curves`` tables.

    Args:
        run_dirs: run directories (each with ``metrics.csv``; ``summary.json`` /
            ``config.json`` give ``env`` and ``seed``).
        variant: how each run's variant name is found: a string (all runs), a mapping from run
            directory (path or name) to name, or a callable ``run_dir -> name``. Otherwise (and
            for runs a mapping lacks) the ``"variant"`` (or string ``"ablation"``) key of
            ``summary.json``/``config.json`` is used, and failing that the directory name.
        skip_invalid: warn about and skip runs without evaluation rows instead of raising.

    Returns:
        ``(records, curves)``: ``records`` has one row per run with columns
        :data:`RECORD_COLUMNS` plus ``frames`` and ``run_dir`` -- ``final_return`` is the
        average return of the run's last evaluation and ``auc`` the :func:`area_under_curve` of
        its evaluations; ``curves`` is long, one row per evaluation, with columns
        :data:`CURVE_COLUMNS` plus ``frames``. A run whose env is unknown gets ``"unknown"``;
        a missing seed is NaN.
    """
    records, curves = [], []
    for raw in run_dirs:
        run_dir = _run_dir(raw)
        try:
            metrics = read_metrics(raw)
        except ValueError as err:
            if not skip_invalid:
                raise
            warnings.warn(f"skipping run: {err}", stacklevel=2)
            continue
        info = read_run_info(run_dir)
        env = str(info.get("env") or "unknown")
        seed = info.get("seed", float("nan"))
        name = _variant_of(run_dir, info, variant)
        last = metrics.iloc[-1]
        frames = last["frames"] if "frames" in metrics.columns else float("nan")
        records.append(
            {
                "env": env,
                "variant": name,
                "seed": seed,
                "final_return": float(last[RETURN_COL]),
                "auc": area_under_curve(metrics[STEP_COL], metrics[RETURN_COL]),
                "frames": frames,
                "run_dir": str(run_dir),
            }
        )
        curve = pd.DataFrame(
            {
                "env": env,
                "variant": name,
                "seed": seed,
                "step": metrics[STEP_COL].to_numpy(),
                "average_return": metrics[RETURN_COL].to_numpy(),
                "frames": metrics["frames"].to_numpy()
                if "frames" in metrics.columns
                else np.nan,
            }
        )
        curves.append(curve)
    records_df = pd.DataFrame(records, columns=[*RECORD_COLUMNS, "frames", "run_dir"])
    curves_df = (
        pd.concat(curves, ignore_index=True)
        if curves
        else pd.DataFrame(columns=[*CURVE_COLUMNS, "frames"])
    )
    return records_df, curves_df


def _curves_frame(curves: pd.DataFrame | Mapping | None) -> pd.DataFrame:
    """Normalise the ``curves`` argument to a long DataFrame with :data:`CURVE_COLUMNS`."""
    if curves is None:
        return pd.DataFrame(columns=CURVE_COLUMNS)
    if isinstance(curves, pd.DataFrame):
        df = curves
    elif isinstance(curves, Mapping):
        parts = []
        for key, value in curves.items():
            if not (isinstance(key, tuple) and len(key) == 3):
                raise ValueError(f"curves dict keys must be (env, variant, seed); got {key!r}")
            env, variant, seed = key
            if isinstance(value, pd.DataFrame) or isinstance(value, Mapping):
                steps, returns = value[STEP_COL], value[RETURN_COL]
            else:
                steps, returns = value
            steps = np.asarray(steps, dtype=float)
            parts.append(
                pd.DataFrame(
                    {
                        "env": env,
                        "variant": variant,
                        "seed": seed,
                        "step": steps,
                        "average_return": np.asarray(returns, dtype=float),
                    }
                )
            )
        df = pd.concat(parts, ignore_index=True) if parts else pd.DataFrame(columns=CURVE_COLUMNS)
    else:
        raise TypeError(f"curves must be a DataFrame or a dict, not {type(curves).__name__}")
    missing = [c for c in CURVE_COLUMNS if c not in df.columns]
    if missing:
        raise ValueError(f"curves lack column(s) {missing}; have {list(df.columns)}")
    df = df[CURVE_COLUMNS].copy()
    for col in ("step", "average_return"):
        df[col] = pd.to_numeric(df[col], errors="coerce")
    return df[df["step"].notna() & df["average_return"].notna()]


def _align_seeds(group: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """Put the seeds of one (env, variant) on a common step grid.

    Returns ``(grid, values)`` with ``values`` of shape ``(n_seeds, len(grid))``. The grid is the
    union of all seeds' evaluation steps inside the range every seed covers
    (``[max of first steps, min of last steps]``); each seed is linearly interpolated onto it
    (repeated steps of one seed are averaged first). If the seeds share no step range the seed
    with the most evaluations is used alone.
    """
    per_seed = []
    for _, s in group.groupby("seed", sort=True, dropna=False):
        s = s.groupby("step", sort=True)["average_return"].mean()
        if len(s):
            per_seed.append((s.index.to_numpy(dtype=float), s.to_numpy(dtype=float)))
    lo = max(x[0] for x, _ in per_seed)
    hi = min(x[-1] for x, _ in per_seed)
    if lo > hi:
        x, y = max(per_seed, key=lambda xy: xy[0].size)
        return x, y[None, :]
    grid = np.unique(np.concatenate([x[(x >= lo) & (x <= hi)] for x, _ in per_seed]))
    values = np.stack([np.interp(grid, x, y) for x, y in per_seed])
    return grid, values


def _bootstrap_band(
    values: np.ndarray, confidence_level: float, n_resamples: int, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """Column-wise percentile-bootstrap CI of the mean over rows (seeds) of ``values``."""
    if values.shape[0] < 2:
        return values[0].copy(), values[0].copy()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", getattr(stats, "DegenerateDataWarning", RuntimeWarning))
        warnings.simplefilter("ignore", RuntimeWarning)
        res = stats.bootstrap(
            (values,),
            np.mean,
            axis=0,
            vectorized=True,
            confidence_level=confidence_level,
            n_resamples=n_resamples,
            method="percentile",
            batch=max(1, min(n_resamples, 2_000_000 // max(1, values.size))),
            **_rng_kwargs(seed),
        )
    low = np.asarray(res.confidence_interval.low, dtype=float)
    high = np.asarray(res.confidence_interval.high, dtype=float)
    mean = values.mean(axis=0)
    # Columns where all seeds agree have a zero-width interval (SciPy may give NaN there).
    low = np.where(np.isfinite(low), low, mean)
    high = np.where(np.isfinite(high), high, mean)
    return low, high


def aggregate_curves(
    curves: pd.DataFrame | Mapping,
    confidence_level: float = CONFIDENCE_LEVEL,
    n_resamples: int = N_RESAMPLES_BAND,
    seed: int = BOOTSTRAP_SEED,
) -> pd.DataFrame:
    """Mean learning curve over seeds, with a bootstrap band, per (env, variant).

    Args:
        curves: long DataFrame with columns ``env``, ``variant``, ``seed``, ``step``,
            ``average_return`` (one row per evaluation; as made by :func:`collect_runs`), or a
            dict mapping ``(env, variant, seed)`` to a DataFrame/dict with ``step`` and
            ``average_return`` or to a ``(steps, returns)`` pair.

    Seeds are aligned by step as in :func:`_align_seeds`: linear interpolation onto the union of
    their evaluation steps, restricted to the step range all seeds cover.

    Returns:
        long DataFrame with columns ``env``, ``variant``, ``step``, ``n`` (seeds), ``mean``,
        ``ci_low``, ``ci_high``; the band is the 95% percentile bootstrap CI of the mean over
        seeds at each step (the mean itself where n=1).
    """
    df = _curves_frame(curves)
    parts = []
    for (env, variant), group in df.groupby(["env", "variant"], sort=True):
        grid, values = _align_seeds(group)
        low, high = _bootstrap_band(values, confidence_level, n_resamples, seed)
        parts.append(
            pd.DataFrame(
                {
                    "env": env,
                    "variant": variant,
                    "step": grid,
                    "n": values.shape[0],
                    "mean": values.mean(axis=0),
                    "ci_low": low,
                    "ci_high": high,
                }
            )
        )
    columns = ["env", "variant", "step", "n", "mean", "ci_low", "ci_high"]
    if not parts:
        return pd.DataFrame(columns=columns)
    return pd.concat(parts, ignore_index=True)[columns]


# --------------------------------------------------------------------------- figures


def safe_filename(name: Any) -> str:
    """A file-name-safe form of ``name``: runs of characters other than letters, digits, ``.``,
    ``_`` and ``-`` become ``_``; leading dots/underscores are stripped (``rlpipe/MinitaurBullet-v0``
    -> ``rlpipe_MinitaurBullet-v0``)."""
    safe = re.sub(r"[^A-Za-z0-9._-]+", "_", str(name)).strip("._")
    return safe or "unnamed"


def _new_figure(figsize: tuple[float, float] = (7.0, 4.5)) -> Figure:
    """A pyplot-free figure on an Agg canvas (nothing to close, nothing registered)."""
    fig = Figure(figsize=figsize, dpi=_DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _save_figure(fig: Figure, out_png: str | os.PathLike) -> Path:
    """Write ``fig`` as PNG to ``out_png`` atomically and release it; returns the path.

    Parent folders are created; the image goes to a temporary file in the same folder that is
    then moved over ``out_png`` with :func:`os.replace`.
    """
    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fig.savefig(fh, format="png", dpi=_DPI)
        os.chmod(tmp, 0o644)
        os.replace(tmp, out)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
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


def plot_return_curves(
    run_dirs: Sequence[str | os.PathLike],
    out_png: str | os.PathLike,
    labels: Sequence[str] | None = None,
    *,
    x: str = STEP_COL,
    title: str | None = None,
) -> Path:
    """Average return vs iteration of one or more runs in one PNG (``rlpipe plot RUN_DIR...``).

    Args:
        run_dirs: run directories (or their ``metrics.csv`` paths).
        out_png: where to write the PNG.
        labels: legend labels, one per run; default: each run directory's name.
        x: ``"step"`` (x label "Iterations", the TF-Agents tutorials' plot) or ``"frames"``
            (x label "Environment steps").
        title: figure title; default: the runs' env id(s) from ``summary.json``/``config.json``.

    Raises:
        ValueError: if a run has no ``metrics.csv`` / no evaluation rows, no runs are given, or
            ``labels`` does not match ``run_dirs`` in length.
    """
    run_dirs = list(run_dirs)
    if not run_dirs:
        raise ValueError("plot_return_curves needs at least one run directory")
    if labels is not None and len(labels) != len(run_dirs):
        raise ValueError(f"{len(labels)} labels for {len(run_dirs)} runs")
    if x not in (STEP_COL, "frames"):
        raise ValueError(f"x must be 'step' or 'frames', not {x!r}")
    series, envs = [], []
    for i, run in enumerate(run_dirs):
        metrics = read_metrics(run)
        xs, ys = _xy(metrics, x)
        if xs.size == 0:
            raise ValueError(f"{_metrics_path(run)}: no evaluation rows with a '{x}' value")
        label = labels[i] if labels is not None else _run_dir(run).name
        series.append((label, xs, ys))
        env = read_run_info(run).get("env")
        if env and str(env) not in envs:
            envs.append(str(env))
    fig = _new_figure()
    ax = fig.add_subplot()
    for label, xs, ys in series:
        ax.plot(xs, ys, marker=_marker(xs.size), markersize=3, linewidth=1.6, label=label)
    ax.set_xlabel("Iterations" if x == STEP_COL else "Environment steps")
    ax.set_ylabel("Average Return")
    ax.set_title(title if title is not None else (", ".join(envs) or "Average return"))
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize="small")
    return _save_figure(fig, out_png)


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

    Drawn with :func:`seaborn.ecdfplot`; the mean return is marked by a dashed vertical line.
    Non-finite returns are dropped.

    Raises:
        ValueError: if there is no finite return.
    """
    import seaborn as sns  # lazy: seaborn is slow to import and only needed here

    x = np.asarray(list(returns) if not isinstance(returns, np.ndarray) else returns, float)
    x = x.ravel()
    x = x[np.isfinite(x)]
    if x.size == 0:
        raise ValueError("plot_ecdf: no finite episode returns to plot")
    fig = _new_figure((6.4, 4.2))
    ax = fig.add_subplot()
    sns.ecdfplot(x=x, ax=ax, linewidth=2.0, color="tab:blue", label=f"episodes (n={x.size})")
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
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize="small", frameon=False)
    return _save_figure(fig, out_png)


def _plot_final_ecdfs(
    records: pd.DataFrame,
    envs: Sequence[str],
    orders: Mapping[str, Sequence[str]],
    styles: Mapping[str, Mapping[str, Any]],
    reference: str | None,
    out_png: Path,
) -> Path:
    import seaborn as sns  # lazy, see plot_ecdf

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
            sns.ecdfplot(x=vals, ax=ax, label=label, **styles[variant])
            handles.setdefault(label, ax.get_lines()[-1])
        ax.set_title(env)
        ax.set_xlabel("Final return")
        ax.set_ylabel("Proportion of seeds")
        ax.set_ylim(0.0, 1.02)
        ax.grid(True, alpha=0.3)
    for ax in axes[len(envs):]:
        ax.set_visible(False)
    fig.suptitle("ECDF of final returns over seeds")
    fig.legend(list(handles.values()), list(handles.keys()), loc="outside right upper",
               fontsize="small", frameon=False)
    return _save_figure(fig, out_png)


# --------------------------------------------------------------------------- ablation report


def _fmt(x: float) -> str:
    if x is None or not np.isfinite(x):
        return "n/a"
    return f"{x:.1f}" if abs(x) >= 10 else f"{x:.3f}"


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


def _write_text_atomic(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="") as fh:
            fh.write(text)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    return path


def write_ablation_report(
    records: pd.DataFrame,
    curves: pd.DataFrame | Mapping | None,
    out_dir: str | os.PathLike,
    reference_variant: str = "full",
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

    Writes:
        * ``ablation.csv`` -- ``env, variant, seed, final_return, auc``, one row per run;
        * ``ablation.md`` -- per env a Markdown table (variant, n, mean final return, 95% CI,
          IQM, AUC) sorted by mean, the reference variant in bold with a ★, under a header
          saying how the numbers were made (see :func:`summarise_runs`);
        * ``curves_<env>.png`` per env with curve data (env id made safe by
          :func:`safe_filename`) -- mean over seeds per variant with a shaded 95% percentile
          bootstrap band (see :func:`aggregate_curves` for the step alignment);
        * ``ecdf_final_returns.png`` -- one panel per env, one ECDF per variant.

    Returns:
        the paths written: csv, md, the curve PNGs (env order), the ECDF PNG.
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
    _write_text_atomic(csv_path, table.to_csv(index=False))
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

    md_path = out / "ablation.md"
    _write_text_atomic(
        md_path, _markdown_report(summary, envs, curve_files, reference, len(table))
    )
    written.append(md_path)
    written += curve_paths
    written.append(
        _plot_final_ecdfs(table, envs, orders, styles, reference, out / "ecdf_final_returns.png")
    )
    return written
