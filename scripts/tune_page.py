"""``rlpipe tune``'s page: ``OUT/tune.html`` with Optuna's plots (as PNGs beside it) and the trials' table."""

from __future__ import annotations

import html
import warnings
from pathlib import Path
from typing import Any

PLOTS = {
    "history.png": ("plot_optimization_history", "Each trial's value (optimization history)", None),
    "importances.png": ("plot_param_importances", "Which settings mattered (parameter importances, fANOVA)", None),
    # the trials report their curve once a second from launch (tune_trials.py), which Optuna calls "Step"
    "curves.png": ("plot_intermediate_values", "Training return over elapsed seconds (the curves pruning compares)",
                   ("seconds since the trial's launch", "training return, mean of its seeds")),
}
"""file name -> (Optuna's matplotlib plot, caption, (x label, y label) in place of Optuna's, or None)"""
MAX_LEGEND = 12
"""the most entries a plot's legend keeps (one per trial: past a dozen it hides the plot)"""


def write_plots(study, out: Path) -> dict[str, str]:
    """Optuna's matplotlib plots as PNGs in ``out``: file name -> caption, or why a plot could not be drawn."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import optuna
    import optuna.visualization.matplotlib as ovm

    optuna.logging.set_verbosity(optuna.logging.ERROR)  # a plot that cannot be drawn says so on the page instead
    shown: dict[str, str] = {}
    for name, (function, caption, labels) in PLOTS.items():
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # Optuna marks its matplotlib plots experimental
                ax = getattr(ovm, function)(study)
            first = ax.flat[0] if hasattr(ax, "flat") else ax
            fig = first.figure
            if labels:
                first.set_xlabel(labels[0])
                first.set_ylabel(labels[1])
            legend = first.get_legend()
            if legend is not None and len(legend.get_texts()) > MAX_LEGEND:
                legend.remove()
            fig.set_size_inches(7, 4)
            fig.tight_layout()
            fig.savefig(out / name, dpi=100)
            plt.close(fig)
            shown[name] = caption
        except (ValueError, RuntimeError) as exc:  # importances need two finished trials that differ
            shown[name] = f"{caption}: not drawn ({exc})"
    return shown


def write_page(study, plan, confirmation: dict[str, Any] | None, preset: Path) -> Path:
    from optuna.trial import TrialState

    plots = write_plots(study, plan.out)
    complete = len(study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,)))
    pruned = len(study.get_trials(deepcopy=False, states=(TrialState.PRUNED,)))
    if complete < 5 and "not drawn" not in plots["importances.png"]:
        plots["importances.png"] += f" from {complete} finished trials: too few to tell the settings apart"
    best = study.best_trial
    rows = []
    for t in study.trials:
        value = f"{t.value:.1f}" if t.value is not None else "—"
        seeds = ", ".join("—" if s is None else f"{s:.1f}"
                          for s in t.user_attrs.get("returns" if plan.return_at else "seconds", []))
        params = ", ".join(f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}" for k, v in t.params.items())
        mark = " class=best" if t.number == best.number else ""
        rows.append(f"<tr{mark}><td>{t.number}</td><td>{t.state.name.lower()}</td><td>{value}</td>"
                    f"<td>{html.escape(seeds)}</td><td>{html.escape(params)}</td></tr>")
    if confirmation and plan.return_at:
        seen = (f"On fresh seeds {', '.join(map(str, confirmation['seeds']))} (never searched on): return "
                + ("—" if confirmation["value"] is None else f"<b>{confirmation['value']:.1f}</b>") + " (seeds: "
                + ", ".join("no evaluation" if v is None else f"{v:.1f}" for v in confirmation["returns"]) + ").")
    elif confirmation:
        seen = (f"On fresh seeds {', '.join(map(str, confirmation['seeds']))} (never searched on): "
                f"<b>{confirmation['value']:.1f} s</b> (seeds: "
                + ", ".join(f"{s:.1f}" + ("" if r else " missed") for s, r in zip(confirmation["seconds"],
                                                                                     confirmation["reached"])) + ").")
    else:
        seen = "Not confirmed on fresh seeds (--confirm-seeds 0)."
    if plan.return_at:
        objective = (f"the greedy evaluation return of the policy each run exports after <code>time_budget="
                     f"{html.escape(plan.return_at)}</code> (its best evaluation's), the mean of {plan.seeds} seeds "
                     f"(0-{plan.seeds - 1}) run side by side, maximised; a run with no evaluation fails its trial")
        best_text, unit = f"return <b>{best.value:.1f}</b>", "return"
    else:
        objective = (f"seconds from launch to the target under <code>rlpipe bench time-to-return</code>'s rule, the "
                     f"mean of {plan.seeds} seeds (0-{plan.seeds - 1}) run side by side; a seed that missed counts "
                     f"{plan.cap_s:g} s (its cap) + {plan.penalty_s:g} s")
        best_text, unit = f"<b>{best.value:.1f} s</b>", "seconds"
    figures = "".join(f"<figure><img src='{name}' alt='{html.escape(c)}'><figcaption>{html.escape(c)}</figcaption></figure>"
                      if (plan.out / name).exists() and "not drawn" not in c else f"<p>{html.escape(c)}</p>"
                      for name, c in plots.items())
    body = f"""<!doctype html><html><head><meta charset=utf-8><title>rlpipe tune: {html.escape(plan.env)}</title>
<style>body{{font-family:sans-serif;max-width:60em;margin:auto}} td,th{{padding:2px 8px;text-align:left}}
tr.best{{background:#e8f4e8}} img{{max-width:100%}}</style></head><body>
<h1>{html.escape(', '.join(plan.algos))} on {html.escape(plan.env)}, {html.escape(plan.goal())}</h1>
<p>Objective: {objective}. {complete} trials finished, {pruned} pruned.</p>
<p>Best: trial {best.number}, {best_text}. {seen}</p>
<p>Preset: <code>{html.escape(str(preset))}</code> (<code>rlpipe train {html.escape(str(preset))}</code>)</p>
{figures}
<h2>Trials</h2><table><tr><th>trial</th><th>state</th><th>{unit}</th><th>seeds</th><th>settings</th></tr>
{''.join(rows)}</table></body></html>
"""
    path = plan.out / "tune.html"
    path.write_text(body)
    return path
