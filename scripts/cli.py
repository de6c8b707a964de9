"""The ``rlpipe`` command line.

    rlpipe train PRESET|FILE.yaml [key=value ...] [--out DIR] [--resume DIR]
    rlpipe train [sac|td3|dqn] env=ID [key=value ...]   (sized for the env: pipelines/sizing.py)
    rlpipe eval RUN_DIR [--step N] [--trust] [--episodes N] [--json] [--ecdf]
    rlpipe eval RUN_DIR --random | rlpipe eval --env ID --random
    rlpipe video RUN_DIR [--step N] [--trust] [--episodes N] [--random] [--out FILE]
    rlpipe plot RUN_DIR [RUN_DIR ...] [--out FILE]
    rlpipe report RUN_DIR [RUN_DIR ...] [--out FILE]
    rlpipe presets [--show NAME|FILE.yaml]
    rlpipe ablate td3 --envs A,B --seeds N --steps S [--workers W] [--out DIR]
    rlpipe tune ALGO[,ALGO] env=ID --target R [--budget 30m] [--workers N] [--seeds 2] [--out DIR]   (scripts/tune.py)
    rlpipe bench {dqn,td3,sac,minitaur,floor,cleanrl,gpu,profile,collect,ray,time-to-return,threads} [...]   (scripts/bench/)

Bad input ends with one line on stderr naming what is wrong and what is expected, and exit status 2.
Any other failure ends with one line naming the error and the file holding its full traceback
(``RUN/error.log`` when a run directory exists, else a temporary file), and exit status 1.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import sys
import tempfile
import time
import traceback
from pathlib import Path

from rlpipe.scripts.output_paths import check_output_dir, check_output_file

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
# TorchRL announces every storage it initialises at INFO level, on stdout; keep the output ours.
os.environ.setdefault("RL_LOGGING_LEVEL", "WARNING")


class _Parser(argparse.ArgumentParser):
    """argparse with the one-line error contract: ``rlpipe: error: ...`` and exit status 2."""

    def error(self, message: str):
        print(f"rlpipe: error: {message} (see `{self.prog} --help`)", file=sys.stderr)
        raise SystemExit(2)


_TRUST_HELP = ("also load a policy that exists only as policy.pt2 (torch.export): loading one unpickles parts of it, "
               "which can run code; only for runs you trust (policy.onnx, data only, needs no flag)")


def _parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="rlpipe", description="RL pipelines (SAC, TD3, DQN) on TorchRL.")
    sub = parser.add_subparsers(dest="command", required=True)

    train = sub.add_parser("train", help="train a preset (dqn, dqn-cartpole-v1, td3, sac, ...)")
    train.add_argument("preset", help="preset name (`rlpipe presets` lists them) or preset file (PATH.yaml: a file "
                       "`rlpipe presets --show NAME` prints, or `rlpipe tune` writes); env=ID alone trains SAC (Box "
                       "actions) or DQN (Discrete) sized for that env, as `sac`, `td3`, `dqn` are when env= names "
                       "another env than their tutorial's")
    train.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides, dotted for groups (collector.workers=2)")
    train.add_argument("--out", type=Path, help="run directory (default runs/<algo>-<env>-<time>)")
    train.add_argument("--resume", type=Path, metavar="RUN_DIR", help="continue the run in RUN_DIR from its last checkpoint")
    train.add_argument("--no-progress", action="store_true", help="no progress bar")
    train.add_argument("--keys", action="store_true", help="list the preset's keys with their values and meaning, then exit")
    train.add_argument("--start-method", choices=("forkserver", "spawn"), default="forkserver",
                       help="how collector and evaluator processes start: forked from a server that has imported "
                            "torch and TorchRL once (default), or each a fresh interpreter (TorchRL's spawn)")

    ev = sub.add_parser("eval", help="evaluate a run's exported policy (or a random agent)")
    ev.add_argument("run_dir", type=Path, nargs="?", help="the run whose policy/policy.onnx to evaluate")
    ev.add_argument("--step", type=int, help="the policy exported at this iteration (policy/step_NNNNNNN.onnx) instead of the latest")
    ev.add_argument("--trust", action="store_true", help=_TRUST_HELP)
    ev.add_argument("--random", action="store_true", help="a uniformly random agent instead (the tutorials' baseline), on the run's env or --env")
    ev.add_argument("--env", metavar="ID", help="with --random and no RUN_DIR: the env to evaluate the random agent on")
    ev.add_argument("--episodes", type=int, default=10)
    ev.add_argument("--seed", type=int, default=12345)
    ev.add_argument("--json", action="store_true", help="print the result as JSON")
    ev.add_argument("--ecdf", action="store_true", help="also plot the ECDF of episode returns to RUN_DIR/ecdf.png")

    video = sub.add_parser("video", help="an mp4 of a run's policy acting (or of a random policy)")
    video.add_argument("run_dir", type=Path)
    video.add_argument("--step", type=int, help="the policy exported at this iteration (policy/step_NNNNNNN.onnx) instead of the latest")
    video.add_argument("--trust", action="store_true", help=_TRUST_HELP)
    video.add_argument("--episodes", type=int, default=3)
    video.add_argument("--random", action="store_true", help="a random policy instead, for comparison")
    video.add_argument("--out", type=Path, help="mp4 path (default RUN_DIR/trained-agent.mp4, trained-agent-step_N.mp4 with --step, or random-agent.mp4)")
    video.add_argument("--seed", type=int, default=0)

    plot = sub.add_parser("plot", help="return curves of one or more runs in one PNG")
    plot.add_argument("run_dirs", type=Path, nargs="+")
    plot.add_argument("--out", type=Path, default=Path("returns.png"))

    report = sub.add_parser("report", help="a run's report.html again, or one HTML page comparing several runs")
    report.add_argument("run_dirs", type=Path, nargs="+")
    report.add_argument("--out", type=Path,
                        help="HTML file (default: RUN_DIR/report.html for one run, compare.html for several)")

    presets = sub.add_parser("presets", help="list the presets: algorithm, the task each is for, its measured time to target")
    presets.add_argument("--show", metavar="NAME", help="print preset NAME's file (or a preset file PATH.yaml) instead: "
                                                         "a start for a file of your own (`rlpipe train my.yaml`)")

    from rlpipe.scripts import ablate, bench, tune

    ablate.add_parser(sub)
    bench.add_parser(sub)
    tune.add_parser(sub)
    return parser


def _positive(name: str, value: int) -> None:
    from rlpipe.pipelines.errors import InputError

    if value <= 0:
        raise InputError(f"{name}={value}: expected a positive integer")


def _value_of(cfg, key: str):
    for part in key.split("."):
        cfg = getattr(cfg, part)
    return cfg


def cmd_train(args) -> int:
    from rlpipe.pipelines import device_hint, pipeline_class, resolve_preset, size_hint
    from rlpipe.pipelines.artifacts.rundir import RunDir, default_run_dir
    from rlpipe.pipelines.config import apply_overrides, config_from_dict, field_docs, flat_keys
    from rlpipe.pipelines.errors import InputError
    from rlpipe.pipelines.sizing import resolve_for_env
    from rlpipe.pipelines.system.runtime import start_fork_server
    from rlpipe.pipelines.workers.factory import backend_class
    from rlpipe.pipelines.workers.supervision import NoRestartLeft

    # `env=ID` with no preset, or a tutorial preset pointed at another env: sized for that env (pipelines/sizing.py)
    sized = resolve_for_env(args.preset, args.overrides, resume=args.resume is not None)
    algo, cfg = (sized.algo, sized.config) if sized else resolve_preset(args.preset)
    overrides, chosen = (sized.overrides, sized.lines) if sized else (args.overrides, [])
    Pipeline = pipeline_class(algo)
    if args.resume is not None:
        if args.out is not None and args.out.resolve() != args.resume.resolve():
            raise InputError("--out and --resume name different directories; expected one run directory")
        run = RunDir.open(args.resume)
        saved_algo, saved = run.read_config()
        if saved_algo != algo:
            raise InputError(f"{args.resume} holds a {saved_algo} run; expected a {algo} run for preset {args.preset!r}")
        cfg = config_from_dict(Pipeline.Config, saved)
    cfg = apply_overrides(cfg, overrides)
    hint = None if args.resume is not None or sized else size_hint(args.preset, cfg)
    if args.keys:  # the values this command would train with, overrides included, and where each came from
        docs = field_docs(type(cfg))
        named = {o.partition("=")[0].strip() for o in overrides}
        base = (f"{args.resume}/config.json" if args.resume is not None else sized.source if sized
                else f"preset {args.preset}")
        default = Pipeline.Config()
        for key in flat_keys(type(cfg)):
            value = _value_of(cfg, key)
            source = ("command line" if any(n == key or n.startswith(key + ".") for n in named)
                      else base if value != _value_of(default, key) else "default")
            print(f"{key}={json.dumps(value)}\n    [{source}] {docs.get(key, '')}")
        for line in chosen:
            print(line, file=sys.stderr)
        if hint:
            print(f"rlpipe: hint: {hint}", file=sys.stderr)
        return 0
    if args.fork_server and args.start_method == "forkserver" and backend_class(cfg).starts_processes(cfg):
        start_fork_server()  # its imports run while the pipeline is built
    pipeline = Pipeline(cfg)
    for line in chosen:  # the run's first lines: what was chosen for its env, and why
        print(line, flush=True)
    for line in (hint, device_hint(pipeline.config)):  # once the env and device are known to fit (else the error
        if line:                                        # is the one line); a hint: the run goes on as asked
            print(f"rlpipe: hint: {line}", file=sys.stderr)
    args.pipeline = pipeline  # where main() writes a traceback, once the run directory exists
    out = args.resume if args.resume is not None else args.out
    check_output_dir(out if out is not None else default_run_dir(algo, pipeline.config.env),
                     "--resume" if args.resume is not None else "--out")
    _show_live_log()
    try:
        result = pipeline.train(out, resume=args.resume is not None, progress=not args.no_progress)
    except KeyboardInterrupt as exc:  # Ctrl-C, SIGTERM or SIGHUP: exit 128 + the signal's number
        run_dir = getattr(getattr(pipeline, "run_dir", None), "path", out)
        signame = getattr(exc, "signum", None)
        by = f" by {signal.Signals(signame).name}" if signame not in (None, signal.SIGINT) else ""
        print(f"rlpipe: interrupted{by}; continue with: rlpipe train {args.preset} --resume {run_dir}", file=sys.stderr)
        return getattr(exc, "exit_status", 130)
    except NoRestartLeft as exc:
        run_dir = getattr(getattr(pipeline, "run_dir", None), "path", out)
        print(f"rlpipe: error: {exc}; continue with: rlpipe train {args.preset} --resume {run_dir}", file=sys.stderr)
        return exc.exit_status
    s = result.summary
    print(f"AverageReturn = {s['final_average_return']:.2f}  AverageEpisodeLength = {s['final_average_episode_length']:.1f}")
    print(f"{s['iterations']} iterations, {s['frames']} env steps, {s['updates']} updates in {s['wall_time_s']:.0f} s "
          f"({s['env_steps_per_s'] or 0:.0f} env steps/s, {s['updates_per_s'] or 0:.0f} updates/s while training)")
    print(f"run directory: {result.run_dir}")
    why = {"target": f"the target return {result.summary.get('target', {}).get('return')} was reached",
           "time_budget": f"the time budget {getattr(pipeline.config, 'time_budget', '')} was spent",
           "plateau": (f"a plateau: no greedy evaluation beat step {s.get('best_evaluation', {}).get('step')}'s over "
                       f"the last {getattr(pipeline.config, 'plateau', 0):g} of the run (plateau)"),
           "num_iterations": f"its last iteration came (num_iterations={s['iterations']})"}
    best = s.get("best_evaluation")
    if best and best["exported"]:
        print(f"policy: the best greedy evaluation's, step {best['step']} (AverageReturn = {best['average_return']:.2f})")
    print(f"stopped because {why.get(s['stopped_because'], s['stopped_because'])}")
    return 0


def _show_live_log() -> None:
    """The run's live log (rlpipe's INFO records: the tutorials' `step = N: ...` lines) on stdout."""
    import logging

    class CurrentStdout(logging.StreamHandler):
        """Writes to whatever ``sys.stdout`` is when a record comes: in-process callers of ``main``
        (tests capturing output) swap it between runs, and a handler bound to a closed one errs."""

        stream = property(lambda self: sys.stdout, lambda self, value: None)

    log = logging.getLogger("rlpipe")
    if not any(getattr(h, "rlpipe_live_log", False) for h in log.handlers):
        handler = CurrentStdout()
        handler.setFormatter(logging.Formatter("%(message)s"))
        handler.rlpipe_live_log = True
        log.addHandler(handler)
    log.setLevel(logging.INFO)
    log.propagate = False  # not twice where the root logger prints too


