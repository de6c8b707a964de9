"""The HTML pages: a run's own ``report.html`` and the comparison page of several runs.

* :func:`write_run_report` -- ``RUN/report.html``, the page a notebook reader expects after a run:
  the config, the return curve with the random agent's return as a baseline, the losses, the speeds,
  the evaluation table and the trained agent's video. The run writes it at every evaluation and at
  its end; ``rlpipe video RUN`` and ``rlpipe report RUN`` write it again from the run directory alone.
* :func:`write_comparison_report` -- ``rlpipe report RUN [RUN...]`` and the ablation study's
  ``report.html``: a table per env over variants (mean, 95% bootstrap CI, IQM, AUC), mean curves
  with CI bands, ECDFs of final returns and a table of the runs, each linked to its own page.

Each page is one file that opens from disk with no network: the figures are SVG documents inlined as
``data:`` URIs (crisp at any zoom, and their element ids cannot clash with another figure's), the
page's style is in the template. The video is the one exception: it stays a file beside the page
(``trained-agent.mp4``, by relative path), because the page is rewritten at every evaluation and a
base64 copy of a video would rewrite megabytes each time and double the run's disk use; the run
directory is the self-contained unit. The mp4 is H.264 (``pipelines/artifacts/video.py``), which Chrome, Edge,
Safari, Firefox and Debian's ``chromium`` play (checked by ``tests/test_report.py``); builds without
the proprietary codecs (Playwright's own Chromium) show the player without the picture. The pages are rendered by Jinja2 from
``templates/*.html.j2``, with autoescaping; no HTML is built in Python.
"""

from __future__ import annotations

import base64
import csv
import datetime
import json
import math
import os
from collections.abc import Mapping, Sequence
from functools import cache
from pathlib import Path
from typing import Any

import jinja2
import pandas as pd

from rlpipe.pipelines.analysis.plots import (
    _env_curves_figure,
    _final_ecdfs_figure,
    _fmt,
    _variant_styles,
    _xy,
    figure_svg,
    run_returns_figure,
    run_series_figure,
    runs_returns_figure,
)
from rlpipe.pipelines.analysis.runs import RECORD_COLUMNS, collect_runs, read_metrics
from rlpipe.pipelines.analysis.stats import aggregate_curves, summarise_runs
from rlpipe.pipelines.artifacts import checkpoint as ckpt
from rlpipe.pipelines.artifacts.files import write_text_atomic
from rlpipe.pipelines.artifacts.rundir import RunDir

__all__ = ["BASELINE_FILE", "REPORT_FILE", "VIDEO_FILE", "read_baseline", "run_labels",
           "write_baseline", "write_comparison_page", "write_comparison_report", "write_run_report"]

REPORT_FILE = "report.html"
BASELINE_FILE = "baseline.json"
VIDEO_FILE = "trained-agent.mp4"
_SPEED_COLUMNS = {"steps_per_s": "env steps / s", "updates_per_s": "updates / s"}
_EVAL_COLUMNS = {"step": "step", "frames": "env steps", "updates": "updates", "average_return": "AverageReturn",
                 "average_episode_length": "AverageEpisodeLength", "wall_time": "wall time (s)"}


@cache
def _templates() -> jinja2.Environment:
    return jinja2.Environment(loader=jinja2.PackageLoader("rlpipe.pipelines.analysis", "templates"),
                              autoescape=True, undefined=jinja2.StrictUndefined, trim_blocks=True,
                              lstrip_blocks=True)


