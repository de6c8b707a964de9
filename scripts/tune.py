"""``rlpipe tune``: search the settings that bring an algorithm to a target return soonest on an env, or to
the best return in a given time.

    rlpipe tune ALGO[,ALGO] env=ID (--target R | --objective return-at=10m) [--budget 30m] [--seeds 2]
                [--workers N] [--trials N] [--cap SECONDS] [--penalty SECONDS] [--confirm-seeds 2] [--out DIR]
                [key=value ...]

An Optuna study (TPE sampler) whose objective is a trial's seconds from launch to the target under the
bench's rule (``rlpipe bench time-to-return``: the mean of the last 5 training episodes reaches the
target and a greedy evaluation confirms it), the mean over ``--seeds`` seeds (0, 1, ...) run side by
side; a seed that misses (its ``--cap`` seconds or the preset's env steps pass first, or it fails)
counts as the cap plus ``--penalty``. Each trial's seeds are ``rlpipe train ALGO env=ID key=value ...``
processes on this machine, ``--workers`` trials at a time, each process on one thread where several
share the machine. A trial whose training return falls behind the best finished trial's at the same
second is stopped (pruned). Several algorithms (``sac,crossq``) make the algorithm a searched setting.

``--objective return-at=T`` searches for the best agent in ``T`` instead: each seed's run is ``rlpipe train ALGO
env=ID time_budget=T keep_best=true ...`` (sized for that budget, as ``rlpipe train`` sizes it), and the trial's
value is the mean over its seeds of the greedy evaluation return of the policy the run exports (its best
evaluation's; the last one's where the user sets ``keep_best=false``), maximised. The best of a run's evaluations
is a little optimistic (the highest of noisy estimates); ``rlpipe bench anytime`` plays the exported policy on
episodes of its own. A trial whose training return falls behind the best trial's at the same second, past half
of ``T``, is pruned; a run past ``T`` + its cap's margin is stopped and fails the trial.

The study lives in ``OUT/study.db`` (SQLite). Ctrl-C ends the running trials (exit 130); rerunning the
same command continues the study with what is left of ``--budget``, running again the trials an
interruption or a crash cut short, and none that finished. When the budget is spent (a running trial
is let finish), the best setting is run on ``--confirm-seeds`` seeds from 100 on, which the search
never used, and ``OUT`` holds the preset file (``rlpipe train OUT/ALGO-ENV-tuned.yaml``), ``tune.html``
with Optuna's plots, and ``results.json``.
"""

from __future__ import annotations

import contextlib
import fcntl
import functools
import io
import json
import re
import signal
import statistics
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

POLL_S = 1.0
CONFIRM_FIRST_SEED = 100
STUDY = "tune"
_UNITS = {"s": 1, "m": 60, "h": 3600}


def add_parser(sub) -> None:
    tune = sub.add_parser("tune", help="search the settings that reach a target return soonest (Optuna)")
    tune.add_argument("algo", help="algorithm, or several comma-separated to search among (sac,crossq)")
    tune.add_argument("overrides", nargs="*", metavar="key=value",
                      help="env=ID (required); ray.address=ADDR: the trials' runs on that Ray cluster, one CPU each "
                           "(empty: a local Ray instance); any other key: an override of every trial")
    tune.add_argument("--target", type=float, default=None, help="the return to reach (the objective: time to it)")
    tune.add_argument("--objective", default=None, metavar="return-at=DURATION",
                      help="return-at=10m: the greedy return of the exported policy after that time, maximised "
                           "(in place of --target's time to the target)")
    tune.add_argument("--budget", default="30m", help="time for the search, such as 90s, 30m or 2h (default 30m)")
    tune.add_argument("--seeds", type=int, default=2, help="seeds per trial, run side by side (default 2, at least 2)")
    tune.add_argument("--workers", type=int, default=1, help="trials at a time (default 1)")
    tune.add_argument("--trials", type=int, default=None, help="stop once the study holds this many finished trials")
    tune.add_argument("--cap", type=float, default=None,
                      help="seconds after which a seed's run stops, missed (default: a tenth of --budget, at least 60; "
                           "with return-at=T: T and a quarter, plus 60)")
    tune.add_argument("--penalty", type=float, default=None, help="seconds added to a missed run's cap (default: the cap)")
    tune.add_argument("--confirm-seeds", type=int, default=2, help="fresh seeds the best setting is timed on (default 2)")
    tune.add_argument("--out", type=Path, default=None, help="study directory (default runs/tune-ALGO-ENV)")
    tune.set_defaults(func=run)