def _run_config(run_dir: Path):
    from rlpipe.pipelines import pipeline_class
    from rlpipe.pipelines.artifacts.rundir import RunDir
    from rlpipe.pipelines.config import config_from_dict

    run = RunDir.open(run_dir)
    algo, saved = run.read_config()
    return run, config_from_dict(pipeline_class(algo).Config, saved)


def _run_env(run, cfg) -> str:
    """A run's ``env`` (checked to name a gymnasium id), or one line saying why `rlpipe eval`/`video` cannot make its env:
    a run on a user's own env (``env=`` from Python) is labelled with a name no id answers to."""
    from rlpipe.envs import EnvError, resolve_env_id
    from rlpipe.envs.user import is_user_env
    from rlpipe.pipelines.errors import InputError

    try:
        resolve_env_id(cfg.env)
        return cfg.env
    except EnvError as exc:
        if "extra" in str(exc) or is_user_env(cfg.env):  # a package missing here: that line says which
            raise
        raise InputError(
            f"{run.path} was trained on env {cfg.env!r}, which is no gymnasium id rlpipe can make (an env given from "
            f"Python, env=...); expected a run on a gymnasium id, or its policy evaluated from Python on your env: "
            f"evaluate(env, TensorDictModule(load_policy('{run.policy_dir}')[0], ['observation'], ['action']), 10) "
            f"(rlpipe.pipelines.workers.evaluation, rlpipe.pipelines.artifacts.export)") from None