def _render(template: str, out: Path, **context: Any) -> Path:
    html = _templates().get_template(template).render(
        generated=datetime.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M:%S %Z"), **context)
    out.parent.mkdir(parents=True, exist_ok=True)
    return write_text_atomic(out, html)


def _svg_uri(fig) -> str:
    return "data:image/svg+xml;base64," + base64.b64encode(figure_svg(fig).encode("utf-8")).decode("ascii")


def _read_json(path: Path) -> dict | None:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def _flatten(config: Mapping[str, Any], prefix: str = "") -> list[tuple[str, str]]:
    rows = []
    for key, value in config.items():
        if isinstance(value, Mapping):
            rows += _flatten(value, f"{prefix}{key}.")
        else:
            rows.append((f"{prefix}{key}", json.dumps(value)))
    return rows


# --- the random agent's return --------------------------------------------------------------------


def write_baseline(run_dir: str | os.PathLike, result: Mapping[str, Any]) -> Path:
    """Store the random agent's evaluation (``evaluate``'s result) as ``RUN/baseline.json``."""
    returns = [float(r) for r in result["returns"]]
    return write_text_atomic(Path(run_dir) / BASELINE_FILE, json.dumps({
        "policy": "random (uniform over the action space)",
        "episodes": len(returns),
        "average_return": float(result["average_return"]),
        "average_episode_length": float(result["average_episode_length"]),
        "returns": returns,
    }, indent=2) + "\n")


def read_baseline(run_dir: str | os.PathLike) -> dict | None:
    """``RUN/baseline.json`` as written by :func:`write_baseline`, or ``None``."""
    data = _read_json(Path(run_dir) / BASELINE_FILE)
    return data if data is not None and isinstance(data.get("average_return"), (int, float)) else None


# --- a run's page ---------------------------------------------------------------------------------------


def _csv_rows(path: Path) -> list[dict[str, str]]:
    try:
        with path.open(newline="") as fh:
            return list(csv.DictReader(fh))
    except OSError:
        return []


def write_run_report(run_dir: str | os.PathLike, out: str | os.PathLike | None = None, *,
                     running: bool | None = None) -> Path:
    """Write ``RUN/report.html`` (or ``out``) from what the run directory holds now; returns its path.

    Works on a run in progress (the page says where it is), a stopped one (it says so, and how to
    continue it) and a finished one (its ``summary.json`` is of its last iteration: a finished run
    trained on with a larger ``num_iterations`` is not finished any more). ``running``: whether the run
    is training now (the run's own writes say); None: while a process holds its writer lock. The tables show ``metrics.csv``'s figures as written there; the video is
    linked when ``trained-agent.mp4`` exists.
    """
    run = Path(run_dir)
    out = Path(out) if out is not None else run / REPORT_FILE
    saved = _read_json(run / "config.json") or {}
    algo, config = saved.get("algo", "?"), saved.get("config", {})
    summary = _read_json(run / "summary.json")
    baseline = read_baseline(run)
    rows = _csv_rows(run / "metrics.csv")
    # by step: a background evaluation's row is written when its result is back, after later rows
    eval_rows = sorted((r for r in rows if r.get("average_return")), key=lambda r: float(r["step"]))
    loss_columns = [c for c in (rows[0] if rows else {}) if c.startswith("loss_")]
    log_rows = [r for r in rows if any(r.get(c) for c in [*loss_columns, *_SPEED_COLUMNS])]
    env = (summary or {}).get("env") or config.get("env", "?")
    seed = config.get("seed", "?")
    title = f"{algo.upper()} on {env}, seed {seed}"

    frame = pd.DataFrame(rows) if rows else pd.DataFrame(columns=["step", "average_return"])
    evals = pd.DataFrame(eval_rows) if eval_rows else pd.DataFrame(columns=["step", "average_return"])
    last_log = log_rows[-1] if log_rows else {}
    iteration = max((int(float(r["step"])) for r in rows), default=0)  # background evaluations land late
    of = f"{iteration:,} of {config.get('num_iterations', 0):,}"
    if running is None:
        running = RunDir(run).being_written()
    if running or (summary or {}).get("iterations") != iteration:
        summary = None  # not finished (any more): its figures are not the run's
    exported_best = (summary or {}).get("best_evaluation")  # keep_best: the policy exported is this evaluation's
    exported_best = exported_best if exported_best and exported_best.get("exported") else None
    figures = {
        "returns": _svg_uri(run_returns_figure(
            evals, title, baseline["average_return"] if baseline else None,
            f"random agent ({baseline['episodes']} episodes)" if baseline else "random agent",
            best=(exported_best["step"], exported_best["average_return"]) if exported_best else None)),
        "losses": _svg_uri(run_series_figure(frame, loss_columns, "Losses (mean over each log interval)",
                                             {c: c.removeprefix("loss_") for c in loss_columns})),
        "speed": _svg_uri(run_series_figure(frame, list(_SPEED_COLUMNS), "Speed (training time only)",
                                            _SPEED_COLUMNS)),
    }
    stopped = not summary and not running
    facts = [
        ("status", "finished" if summary else f"at iteration {of}" if running else
         f"stopped at iteration {of} (interrupted, or killed){_last_checkpoint(run)}"),
        ("final AverageReturn" if summary else "last AverageReturn", eval_rows[-1]["average_return"] if eval_rows else "n/a"),
        ("random agent's AverageReturn",
         f"{_fmt(baseline['average_return'])} ({baseline['episodes']} episodes)" if baseline else "n/a"),
    ]
    success = "success_rate" in (rows[0] if rows else {})  # a goal env's evaluated share of successful episodes
    if success and eval_rows:
        facts.insert(2, ("final SuccessRate" if summary else "last SuccessRate", eval_rows[-1].get("success_rate", "n/a")))
    if stopped:
        facts.append(("to continue it", f"rlpipe train {algo} --resume {run.resolve()}"))
    if summary and summary.get("stopped_because"):
        facts.append(("stopped because", summary["stopped_because"]))
    if summary and exported_best:
        facts.append(("exported policy", f"the best evaluation's: step {exported_best['step']:,}, AverageReturn "
                                         f"{_fmt(exported_best['average_return'])} (the last is "
                                         f"policy/step_{summary['iterations']:07d}.onnx)"))
    if summary:
        facts += [
            ("iterations / env steps / updates", f"{summary['iterations']:,} / {summary['frames']:,} / {summary['updates']:,}"),
            ("wall time", f"{summary['wall_time_s']:.1f} s"),
            ("env steps / s, updates / s", f"{summary.get('env_steps_per_s') or 0:.1f}, {summary.get('updates_per_s') or 0:.1f} (whole run, training time)"),
        ]
    elif last_log:
        facts.append(("env steps / s, updates / s",
                      f"{last_log.get('steps_per_s', '')}, {last_log.get('updates_per_s', '')} (last log interval)"))
    video = run / VIDEO_FILE
    video_src = os.path.relpath(video, out.parent) if video.is_file() else None
    return _render(
        "run.html.j2", out, title=title, run_name=run.resolve().name, algo=algo, env=env, facts=facts,
        figures=figures, video=video_src, exported=_has_policy(run), policy_save_interval=config.get(
            "policy_save_interval"), config=_flatten(config),
        eval_columns={**_EVAL_COLUMNS, **({"success_rate": "SuccessRate"} if success else {})},
        eval_rows=eval_rows, log_columns=["step", *loss_columns, "train_episode_return", *_SPEED_COLUMNS],
        log_rows=log_rows,
    )


def _last_checkpoint(run: Path) -> str:
    steps = ckpt.checkpoint_steps(run / "checkpoints")
    return f"; its last checkpoint is at iteration {max(steps):,}, where it continues" if steps else ""


def _has_policy(run: Path) -> bool:
    """Whether ``rlpipe video RUN`` has a policy to film: the run exported one (``RUN/policy``)."""
    return any((run / "policy" / name).is_file() for name in ("policy.onnx", "policy.pt2"))


# --- the comparison page ---------------------------------------------------------------------------------


_NOT_VARIANT = {"seed", "video", "num_threads", "log_interval", "checkpoint_interval", "policy_save_interval",
                "checkpoint_keep", "policy_keep", "eval_timeout", "collector.max_restarts", "collector.timeout",
                "ray.address"}
"""config keys that say how a run is recorded, seeded or supervised, not what it learns: runs differing only here
are one variant"""
_MAX_LABEL_KEYS = 4
"""more differing keys than this make a label too long to read: the run's directory name stands for them"""


def run_labels(run_dirs: Sequence[str | os.PathLike]) -> dict[str, str]:
    """A variant name per run directory. Runs share a name (and pool into one variant, with a confidence
    interval over them) only when their algorithm and configs agree on every key but the seed and the keys of
    how a run is recorded (``video``, intervals of logs, checkpoints and exports, threads, ...).

    The name lists the keys in which the config differs from the other runs' of its algorithm
    (``clipped_double_q=false``), after the algorithm's name when the runs span several (``td3
    clipped_double_q=false``); it is the algorithm's name alone for a config that is its algorithm's only one.
    """
    configs: dict[str, tuple[str, dict[str, str]]] = {}
    for run in run_dirs:
        saved = _read_json(Path(run) / "config.json") or {}
        flat = {k: v for k, v in _flatten(saved.get("config", {})) if k not in _NOT_VARIANT}
        configs[str(run)] = (str(saved.get("algo", "?")), flat)
    several_algos = len({algo for algo, _ in configs.values()}) > 1
    by_algo: dict[str, list[dict[str, str]]] = {}
    for algo, flat in configs.values():
        by_algo.setdefault(algo, []).append(flat)
    labels: dict[str, str] = {}
    by_config: dict[tuple, str] = {}
    for run, (algo, flat) in configs.items():
        config = (algo, tuple(sorted((k, v) for k, v in flat.items() if k != "env")))  # env: a section of its own
        if config not in by_config:
            others = by_algo[algo]
            keys = sorted({k for f in others for k in f} - {"env"})
            varying = [k for k in keys if len({f.get(k) for f in others}) > 1]
            parts = [f"{k}={flat[k]}" if k in flat else f"{k} unset" for k in varying]
            if len(parts) > _MAX_LABEL_KEYS:
                parts = [Path(run).name]
            label = " ".join([algo] * (several_algos or not parts) + [", ".join(parts)] * bool(parts))
            if label in by_config.values():  # cut short to a directory name another config's run has too
                label = f"{label} ({Path(run).resolve().parent.name})"
            by_config[config] = label
        labels[run] = by_config[config]
    return labels


def write_comparison_report(run_dirs: Sequence[str | os.PathLike], out: str | os.PathLike,
                            *, title: str = "Comparison of runs") -> Path:
    """``rlpipe report RUN [RUN...]``: the comparison page of ``run_dirs`` at ``out``.

    Runs are grouped into variants by :func:`run_labels` (seeds of one config together).
    Raises ``ValueError`` naming a run without an evaluation.
    """
    labels = run_labels(run_dirs)
    records, curves = collect_runs(run_dirs, variant=labels)
    return write_comparison_page(records, curves, out, title=title)


def write_comparison_page(records: pd.DataFrame, curves: pd.DataFrame | Mapping | None, out: str | os.PathLike, *,
                          reference: str | None = None, title: str = "Comparison of runs",
                          notes: Sequence[str] = ()) -> Path:
    """The comparison page of :func:`collect_runs`' tables at ``out`` (the ablation report's page too).

    Per env: the variants' table (n, mean final return, 95% bootstrap CI of the mean over seeds,
    IQM, AUC; best first, ``reference`` marked) and their mean curves with CI bands; then the ECDFs
    of final returns, every run's own curve, and a table of runs linking to their ``report.html``.
    """
    out = Path(out)
    table = records[RECORD_COLUMNS].copy()
    table["env"], table["variant"] = table["env"].astype(str), table["variant"].astype(str)
    summary = summarise_runs(table)
    envs = sorted(table["env"].unique())
    orders = {env: list(summary.loc[summary["env"] == env, "variant"]) for env in envs}
    reference = reference if reference in set(table["variant"]) else None
    agg = aggregate_curves(curves)
    if not agg.empty:
        agg["env"], agg["variant"] = agg["env"].astype(str), agg["variant"].astype(str)
    styles = _variant_styles(set(table["variant"]) | set(agg["variant"]), reference)

    sections = []
    for env in envs:
        env_agg = agg[agg["env"] == env]
        variants = [
            {"variant": r.variant, "reference": r.variant == reference, "n": int(r.n), "mean": _fmt(r.mean),
             "ci": f"[{_fmt(r.ci_low)}, {_fmt(r.ci_high)}]", "iqm": _fmt(r.iqm), "auc": _fmt(r.auc_mean)}
            for r in summary[summary["env"] == env].itertuples(index=False)
        ]
        curve = None
        if not env_agg.empty:
            order = orders[env] + sorted(set(env_agg["variant"]) - set(orders[env]))
            curve = _svg_uri(_env_curves_figure(env_agg, env, order, styles, reference))
        sections.append({"env": env, "variants": variants, "curves": curve})

    runs = []
    series = []
    for r in records.sort_values(["env", "variant", "seed"], kind="mergesort").itertuples(index=False):
        run_dir = Path(r.run_dir) if getattr(r, "run_dir", None) else None  # records made elsewhere may lack it
        page = run_dir / REPORT_FILE if run_dir is not None else None
        label = f"{r.variant} / seed {r.seed}" if str(r.seed) not in ("nan", "") else str(r.variant)
        runs.append({"label": label, "env": r.env, "variant": r.variant, "seed": r.seed,
                     "final": _fmt(r.final_return), "auc": _fmt(r.auc), "frames": _count(getattr(r, "frames", None)),
                     "dir": str(run_dir or ""),
                     "page": os.path.relpath(page, out.parent) if page is not None and page.is_file() else None})
        if run_dir is not None and (run_dir / "metrics.csv").is_file():
            xs, ys = _xy(read_metrics(run_dir))
            series.append((f"{r.env}: {label}" if len(envs) > 1 else label, xs, ys))
    figures = {
        "ecdf": _svg_uri(_final_ecdfs_figure(table, envs, orders, styles, reference)),
        "runs": _svg_uri(runs_returns_figure(series, "Every run's return curve")) if series else None,
    }
    return _render("compare.html.j2", out, title=title, sections=sections, runs=runs, figures=figures,
                   reference=reference, notes=list(notes), n_runs=len(table))


def _count(value: Any) -> str:
    try:
        f = float(value)
    except (TypeError, ValueError):
        return "n/a"
    return f"{int(f):,}" if math.isfinite(f) else "n/a"