@dataclass(frozen=True)
class Plan:
    algos: list[str]
    env: str
    target: float | None
    """the return to reach soonest; None with ``return_at``"""
    overrides: list[str]
    """every trial's overrides (env= left out)"""
    seeds: int
    cap_s: float
    penalty_s: float
    budget_s: float
    workers: int
    trials: int | None
    confirm_seeds: int
    out: Path
    ray_address: str | None = None
    """``ray.address=``: the trials' runs are Ray actors on that cluster ('': a local Ray instance); None: processes here"""
    return_at: str | None = None
    """``--objective return-at=T``: T as written (``10m``); the objective is the return after T, maximised"""

    def study_settings(self) -> dict[str, Any]:
        """What a study is of: a rerun must match them to continue it."""
        return {k: v for k, v in asdict(self).items() if k in ("algos", "env", "target", "overrides", "seeds", "cap_s",
                                                               "penalty_s", "return_at")}

    @property
    def direction(self) -> str:
        return "maximize" if self.return_at else "minimize"

    @property
    def horizon_s(self) -> float | None:
        """the seconds a trial's runs are given (``return_at``), None when they run to the target"""
        return parse_budget(self.return_at) if self.return_at else None

    def trial_overrides(self) -> list[str]:
        """what every trial's runs add to the command's overrides: with ``return_at``, the time budget and the
        best evaluation's policy kept (unless the command says otherwise)"""
        if not self.return_at:
            return []
        keep = [] if any(o.split("=", 1)[0].strip() == "keep_best" for o in self.overrides) else ["keep_best=true"]
        return [f"time_budget={self.return_at}", *keep]

    def goal(self) -> str:
        """what the study is for, in words: 'to -200' or 'the return at 10m'"""
        return f"the return at {self.return_at}" if self.return_at else f"to {self.target:g}"


def parse_budget(text: str) -> float:
    """``90s``, ``30m``, ``2h``, ``1h30m`` or plain seconds -> seconds."""
    from rlpipe.pipelines.errors import InputError

    number = r"\d+(?:\.\d+)?"
    text = text.strip()
    if re.fullmatch(number, text):
        seconds = float(text)
    elif re.fullmatch(f"(?:{number}[smh])+", text):
        seconds = sum(float(n) * _UNITS[unit] for n, unit in re.findall(f"({number})([smh])", text))
    else:
        seconds = 0.0
    if not seconds > 0:
        raise InputError(f"--budget {text}: expected a positive duration such as 90s, 30m or 2h")
    return seconds


def make_plan(args) -> Plan:
    """The command's plan, its input checked (one line on bad input) before anything is written."""
    from rlpipe.envs import resolve_env_id
    from rlpipe.pipelines import ALGOS, pipeline_class
    from rlpipe.pipelines.errors import InputError
    from rlpipe.scripts.output_paths import check_output_dir

    try:
        import optuna  # noqa: F401
    except ImportError:
        raise InputError("rlpipe tune needs Optuna, which is not installed; expected `pip install 'rlpipe[tune]'`") from None
    algos = [a.strip() for a in args.algo.split(",") if a.strip()]
    for algo in algos or [args.algo]:
        if algo not in ALGOS:
            raise InputError(f"unknown algorithm {algo!r}; expected one of {', '.join(ALGOS)}, or several comma-separated")
        pipeline_class(algo)
    env = [o.split("=", 1)[1] for o in args.overrides if o.startswith("env=")]
    if not env or not env[-1]:
        raise InputError("no env: expected env=ID (a gymnasium id, or module:Class)")
    resolve_env_id(env[-1])
    overrides = [o for o in args.overrides if not o.startswith(("env=", "ray.address="))]
    out = args.out or Path("runs") / f"tune-{'-'.join(algos)}-{_slug(env[-1])}"
    check_output_dir(out)
    ray_address = next((o.split("=", 1)[1] for o in reversed(args.overrides) if o.startswith("ray.address=")), None)
    for name, value, least in (("--seeds", args.seeds, 2), ("--workers", args.workers, 1),
                               ("--confirm-seeds", args.confirm_seeds, 0), ("--trials", args.trials, 1)):
        if value is not None and value < least:
            raise InputError(f"{name}={value}: expected an integer of at least {least}")
    budget = parse_budget(args.budget)
    return_at = _objective(args)
    saved = _saved_settings(out)
    default_cap = parse_budget(return_at) * 1.25 + 60 if return_at else max(60.0, budget / 10)
    cap = args.cap if args.cap is not None else saved.get("cap_s", default_cap)
    penalty = args.penalty if args.penalty is not None else saved.get("penalty_s", cap)
    if not cap > 0 or penalty < 0:
        raise InputError(f"--cap {cap:g} --penalty {penalty:g}: expected a positive cap and a penalty of at least 0 seconds")
    budget_keys = [f"time_budget={return_at}"] if return_at else []
    for algo in algos:
        # an unknown key, a bad value, an env: its own line
        check_env(algo, base_config(algo, env[-1], [*overrides, *budget_keys]))
    if ray_address:
        from rlpipe.pipelines.workers.ray_runtime import check_address

        check_address(ray_address)
    return Plan(algos, env[-1], None if return_at else float(args.target), overrides, args.seeds, cap, penalty, budget,
                args.workers, args.trials, args.confirm_seeds, out.resolve(), ray_address, return_at)