def cmd_eval(args) -> int:
    from tensordict.nn import TensorDictModule

    from rlpipe.envs import make_env
    from rlpipe.pipelines.artifacts.export import load_policy
    from rlpipe.pipelines.config import env_options
    from rlpipe.pipelines.errors import InputError
    from rlpipe.pipelines.workers.evaluation import evaluate

    _positive("--episodes", args.episodes)
    if args.run_dir is None and args.env is None:
        raise InputError("no run directory: expected `rlpipe eval RUN_DIR`, or `rlpipe eval --env ID --random` for a random agent")
    if args.env is not None and not args.random:
        raise InputError(f"--env {args.env} without --random: a run's policy is evaluated on the run's own env; "
                         "expected --random with --env")
    if args.env is not None and args.run_dir is not None:
        raise InputError(f"both {args.run_dir} and --env {args.env}: expected one of them (a run names its own env)")
    _check_random_without_step(args)
    run, env_id, env_kwargs = None, args.env, {}
    if args.run_dir is not None:
        run, cfg = _run_config(args.run_dir)
        env_id, env_kwargs = _run_env(run, cfg), {**cfg.env_kwargs, **env_options(cfg, rescaled=False)}
    if args.random:
        module, source = None, "random"
    else:
        module, _ = load_policy(run.policy_dir, step=args.step, trust=args.trust)
        source = str(module.path)
    env = make_env(env_id, seed=args.seed, **env_kwargs)
    if module is None:
        import torch
        from torchrl.envs.utils import RandomPolicy

        torch.manual_seed(args.seed)  # RandomPolicy draws from the action spec with torch's generator
        policy = RandomPolicy(env.action_spec)
    else:
        policy = TensorDictModule(module, in_keys=["observation"], out_keys=["action"])
    result = evaluate(env, policy, args.episodes)
    if args.ecdf:
        from rlpipe.pipelines.analysis import plot_ecdf

        folder = run.path if run is not None else Path.cwd()
        name = "ecdf-random.png" if args.random else "ecdf.png" if args.step is None else f"ecdf-step_{args.step}.png"
        what = "random agent" if args.random else "policy" if args.step is None else f"policy at iteration {args.step}"
        result["ecdf_png"] = str(plot_ecdf(result["returns"], folder / name,
                                           title=f"{env_id}: {what}, {args.episodes} episodes"))
    if args.json:
        print(json.dumps({"AverageReturn": result["average_return"], "AverageEpisodeLength": result["average_episode_length"],
                          "returns": result["returns"], "policy": source, "env": env_id,
                          **({"ecdf_png": result["ecdf_png"]} if args.ecdf else {})}))
    else:
        print(f"AverageReturn = {result['average_return']:.2f}")
        print(f"AverageEpisodeLength = {result['average_episode_length']:.1f}")
        if args.ecdf:
            print(f"ECDF of returns: {result['ecdf_png']}")
    return 0


