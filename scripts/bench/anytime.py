"""``rlpipe bench anytime``: the greedy return each side has at fixed wall-clock times, rlpipe and its peers.

    rlpipe bench anytime --envs Hopper-v5 [--algos sac] [--budget 10m] [--marks 10] [--peers sbx sb3 | none]
                         [--seeds 3] [--seed 100] [--threads SIDE=N ...] [--preset P] [key=value ...]

The question a user asks of a default is "what is the best agent I can have in the time I have": the return
against wall-clock time, not only the first crossing of a target. Every side runs for ``--budget`` and is evaluated
at ``--marks`` evenly spaced times (``budget/marks``, ``2*budget/marks``, ... ``budget``) by one rule
(``peers/ttr_rule.py`` ``Marks``): a side's time runs from just before its command is launched (imports count) and
leaves out the rule's own evaluations; at a mark the policy is played greedily for ``--eval-episodes`` (10) episodes,
seeded by the mark alone (the same episodes for every side and seed), on an env of the runner's own.

Sides, interleaved per seed: ``rlpipe`` (``rlpipe train env=ID key=value ...`` as a user types it: the sized
default, or ``--preset``; ``scripts/bench/anytime_run.py``), evaluated twice at each mark: ``exported``, what
``policy/`` would hold if the run ended there (the best evaluation's weights where ``keep_best`` kept them), and
``last``, the learner's policy as it is; and the peers ``sbx``/``sb3`` with RL-Zoo's settings for the env
(``peers/ttr_sb3.py``), their last policy. The page: each side's mean return per mark with a 95% bootstrap
confidence band across seeds (scipy), every seed's value in the table, and per seed the first mark at which rlpipe's
exported policy reached the return the peer had at the budget.
"""

from __future__ import annotations

import json
import os
import signal
import statistics
import sys
import time
from pathlib import Path
from typing import Any

from rlpipe.pipelines.errors import InputError
from rlpipe.pipelines.system.runtime import DeferredInterrupt
from rlpipe.scripts.bench.peers.ttr_rule import ANYTIME_PREFIX, LAUNCH_ENV
from rlpipe.scripts.bench.time_to_return import (
    Task,
    _here_environ,
    _machine,
    _threads,
    launch_and_wait,
    peer_launch,
)

PEERS = ("sbx", "sb3")
DEFAULT_PEERS = ("sbx",)
PEER_CAP = 10_000_000
"""the peers' ``learn(total_timesteps=...)``: beyond any budget's reach, so that the clock ends their runs (RL-Zoo's
linear schedules, where the zoo has them, are over the zoo's own ``n_timesteps``)"""


def check_args(args) -> tuple[float, list[float], list[str]]:
    """(budget seconds, marks, peers), or one line naming what is wrong."""
    from rlpipe.pipelines.config import duration_seconds

    if not getattr(args, "envs", None):
        raise InputError("anytime: expected --envs ID ... (the envs to train, e.g. --envs Hopper-v5)")
    budget = duration_seconds(args.budget)
    if budget is None:
        raise InputError(f"--budget {args.budget}: expected a positive duration such as 600, 90s, 10m or 2h")
    if args.marks is None or args.marks < 1:
        raise InputError(f"--marks {args.marks}: expected a positive count of evaluation times")
    if args.eval_episodes < 1:
        raise InputError(f"--eval-episodes {args.eval_episodes}: expected a positive count")
    peers = [] if args.peers == ["none"] else list(args.peers or DEFAULT_PEERS)
    for name in peers:
        if name not in PEERS:
            raise InputError(f"--peers: unknown peer {name!r} for anytime; expected some of {', '.join(PEERS)}, or none")
    if len(args.algos or ()) > 1:
        raise InputError(f"--algos {' '.join(args.algos)}: expected one algorithm for anytime")
    for env in args.envs:  # each env made once: a bad one is refused before any run
        _task(env, args)
    return budget, [budget * (i + 1) / args.marks for i in range(args.marks)], peers