def _objective(args) -> str | None:
    """``--objective return-at=T``'s T (None: time to ``--target``), the pair checked: one or the other."""
    from rlpipe.pipelines.errors import InputError

    if args.objective is None:
        if args.target is None:
            raise InputError("no objective: expected --target R (the time to a return of R) or --objective "
                             "return-at=DURATION (the return after that time, such as 10m)")
        return None
    kind, _, duration = args.objective.partition("=")
    if kind.strip() != "return-at" or not duration.strip():
        raise InputError(f"--objective {args.objective}: expected return-at=DURATION, such as return-at=10m "
                         "(for the time to a return, --target R)")
    try:
        parse_budget(duration)
    except InputError:
        raise InputError(f"--objective {args.objective}: expected a positive duration after return-at=, such as "
                         "90s, 10m or 2h") from None
    if args.target is not None:
        raise InputError(f"--target {args.target:g} and --objective {args.objective}: two objectives; expected one "
                         "(the time to a target, or the return at a time)")
    given = [o for o in args.overrides if o.split("=", 1)[0].strip() in ("time_budget", "target_return")]
    if given:
        raise InputError(f"{given[0]} with --objective {args.objective}: the objective sets each run's time budget; "
                         "expected neither time_budget= nor target_return= among the overrides")
    return duration.strip()


def check_env(algo: str, cfg) -> None:
    """The env made once, as a trial's runs make it: one that fails, or whose actions ``algo`` does not learn, is
    one line before anything runs."""
    from rlpipe.pipelines import pipeline_class
    from rlpipe.pipelines.own_parts import check_action_space, factory_and_env

    _, env = factory_and_env(None, cfg)
    try:
        check_action_space(algo, pipeline_class(algo).action_space, env.action_spec_unbatched, cfg.env)
    finally:
        env.close()


def _saved_settings(out: Path) -> dict[str, Any]:
    """The settings of the study stored in ``out`` ({} for none), read without changing it: a rerun keeps the
    study's --cap and --penalty unless it names them."""
    import sqlite3

    db = out / "study.db"
    if not db.exists():
        return {}
    try:
        with contextlib.closing(sqlite3.connect(f"file:{db}?mode=ro", uri=True)) as conn:
            row = conn.execute("SELECT value_json FROM study_user_attributes WHERE key = 'settings'").fetchone()
    except sqlite3.Error:
        return {}
    return json.loads(row[0]) if row else {}


def _slug(env: str) -> str:
    return re.sub(r"[^A-Za-z0-9]+", "-", env).strip("-").lower()


def base_config(algo: str, env: str, overrides: list[str]):
    """``rlpipe train ALGO env=ENV key=value ...``'s config: a trial's runs train it."""
    from rlpipe.pipelines.config import apply_overrides

    budget = next((o.split("=", 1)[1] for o in reversed(overrides) if o.split("=", 1)[0].strip() == "time_budget"),
                  None)
    return apply_overrides(_base(algo, env, budget), [f"env={env}", *overrides])