def _check_random_without_step(args) -> None:
    from rlpipe.pipelines.errors import InputError

    if args.random and args.step is not None:
        raise InputError(f"--step {args.step} picks an exported policy and --random acts without one; expected one of them")


def cmd_video(args) -> int:
    from rlpipe.pipelines.analysis.report_pages import VIDEO_FILE, write_run_report
    from rlpipe.pipelines.artifacts.export import load_policy
    from rlpipe.pipelines.artifacts.video import record_video
    from rlpipe.pipelines.config import env_options

    _positive("--episodes", args.episodes)
    _check_random_without_step(args)
    if args.out is not None:
        check_output_file(args.out)
    run, cfg = _run_config(args.run_dir)
    env_id = _run_env(run, cfg)
    policy = None if args.random else load_policy(run.policy_dir, step=args.step, trust=args.trust)[0]
    name = "random-agent.mp4" if args.random else "trained-agent.mp4" if args.step is None else f"trained-agent-step_{args.step}.mp4"
    path = record_video(env_id, policy, args.out or run.path / name, episodes=args.episodes, seed=args.seed,
                        env_kwargs=cfg.env_kwargs, observation_options=env_options(cfg, rescaled=False))
    print(f"video: {path}")
    if not args.random and path == run.path / VIDEO_FILE:  # the page shows the trained agent's video
        print(f"report: {write_run_report(run.path)}")
    return 0