def _task(env: str, args) -> Task:
    from rlpipe.pipelines.config import TrainConfig, apply_overrides
    from rlpipe.pipelines.sizing import _env_overrides, measure

    made = apply_overrides(TrainConfig(), [f"env={env}", *_env_overrides(list(args.overrides))])
    if args.preset is not None:
        from rlpipe.pipelines import resolve_preset

        algo = resolve_preset(args.preset)[0]
    else:
        algo = args.algos[0] if args.algos else ("dqn" if measure(made, play=False).discrete else "sac")
    return Task(env, algo, 0.0, PEER_CAP, "", (algo, (f"env={env}",)), peers=PEERS,
                env_kwargs=tuple(sorted(made.env_kwargs.items())))


def _launch_rlpipe(task: Task, seed: int, marks: list[float], args, work: Path, threads: int | None):
    overrides = [*args.overrides, *([f"num_threads={threads}"] if threads else [])]
    spec = {"env": task.env, "algo": task.algo, "seed": seed, "overrides": overrides, "marks": marks,
            "eval_episodes": args.eval_episodes, "out": str(work / "run"), "preset": args.preset}
    cmd = [sys.executable, "-m", "rlpipe.scripts.bench.anytime_run", json.dumps(spec)]
    shown = " ".join([f"env={task.env}", *args.overrides])
    return cmd, _here_environ(), f"`rlpipe train {args.preset + ' ' if args.preset else ''}{shown}`"


def _run(cmd: list[str], env: dict[str, str], cwd: Path, log: Path, timeout_s: float) -> dict[str, Any]:
    rc = launch_and_wait(cmd, {**env, LAUNCH_ENV: repr(time.time())}, cwd, log, timeout_s)
    found = None
    for line in log.read_text(errors="replace").splitlines():
        if line.startswith(ANYTIME_PREFIX):
            found = json.loads(line[len(ANYTIME_PREFIX):])
    if found is None:
        lines = [line for line in log.read_text(errors="replace").splitlines() if line.strip()]
        return {"rc": rc, "failed": True, "error": lines[-1] if lines else "no output", "log": str(log)}
    return {"rc": rc, "failed": False, "log": str(log), **found}


def bench_anytime(args, out: Path) -> dict[str, Any]:
    budget, marks, peers = check_args(args)
    out = out.resolve()
    threads = _threads(args)
    machine = _machine()
    seeds = list(range(args.seed, args.seed + args.seeds))
    runs: list[dict[str, Any]] = []
    settings: dict[str, dict[str, str]] = {}
    plan = [(env, seed, side) for env in args.envs for seed in seeds for side in ("rlpipe", *peers)]
    interrupted = None
    current = None
    try:
        with DeferredInterrupt(immediate=True):
            for n, (env, seed, side) in enumerate(plan, 1):
                current = f"{env} seed {seed} {side}"
                task = _task(env, args)
                work = out / env.replace("/", "_").replace(":", "_") / f"{side}-seed{seed}"
                if side == "rlpipe":
                    cmd, environ, shown = _launch_rlpipe(task, seed, marks, args, work, threads["rlpipe"])
                else:
                    try:
                        launch = peer_launch(task, side, seed, 0.0, PEER_CAP, work, threads[side])
                    except (RuntimeError, OSError, InputError) as exc:
                        settings.setdefault(env, {})[side] = f"not run: could not be set up: {exc}"
                        continue
                    spec = json.loads(launch.cmd[-1])
                    spec.update(marks=marks, eval_episodes=args.eval_episodes)
                    cmd, environ, shown = [*launch.cmd[:-1], json.dumps(spec)], launch.env, launch.settings
                settings.setdefault(env, {})[side] = f"{shown}; threads {threads[side] or 'default'}"
                result = _run(cmd, environ, work, work / "output.log", timeout_s=3 * budget + 1800)
                result.update(env=env, side=side, seed=seed)
                runs.append(result)
                print(progress_line(n, len(plan), result), flush=True)
    except KeyboardInterrupt as exc:
        interrupted = {"signal": signal.Signals(getattr(exc, "signum", signal.SIGINT)).name, "during": current,
                       "runs_done": len(runs), "runs_planned": len(plan)}
        print(f"{current}: interrupted by {interrupted['signal']}; the {len(runs)} runs finished before it are kept",
              flush=True)
    figures: dict[str, Any] = {"budget_s": budget, "marks_s": marks, "seeds": seeds, "envs": list(args.envs),
                               "settings": settings, "runs": runs, "threads": threads,
                               "eval_episodes": args.eval_episodes,
                               "machine": {**machine, "load_avg_1min_end": os.getloadavg()[0]}}
    if interrupted:
        figures["interrupted"] = interrupted
    figures["curves"] = curves(runs, marks)
    png = args.json.with_suffix(".png") if args.json else out / "anytime.png"
    figures["png"] = str(plot(figures, png))
    figures["table"] = tables(figures)
    return figures