@functools.cache
def _base(algo: str, env: str, time_budget: str | None = None):
    """What ``rlpipe train ALGO env=ENV [time_budget=T]`` starts from: the preset sized for the env, a config
    sized for it (and for the time budget), or the algorithm's own preset (``pipelines/sizing.py`` decides, as for
    ``rlpipe train``); sized once per command."""
    from rlpipe.pipelines import resolve_preset
    from rlpipe.pipelines.sizing import resolve_for_env

    sized = resolve_for_env(algo, [f"env={env}", *([f"time_budget={time_budget}"] if time_budget else [])])
    return sized.config if sized is not None else resolve_preset(algo)[1]


# --- the study ----------------------------------------------------------------------------------------


def open_study(plan: Plan):
    """The study in ``OUT/study.db``, new or continued; a study of other settings is refused."""
    import optuna

    from rlpipe.pipelines.errors import InputError
    from rlpipe.scripts.tune_trials import BehindBestPruner

    settings = json.loads(json.dumps(plan.study_settings()))
    saved = _saved_settings(plan.out) or None  # compared before Optuna opens it: a study's direction is its own
    if saved is not None and any(saved.get(k) != settings[k] for k in settings):
        changed = next(k for k in settings if saved.get(k) != settings[k])
        raise InputError(f"{plan.out} holds a study with {changed}={saved.get(changed)!r}, not {settings[changed]!r}; "
                         "expected the same algorithm, env, objective, overrides, --seeds, --cap and --penalty to "
                         "continue it, or another --out")
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(
        storage=f"sqlite:///{(plan.out / 'study.db').resolve()}", study_name=STUDY, direction=plan.direction,
        sampler=optuna.samplers.TPESampler(n_startup_trials=5, constant_liar=True),
        pruner=BehindBestPruner(horizon_s=plan.horizon_s), load_if_exists=True)
    if study.user_attrs.get("settings") is None:
        study.set_user_attr("settings", settings)
        study.enqueue_trial(first_params(plan))
    return study


def first_params(plan: Plan) -> dict[str, Any]:
    """The first trial of a new study: what ``rlpipe train ALGO env=ENV`` trains (the first algorithm's), as far as
    the search space holds it (``tune_space.params_of``)."""
    from rlpipe.scripts import tune_space

    algo = plan.algos[0]
    params = tune_space.params_of(algo, base_config(algo, plan.env, [*plan.overrides, *plan.trial_overrides()]))
    return {"algo": algo, **params} if len(plan.algos) > 1 else params


def requeue_cut_short(study) -> list[int]:
    """Trials that an interruption (FAIL) or a crash (still RUNNING) cut short are asked again, once each."""
    from optuna.trial import TrialState

    done = set(study.user_attrs.get("requeued", []))
    cut = [t for t in study.get_trials(deepcopy=False, states=(TrialState.RUNNING, TrialState.FAIL))
           if t.number not in done and not t.user_attrs.get("refused") and not t.user_attrs.get("unevaluated")]
    for t in cut:
        if t.state == TrialState.RUNNING:  # its tuner died: one tuner holds the study at a time (the lock)
            study.tell(t.number, state=TrialState.FAIL)
        study.enqueue_trial(t.params, skip_if_exists=False)
    if cut:
        study.set_user_attr("requeued", sorted(done | {t.number for t in cut}))
    return [t.number for t in cut]


def finished(study) -> list:
    from optuna.trial import TrialState

    return study.get_trials(deepcopy=False, states=(TrialState.COMPLETE, TrialState.PRUNED))