def cmd_plot(args) -> int:
    from rlpipe.pipelines.analysis import plot_return_curves
    from rlpipe.pipelines.analysis.runs import read_run_info
    from rlpipe.pipelines.artifacts.rundir import RunDir

    for run_dir in args.run_dirs:
        RunDir.open(run_dir)
    check_output_file(args.out)
    path = plot_return_curves(list(args.run_dirs), args.out)
    envs = list(dict.fromkeys(str(read_run_info(run).get("env") or "env unknown") for run in args.run_dirs))
    print(f"plot: {path}" + (f" (one axis per env: {', '.join(envs)})" if len(envs) > 1 else ""))
    return 0


def cmd_report(args) -> int:
    from rlpipe.pipelines.analysis.report_pages import write_comparison_report, write_run_report
    from rlpipe.pipelines.artifacts.rundir import RunDir
    from rlpipe.pipelines.errors import InputError

    for run_dir in args.run_dirs:
        RunDir.open(run_dir)
    if args.out is not None and args.out.suffix.lower() not in (".html", ".htm"):
        raise InputError(f"--out {args.out}: expected an .html file")
    if args.out is not None and args.out.is_dir():
        raise InputError(f"--out {args.out}: is a directory; expected an .html file")
    if len(args.run_dirs) == 1:
        print(f"report: {write_run_report(args.run_dirs[0], args.out)}")
        return 0
    try:
        path = write_comparison_report(args.run_dirs, args.out or Path("compare.html"))
    except ValueError as exc:  # a run without an evaluation
        raise InputError(f"{exc}; expected runs with at least one evaluation") from exc
    print(f"report: {path}")
    return 0


def _measured(entry: dict) -> str:
    """A preset's measured time to its target, as its file's ``info.measured`` records it."""
    if not entry:
        return "not measured yet"
    when = ", ".join(str(entry[k]) for k in ("date", "commit") if entry.get(k))
    to = f" to {entry['target']:g}" if entry.get("target") is not None else ""  # a preset with two targets
    return f"{entry['seconds']:.1f} s{to}" + (f" ({when})" if when else "")


def cmd_presets(args) -> int:
    from rlpipe.pipelines import preset_info, presets, resolve_preset

    if args.show is not None:
        resolve_preset(args.show)  # a file that does not load: its one line, not its text
        print(presets.text(args.show), end="")
        return 0
    rows = [("preset", "algo", "env", "iterations", "target", "time to target", "what it is")]
    for name, algo in presets.names().items():
        info, cfg = preset_info(name), resolve_preset(name)[1]
        targets = " then ".join(f"{t:g}" for t in info.targets) if info and info.targets else "-"
        rows.append((name, algo, cfg.env, str(cfg.num_iterations), targets,
                     _measured(dict(info.measured)) if info and info.targets else "-", info.task if info else ""))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]) - 1)]
    for row in rows:
        print("  ".join(cell.ljust(w) for cell, w in zip(row, widths)) + "  " + row[-1])
    return 0