def progress_line(n: int, total: int, r: dict[str, Any]) -> str:
    head = f"[{n}/{total}] {r['env']} seed {r['seed']} {r['side']}: "
    if r.get("failed"):
        return head + f"FAILED (exit {r['rc']}): {r.get('error', '')[:200]} (log: {r['log']})"
    last = r["points"][-1] if r["points"] else None
    if last is None:
        return head + "no mark reached"
    got = last.get("exported", last.get("last"))
    return head + (f"return {got['return']:.1f} at {last['mark_s']:.0f} s ({last['env_steps']:,} env steps, "
                   f"{last['updates']:,} updates; evaluations left out {r['excluded_s']:.0f} s)")


def _curve_names(side: str) -> list[tuple[str, str]]:
    """(curve, policy key) of a side: rlpipe's exported and last policies, a peer's last."""
    return [("rlpipe", "exported"), ("rlpipe (last)", "last")] if side == "rlpipe" else [(side, "last")]


def curves(runs: list[dict[str, Any]], marks: list[float]) -> dict[str, dict[str, Any]]:
    """Per env and curve: each seed's return at each mark, their mean and a 95% bootstrap confidence interval of
    the mean (scipy; none from fewer than 3 seeds)."""
    import numpy as np
    from scipy import stats

    out: dict[str, dict[str, Any]] = {}
    for r in runs:
        if r.get("failed"):
            continue
        for curve, key in _curve_names(r["side"]):
            by_seed = out.setdefault(r["env"], {}).setdefault(curve, {"seeds": {}})["seeds"]
            by_seed[r["seed"]] = [p[key]["return"] if key in p else None for p in r["points"]]
    for by_curve in out.values():
        for c in by_curve.values():
            c["mean"], c["low"], c["high"] = [], [], []
            for i in range(len(marks)):
                values = [v[i] for v in c["seeds"].values() if i < len(v) and v[i] is not None]
                c["mean"].append(statistics.fmean(values) if values else None)
                if len(values) >= 3 and len(set(values)) > 1:
                    ci = stats.bootstrap((np.array(values),), np.mean, confidence_level=0.95, n_resamples=2000,
                                         method="percentile", random_state=0).confidence_interval
                    c["low"].append(float(ci.low))
                    c["high"].append(float(ci.high))
                else:
                    c["low"].append(None)
                    c["high"].append(None)
    return out


def _peer_at_budget(runs, env, peer, seed):
    for r in runs:
        if r["env"] == env and r["side"] == peer and r["seed"] == seed and not r.get("failed") and r["points"]:
            return r["points"][-1]["last"]["return"]
    return None


def sooner(figures: dict[str, Any], env: str, peer: str) -> list[dict[str, Any]]:
    """Per seed: the peer's return at the budget, and the first mark at which rlpipe's exported policy had it."""
    rows = []
    for seed in figures["seeds"]:
        theirs = _peer_at_budget(figures["runs"], env, peer, seed)
        ours = figures["curves"].get(env, {}).get("rlpipe", {}).get("seeds", {}).get(seed)
        if theirs is None or ours is None:
            continue
        at = next((figures["marks_s"][i] for i, v in enumerate(ours) if v is not None and v >= theirs), None)
        rows.append({"seed": seed, "peer_return": theirs, "rlpipe_return": ours[-1] if ours else None, "at_s": at})
    return rows


