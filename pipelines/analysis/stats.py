"""Statistics of learning curves and of final returns over seeds.

* :func:`area_under_curve` is the normalised area under a learning curve;
* :func:`bootstrap_ci` and :func:`interquartile_mean` summarise values over seeds;
* :func:`summarise_runs` gives per (env, variant) statistics of a ``records`` table and
  :func:`aggregate_curves` the mean learning curve with a band of a ``curves`` table (both as
  made by :func:`rlpipe.pipelines.analysis.runs.collect_runs`).

Statistics come from SciPy: 95% confidence intervals are percentile bootstraps of the mean
(:func:`scipy.stats.bootstrap`, fixed seed, so every report is reproducible) and the
interquartile mean is :func:`scipy.stats.trim_mean` with 25% cut from each end.

SciPy is imported by the functions that use it, not with this module: a run's own ``report.html``
(written by the run, through :mod:`~rlpipe.pipelines.analysis.report_pages`) needs none of it, and
``import scipy.stats`` costs a run 0.6-1.0 s on a 2-core machine (importing ``pages`` after torch: 1.2 s
without it, 1.8-2.2 s with it).
"""

from __future__ import annotations

import inspect
import warnings
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np
import pandas as pd

from rlpipe.pipelines.analysis.columns import CURVE_COLUMNS, RECORD_COLUMNS, RETURN_COL, STEP_COL

__all__ = [
    "area_under_curve",
    "bootstrap_ci",
    "interquartile_mean",
    "summarise_runs",
    "aggregate_curves",
]

CONFIDENCE_LEVEL = 0.95
N_RESAMPLES = 9999  # for the per-variant table
N_RESAMPLES_BAND = 2000  # for the learning-curve bands (one CI per plotted step)
BOOTSTRAP_SEED = 0
IQM_CUT = 0.25


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
    from scipy import stats

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
    from scipy import stats

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
    from scipy import stats

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
    from scipy import stats

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