def launch_trial(plan: Plan, number_of_processes: int, seeds: list[int], work: Path, trial=None, params=None):
    """A trial's seed runs, launched: Optuna's next trial (``trial``: an asked one; ``params``: a fixed setting)."""
    from rlpipe.scripts import tune_space
    from rlpipe.scripts.bench.time_to_return import Task, rlpipe_launch
    from rlpipe.scripts.tune_trials import RemoteRun, SeedRun, TrialRuns, budget_launch, returned_result

    if params is None:
        algo, keys = tune_space.suggest(trial, plan.algos)
    else:
        algo = params.get("algo", plan.algos[0])
        keys = tune_space.overrides(algo, params)
    threads = 1 if number_of_processes > 1 else None
    Run = SeedRun if plan.ray_address is None else RemoteRun
    runs = []
    for seed in seeds:
        run_dir, log = work / f"seed{seed}" / "run", work / f"seed{seed}" / "output.log"
        if plan.return_at:
            launch = budget_launch(algo, seed, run_dir, threads, [*plan.overrides, *plan.trial_overrides(), *keys])
            runs.append(Run(launch, run_dir, log, plan.cap_s, returned_result))
            continue
        cfg = base_config(algo, plan.env, [*plan.overrides, *keys])
        cap_steps = cfg.initial_collect_steps + cfg.num_iterations * cfg.collect_steps_per_iteration
        task = Task(plan.env, algo, plan.target, cap_steps, algo, (algo, ()))
        launch = rlpipe_launch(task, "rlpipe", seed, plan.target, cap_steps, run_dir, threads,
                               [*plan.overrides, *keys], preset=algo)
        runs.append(Run(launch, run_dir, log, plan.cap_s))
    trial_runs = TrialRuns(trial, algo, keys, runs)
    trial_runs.begin()
    return trial_runs


def search(study, plan: Plan, stop) -> list:
    """Ask, run and tell trials until the budget or ``--trials`` is spent; returns the trials running when a stop
    signal came (ended, and told as failed: a rerun runs them again)."""
    spent_before = float(study.user_attrs.get("spent_s", 0.0))
    began = time.time()
    running: list = []
    try:
        _search(study, plan, stop, running, spent_before, began)
    except BaseException:  # a second stop signal, or a failure: no run outlives the loop
        _cut_short(study, running, signal.SIGKILL)
        raise
    _cut_short(study, running, signal.SIGTERM)
    study.set_user_attr("spent_s", spent_before + time.time() - began)
    return running


def _search(study, plan: Plan, stop, running: list, spent_before: float, began: float) -> None:
    from rlpipe.pipelines.system.faults import fault_point

    processes = plan.workers * plan.seeds
    while True:
        spent = spent_before + time.time() - began
        while (not stop.requested and len(running) < plan.workers and spent < plan.budget_s
               and (plan.trials is None or len(finished(study)) + len(running) < plan.trials)):
            trial = study.ask()
            trial_runs = launch_trial(plan, processes, list(range(plan.seeds)),
                                      plan.out / "trials" / f"{trial.number:04d}", trial=trial)
            running.append(trial_runs)
            print(f"trial {trial.number}: {trial_runs.algo} {' '.join(trial_runs.overrides)}", flush=True)
            fault_point("tune_trial", trial.number)  # tests: a stop signal while a trial runs
        if stop.requested or not running:
            return
        time.sleep(POLL_S)
        for trial_runs in list(running):
            if trial_runs.poll():
                running.remove(trial_runs)
                tell(study, plan, trial_runs)
        study.set_user_attr("spent_s", spent_before + time.time() - began)


def _cut_short(study, running: list, sig: int) -> None:
    for trial_runs in running:
        trial_runs.stop(sig)
        trial_runs.close()
        study.tell(trial_runs.trial, state=_state("FAIL"))


def _state(name: str):
    from optuna.trial import TrialState

    return getattr(TrialState, name)


def tell(study, plan: Plan, trial_runs) -> None:
    """Tell Optuna a trial's end: pruned, or its time (a run that missed: cap + penalty)."""
    from rlpipe.pipelines.errors import InputError
    from rlpipe.scripts.tune_trials import seconds, trial_value

    trial = trial_runs.trial
    results = [] if trial_runs.pruned else trial_runs.results()
    trial_runs.close()
    if trial_runs.pruned:
        study.tell(trial, state=_state("PRUNED"))
        print(f"trial {trial.number}: pruned at {trial_runs.reported} s (behind the best trial's curve)", flush=True)
        return
    if all(r["rc"] == 2 for r in results):  # every seed refused its input: the settings, not the luck
        trial.set_user_attr("refused", True)  # not asked again on a rerun
        study.tell(trial, state=_state("FAIL"))
        raise InputError(f"trial {trial.number}'s runs refused their input: {results[0].get('error', '')} "
                         f"(log: {results[0]['log']})")
    if plan.return_at:
        _tell_return(study, plan, trial, results)
        return
    times = [seconds(r, plan.cap_s, plan.penalty_s) for r in results]
    trial.set_user_attr("seconds", times)
    trial.set_user_attr("reached", [bool(r.get("reached")) for r in results])
    trial.set_user_attr("nodes", [r.get("node") for r in results])
    value = trial_value(results, plan.cap_s, plan.penalty_s)
    study.tell(trial, value)
    print(f"trial {trial.number}: {value:.1f} s (seeds: " + ", ".join(
        f"{t:.1f}" + ("" if r.get("reached") else " missed") for t, r in zip(times, results)) + ")", flush=True)