def tables(figures: dict[str, Any]) -> str:
    m = figures["machine"]
    lines = [f"Anytime: greedy return ({figures['eval_episodes']} episodes, seeded by the mark) at wall-clock marks "
             f"(seconds from launch, imports counted, the rule's evaluations left out); seeds "
             f"{', '.join(map(str, figures['seeds']))}, interleaved. Machine: {m['cpus']} CPUs ({m.get('cpu')}), "
             f"1-minute load {m['load_avg_1min']:.2f} at the start, {m['load_avg_1min_end']:.2f} at the end."]
    if figures.get("interrupted"):
        i = figures["interrupted"]
        lines.append(f"**Interrupted by {i['signal']} during {i['during']}: {i['runs_done']} of {i['runs_planned']} "
                     "runs finished, and only they are below.**")
    marks = figures["marks_s"]
    for env in figures["envs"]:
        lines += ["", f"### {env}", ""]
        for side, shown in figures["settings"].get(env, {}).items():
            lines.append(f"- {side}: {shown}")
        lines += ["", "| curve | " + " | ".join(f"{t:.0f} s" for t in marks) + " |",
                  "|---|" + "---|" * len(marks)]
        for curve, c in figures["curves"].get(env, {}).items():
            cells = []
            for i in range(len(marks)):
                mean = c["mean"][i]
                band = f" [{_r(c['low'][i])}, {_r(c['high'][i])}]" if c["low"][i] is not None else ""
                cells.append("—" if mean is None else f"{_r(mean)}{band}")
            lines.append(f"| {curve} (mean [95% CI]) | " + " | ".join(cells) + " |")
            for seed, values in c["seeds"].items():
                lines.append(f"| {curve}, seed {seed} | " + " | ".join("—" if v is None else _r(v) for v in values)
                             + " |")
        for peer in PEERS:
            rows = sooner(figures, env, peer)
            if rows:
                lines.append("")
                for r in rows:
                    at = (f"at {r['at_s']:.0f} s ({figures['budget_s'] / r['at_s']:.1f}x sooner)" if r["at_s"]
                          else "not within the budget")
                    lines.append(f"- seed {r['seed']}: {peer}'s return at {figures['budget_s']:.0f} s, "
                                 f"{_r(r['peer_return'])}; rlpipe's exported policy had it {at}; rlpipe's at the "
                                 f"budget {_r(r['rlpipe_return'])}")
    lines += ["", f"Curves with their bands: {figures['png']}"]
    return "\n".join(lines)


def _r(x: float) -> str:
    return f"{x:.0f}" if abs(x) >= 100 else f"{x:.1f}"


def plot(figures: dict[str, Any], path: Path) -> Path:
    """Return against wall-clock time per env: each curve's mean with its 95% band, every seed as a faint line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    envs = figures["envs"]
    marks = figures["marks_s"]
    fig, axes = plt.subplots(1, len(envs), figsize=(5 * len(envs), 3.8), squeeze=False)
    for ax, env in zip(axes[0], envs):
        for k, (curve, c) in enumerate(figures["curves"].get(env, {}).items()):
            color = f"C{k}"
            style = "--" if "(last)" in curve else "-"
            xs = [t for t, v in zip(marks, c["mean"]) if v is not None]
            ax.plot(xs, [v for v in c["mean"] if v is not None], style, color=color, label=curve, marker="o", ms=3)
            band = [(t, lo, hi) for t, lo, hi in zip(marks, c["low"], c["high"]) if lo is not None]
            if band:
                ax.fill_between([b[0] for b in band], [b[1] for b in band], [b[2] for b in band], color=color,
                                alpha=0.2, linewidth=0)
            for values in c["seeds"].values():
                pts = [(t, v) for t, v in zip(marks, values) if v is not None]
                ax.plot([p[0] for p in pts], [p[1] for p in pts], style, color=color, alpha=0.25, linewidth=0.8)
        ax.set_title(env, fontsize=10)
        ax.set_xlabel("seconds from launch (evaluations left out)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    axes[0][0].set_ylabel("greedy return (mean, 95% CI over seeds)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
