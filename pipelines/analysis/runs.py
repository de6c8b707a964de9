"""Reading finished run directories into tables.

Every training run writes a run directory with

* ``metrics.csv`` -- one row per log point; columns ``step`` (iteration), ``frames``,
  ``average_return``, ``average_episode_length``, ``loss_*``, ``steps_per_s``, ... Rows whose
  ``average_return`` is empty are log-only rows; the others are *evaluation rows*.
* ``summary.json`` -- ``{"algo", "env", "seed", "final_average_return", "frames", ...}``.
* ``config.json`` -- the resolved config (keys include ``"env"`` and ``"seed"``).

:func:`read_metrics`, :func:`eval_rows` and :func:`read_run_info` read one run;
:func:`collect_runs` turns many run directories into the ``records`` (:data:`RECORD_COLUMNS`)
and ``curves`` (:data:`CURVE_COLUMNS`) tables that the statistics and the ablation report take.
"""

from __future__ import annotations

import json
import os
import warnings
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from rlpipe.pipelines.analysis.columns import CURVE_COLUMNS, RECORD_COLUMNS, RETURN_COL, STEP_COL
from rlpipe.pipelines.analysis.stats import area_under_curve

__all__ = [
    "METRICS_FILE",
    "RECORD_COLUMNS",
    "CURVE_COLUMNS",
    "read_metrics",
    "eval_rows",
    "read_run_info",
    "collect_runs",
]

METRICS_FILE = "metrics.csv"
SUMMARY_FILE = "summary.json"
CONFIG_FILE = "config.json"
_NUMERIC_COLUMNS = ("step", "frames", "average_return", "average_episode_length")


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
    """``config.json`` (the config's keys and ``algo``) updated with ``summary.json`` of a run
    (either may be missing: ``{}``); a run still in progress has no ``summary.json`` yet.

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
            if name == CONFIG_FILE and isinstance(data.get("config"), dict):  # a run's {"algo", "config"}
                data = {"algo": data.get("algo"), **data["config"]}
            info.update(data)
    return info


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