def _tell_return(study, plan: Plan, trial, results: list[dict[str, Any]]) -> None:
    """A return-at trial's end: the mean of its seeds' returns; a seed that ended with no evaluation (a crash, its
    cap) fails the trial, which a rerun does not run again (its settings, not an interruption, ended it)."""
    returns = [r.get("return") for r in results]
    trial.set_user_attr("returns", returns)
    trial.set_user_attr("nodes", [r.get("node") for r in results])
    if any(v is None for v in returns):
        trial.set_user_attr("unevaluated", True)
        study.tell(trial, state=_state("FAIL"))
        bad = next(r for r in results if r.get("return") is None)
        print(f"trial {trial.number}: failed, a run ended with no evaluation: {bad.get('error', '')} "
              f"(log: {bad['log']})", flush=True)
        return
    value = statistics.fmean(returns)
    study.tell(trial, value)
    print(f"trial {trial.number}: return {value:.1f} at {plan.return_at} (seeds: "
          + ", ".join(f"{v:.1f}" for v in returns) + ")", flush=True)


def value_text(plan: Plan, value: float) -> str:
    """A trial's value in words: '41.2 s' (time to the target) or 'return 812.3' (the return at a time)."""
    return f"return {value:.1f}" if plan.return_at else f"{value:.1f} s"


# --- after the search ---------------------------------------------------------------------------------


def confirm(study, plan: Plan, stop) -> dict[str, Any] | None:
    """The best trial's setting timed on ``--confirm-seeds`` fresh seeds (kept in the study: a rerun reuses it)."""
    from rlpipe.pipelines.errors import InputError
    from rlpipe.scripts.tune_trials import seconds, trial_value

    if not study.get_trials(deepcopy=False, states=(_state("COMPLETE"),)):
        raise InputError(f"no trial finished within the budget ({plan.budget_s:g} s); expected a longer --budget or a "
                         "shorter --cap")
    best = study.best_trial
    saved = study.user_attrs.get("confirmation")
    if plan.confirm_seeds == 0 or (saved and saved["trial"] == best.number and len(saved["seeds"]) == plan.confirm_seeds):
        return saved
    seeds = list(range(CONFIRM_FIRST_SEED, CONFIRM_FIRST_SEED + plan.confirm_seeds))
    print(f"confirming trial {best.number} on fresh seeds {', '.join(map(str, seeds))}", flush=True)
    trial_runs = launch_trial(plan, len(seeds), seeds, plan.out / "confirm" / f"{best.number:04d}",
                              params=best.params)
    while not all(run.done() for run in trial_runs.runs):
        if stop.requested:
            trial_runs.stop()
            trial_runs.close()
            return None
        time.sleep(POLL_S)
    results = trial_runs.results()
    trial_runs.close()
    if plan.return_at:
        returns = [r.get("return") for r in results]
        got = [v for v in returns if v is not None]
        confirmation = {"trial": best.number, "seeds": seeds, "returns": returns,
                        "value": statistics.fmean(got) if got else None}
        study.set_user_attr("confirmation", confirmation)
        return confirmation
    confirmation = {"trial": best.number, "seeds": seeds,
                    "seconds": [seconds(r, plan.cap_s, plan.penalty_s) for r in results],
                    "reached": [bool(r.get("reached")) for r in results],
                    "value": trial_value(results, plan.cap_s, plan.penalty_s)}
    study.set_user_attr("confirmation", confirmation)
    return confirmation