def _error_log(args, argv: list[str], exc: BaseException) -> Path:
    """Write ``exc``'s traceback to RUN/error.log (the run's, where one exists) or a temporary file."""
    text = f"{time.strftime('%Y-%m-%d %H:%M:%S')} rlpipe {' '.join(map(str, argv))}\n" + "".join(
        traceback.format_exception(exc))
    run = getattr(getattr(args, "pipeline", None), "run_dir", None)
    run_path = getattr(run, "path", None)
    resume = getattr(args, "resume", None)
    if run_path is None and resume is not None and (Path(resume) / "config.json").exists():
        run_path = Path(resume)
    if run_path is not None:
        try:
            with open(Path(run_path) / "error.log", "a") as fh:
                fh.write(text + "\n")
            return Path(run_path) / "error.log"
        except OSError:
            pass
    fd, name = tempfile.mkstemp(prefix="rlpipe-error-", suffix=".log")
    with os.fdopen(fd, "w") as fh:
        fh.write(text)
    return Path(name)


def main(argv: list[str] | None = None, *, fork_server: bool | None = None) -> int:
    """``rlpipe ARGV`` (None: the command line). ``fork_server``: whether ``train`` may start its worker processes
    from a fork server (``--start-method``), which sets this process's multiprocessing start method; default: only
    when run as the program (``argv`` None), not when called from a program of its own with ``argv``.

    What cannot be shown is dropped (the reader of a pipe gone, the terminal closed, the descriptors closed): the
    command goes on and ends with its own status. As the program, any number of stop signals end it as the first
    asked (``runtime.hold_stops_to_exit``): 130, 143 or 129 and one line, never a traceback."""
    try:  # rlpipe.pipelines (numpy, the configs): the first import that takes time
        from rlpipe.pipelines.system import runtime
    except KeyboardInterrupt:
        with contextlib.suppress(OSError):
            os.write(2, b"rlpipe: interrupted\n")  # unbuffered: nothing is left to fail at the interpreter's exit
        return 130
    program = argv is None  # the rlpipe program: its stops are held to its exit (a caller's own Python: not)
    if program:
        runtime.hold_stops_to_exit()
    runtime.open_closed_descriptors()
    with runtime.output_dropped_when_gone():
        try:
            status = _command(argv, fork_server)
        except KeyboardInterrupt as exc:  # while the command starts (its imports take seconds), or around a run
            signum = getattr(exc, "signum", signal.SIGINT)  # (a run's own stop is answered in cmd_train)
            by = f" by {signal.Signals(signum).name}" if signum != signal.SIGINT else ""
            print(f"rlpipe: interrupted{by}", file=sys.stderr)
            status = 128 + int(signum)
        return runtime.command_returned(status) if program else status


def _command(argv: list[str] | None, fork_server: bool | None) -> int:
    from rlpipe.envs import EnvError
    from rlpipe.pipelines.errors import InputError, TrainingDiverged

    parser = _parser()
    args, extra = parser.parse_known_args(argv)
    args.fork_server = argv is None if fork_server is None else fork_server
    # key=value overrides may come after options too (`--resume RUN num_iterations=40000`).
    if extra and hasattr(args, "overrides") and all("=" in e and not e.startswith("-") for e in extra):
        args.overrides = [*args.overrides, *extra]
    elif extra:
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    commands = {"train": cmd_train, "eval": cmd_eval, "video": cmd_video, "plot": cmd_plot,
                "report": cmd_report, "presets": cmd_presets}
    try:
        if args.command in commands:
            return commands[args.command](args)
        return args.func(args)
    except (InputError, EnvError) as exc:
        print(f"rlpipe: error: {exc}", file=sys.stderr)
        return 2
    except TrainingDiverged as exc:
        print(f"rlpipe: error: {exc}", file=sys.stderr)
        return 1
    except Exception as exc:
        log = _error_log(args, sys.argv[1:] if argv is None else argv, exc)
        first = (str(exc).strip().splitlines() or [""])[0][:300]
        print(f"rlpipe: error: {type(exc).__name__}{': ' + first if first else ''} (full traceback in {log})",
              file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