def write_preset(study, plan: Plan) -> Path:
    """The best setting as a preset file: ``rlpipe train`` takes it as it takes a shipped preset."""
    from rlpipe.pipelines import presets
    from rlpipe.pipelines.config import PresetInfo
    from rlpipe.scripts import tune_space

    best = study.best_trial
    algo = best.params.get("algo", plan.algos[0])
    keys = [*plan.overrides, *plan.trial_overrides(), *tune_space.overrides(algo, best.params)]
    cfg = base_config(algo, plan.env, keys)
    name = f"{algo}-{_slug(plan.env)}-tuned"
    path = plan.out / f"{name}.yaml"
    if plan.return_at:
        info = PresetInfo(plan.env, (), f"tuned by rlpipe tune for the return at {plan.return_at}", True)
    else:
        info = PresetInfo(plan.env, (plan.target,), f"tuned by rlpipe tune for time to {plan.target:g}", True)
    presets.save(path, algo, cfg, info=info,
                 comment=f"{name}: {plan.env}, {plan.goal()}, found by rlpipe tune (trial {best.number}: "
                         f"{value_text(plan, best.value)} over seeds 0-{plan.seeds - 1}); figures: "
                         f"{plan.out / 'tune.html'}")
    return path


def run(args) -> int:
    from rlpipe.scripts.tune_page import write_page

    plan = make_plan(args)
    plan.out.mkdir(parents=True, exist_ok=True)
    with _only_tuner(plan.out), _ray(plan):
        study = open_study(plan)
        again = requeue_cut_short(study)
        if again:
            print(f"running again the trials cut short: {', '.join(map(str, again))}", flush=True)
        stop = _stop_request()
        with stop:
            cut = search(study, plan, stop)
            confirmation = None if stop.requested else confirm(study, plan, stop)
        if stop.requested:
            print(f"rlpipe: interrupted; {len(finished(study))} finished trials kept in {plan.out / 'study.db'} "
                  f"({len(cut)} cut short, to run again); rerun the same command to continue", file=sys.stderr)
            return 128 + stop.signum
        preset = write_preset(study, plan)
        page = write_page(study, plan, confirmation, preset)
    best = study.best_trial
    results = {"objective": f"return-at={plan.return_at}" if plan.return_at else f"time-to={plan.target:g}",
               "best_trial": best.number, "best_value": best.value, "best_params": best.params,
               "confirmation": confirmation, "preset": str(preset), "page": str(page),
               "trials": len(study.trials), "finished": len(finished(study))}
    results["best_return" if plan.return_at else "best_seconds"] = best.value
    (plan.out / "results.json").write_text(json.dumps(results, indent=1))
    seen = (f"; on fresh seeds {confirmation['seeds']}: {value_text(plan, confirmation['value'])}"
            if confirmation and confirmation["value"] is not None else "")
    if plan.return_at:
        print(f"best: trial {best.number}, return {best.value:.1f} at {plan.return_at} on seeds 0-{plan.seeds - 1}"
              f"{seen} (mean of seeds: the greedy return of the policy each run exports)")
    else:
        print(f"best: trial {best.number}, {best.value:.1f} s to {plan.target:g} on seeds 0-{plan.seeds - 1}{seen} "
              f"(mean of seeds; a miss counts {plan.cap_s + plan.penalty_s:g} s)")
    print(f"preset: {preset} (rlpipe train {preset})")
    print(f"page: {page}")
    return 0


def _stop_request():
    """Ctrl-C, SIGTERM or SIGHUP as a flag the loop reads between polls (``DeferredInterrupt``), without the line a
    training run prints about its checkpoint: the tuner's own line says what was kept. A second one stops at once."""
    from rlpipe.pipelines.system.runtime import DeferredInterrupt

    class StopRequest(DeferredInterrupt):
        def _handle(self, signum, frame) -> None:
            with contextlib.redirect_stderr(io.StringIO()):
                super()._handle(signum, frame)

    return StopRequest()


@contextlib.contextmanager
def _only_tuner(out: Path):
    """One ``rlpipe tune`` on a study at a time (an OS file lock, let go when the process ends however it ends)."""
    from rlpipe.pipelines.errors import InputError

    with (out / "tune.lock").open("w") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise InputError(f"{out}: another rlpipe tune is running on this study; expected another --out") from None
        yield


@contextlib.contextmanager
def _ray(plan: Plan):
    """With ``ray.address=``: this command's hold on Ray (the cluster joined, or a local instance) while it runs."""
    if plan.ray_address is None:
        yield
        return
    from rlpipe.pipelines.workers.ray_runtime import RayRuntime

    runtime = RayRuntime(plan.ray_address, plan.workers * plan.seeds)
    try:
        yield
    finally:
        runtime.close()
