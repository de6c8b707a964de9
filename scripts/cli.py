"""The ``rlpipe`` command line.

    rlpipe train PRESET [key=value ...] [--out DIR] [--resume DIR]
    rlpipe eval RUN_DIR [--episodes N] [--json] [--ecdf]
    rlpipe video RUN_DIR [--episodes N] [--random] [--out FILE]
    rlpipe plot RUN_DIR [RUN_DIR ...] [--out FILE]
    rlpipe presets
    rlpipe ablate td3 --envs A,B --seeds N --steps S [--workers W] [--out DIR]
    rlpipe bench {dqn,td3,sac,minitaur} [...]

Bad input ends with one line on stderr naming what is wrong and what is expected, and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
from pathlib import Path

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


def _parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="rlpipe", description="RL pipelines (SAC, TD3, DQN) on TorchRL.")
    sub = parser.add_subparsers(dest="command", required=True)

    train = sub.add_parser("train", help="train a preset (dqn, dqn-cartpole-v1, td3, sac, ...)")
    train.add_argument("preset", help="preset name; `rlpipe presets` lists them")
    train.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides, dotted for groups (collector.workers=2)")
    train.add_argument("--out", type=Path, help="run directory (default runs/<algo>-<env>-<time>)")
    train.add_argument("--resume", type=Path, metavar="RUN_DIR", help="continue the run in RUN_DIR from its last checkpoint")
    train.add_argument("--no-progress", action="store_true", help="no progress bar")
    train.add_argument("--keys", action="store_true", help="list the preset's keys with their values and meaning, then exit")

    ev = sub.add_parser("eval", help="evaluate a run's exported policy")
    ev.add_argument("run_dir", type=Path)
    ev.add_argument("--episodes", type=int, default=10)
    ev.add_argument("--seed", type=int, default=12345)
    ev.add_argument("--json", action="store_true", help="print the result as JSON")
    ev.add_argument("--ecdf", action="store_true", help="also plot the ECDF of episode returns to RUN_DIR/ecdf.png")

    video = sub.add_parser("video", help="an mp4 of a run's policy acting (or of a random policy)")
    video.add_argument("run_dir", type=Path)
    video.add_argument("--episodes", type=int, default=3)
    video.add_argument("--random", action="store_true", help="a random policy instead, for comparison")
    video.add_argument("--out", type=Path, help="mp4 path (default RUN_DIR/trained-agent.mp4 or random-agent.mp4)")
    video.add_argument("--seed", type=int, default=0)

    plot = sub.add_parser("plot", help="return curves of one or more runs in one PNG")
    plot.add_argument("run_dirs", type=Path, nargs="+")
    plot.add_argument("--out", type=Path, default=Path("returns.png"))

    sub.add_parser("presets", help="list the presets")

    from rlpipe.scripts import ablate, bench

    ablate.add_parser(sub)
    bench.add_parser(sub)
    return parser


def _positive(name: str, value: int) -> None:
    from rlpipe.pipelines.errors import InputError

    if value <= 0:
        raise InputError(f"{name}={value}: expected a positive integer")


def cmd_train(args) -> int:
    from rlpipe.pipelines import pipeline_class, resolve_preset
    from rlpipe.pipelines.config import apply_overrides, config_from_dict, field_docs, flat_keys
    from rlpipe.pipelines.errors import InputError
    from rlpipe.pipelines.rundir import RunDir
    from rlpipe.pipelines.supervision import WorkersLost

    algo, cfg = resolve_preset(args.preset)
    Pipeline = pipeline_class(algo)
    if args.resume is not None:
        if args.out is not None and args.out.resolve() != args.resume.resolve():
            raise InputError("--out and --resume name different directories; expected one run directory")
        run = RunDir.open(args.resume)
        saved_algo, saved = run.read_config()
        if saved_algo != algo:
            raise InputError(f"{args.resume} holds a {saved_algo} run; expected a {algo} run for preset {args.preset!r}")
        cfg = config_from_dict(Pipeline.Config, saved)
    cfg = apply_overrides(cfg, args.overrides)
    if args.keys:  # the values this command would train with, overrides included
        docs = field_docs(type(cfg))
        for key in flat_keys(type(cfg)):
            value = cfg
            for part in key.split("."):
                value = getattr(value, part)
            print(f"{key}={json.dumps(value)}\n    {docs.get(key, '')}")
        return 0
    pipeline = Pipeline(cfg)
    out = args.resume if args.resume is not None else args.out
    try:
        result = pipeline.train(out, resume=args.resume is not None, progress=not args.no_progress)
    except KeyboardInterrupt as exc:  # Ctrl-C, SIGTERM or SIGHUP: exit 128 + the signal's number
        run_dir = getattr(getattr(pipeline, "run_dir", None), "path", out)
        signame = getattr(exc, "signum", None)
        by = f" by {signal.Signals(signame).name}" if signame not in (None, signal.SIGINT) else ""
        print(f"rlpipe: interrupted{by}; continue with: rlpipe train {args.preset} --resume {run_dir}", file=sys.stderr)
        return getattr(exc, "exit_status", 130)
    except WorkersLost as exc:
        run_dir = getattr(getattr(pipeline, "run_dir", None), "path", out)
        print(f"rlpipe: error: {exc}; continue with: rlpipe train {args.preset} --resume {run_dir}", file=sys.stderr)
        return exc.exit_status
    s = result.summary
    print(f"AverageReturn = {s['final_average_return']:.2f}  AverageEpisodeLength = {s['final_average_episode_length']:.1f}")
    print(f"{s['iterations']} iterations, {s['frames']} env steps, {s['updates']} updates in {s['wall_time_s']:.0f} s "
          f"({s['env_steps_per_s'] or 0:.0f} env steps/s, {s['updates_per_s'] or 0:.0f} updates/s while training)")
    print(f"run directory: {result.run_dir}")
    return 0


def _run_config(run_dir: Path):
    from rlpipe.pipelines import pipeline_class
    from rlpipe.pipelines.config import config_from_dict
    from rlpipe.pipelines.rundir import RunDir

    run = RunDir.open(run_dir)
    algo, saved = run.read_config()
    return run, config_from_dict(pipeline_class(algo).Config, saved)


def cmd_eval(args) -> int:
    from tensordict.nn import TensorDictModule

    from rlpipe.envs import make_env
    from rlpipe.pipelines.evaluation import evaluate
    from rlpipe.pipelines.export import load_policy

    _positive("--episodes", args.episodes)
    run, cfg = _run_config(args.run_dir)
    module, _ = load_policy(run.policy_dir)
    env = make_env(cfg.env, seed=args.seed)
    policy = TensorDictModule(module, in_keys=["observation"], out_keys=["action"])
    result = evaluate(env, policy, args.episodes)
    if args.ecdf:
        from rlpipe.pipelines.analysis import plot_ecdf

        result["ecdf_png"] = str(plot_ecdf(result["returns"], run.path / "ecdf.png", title=f"{cfg.env}: {args.episodes} episodes"))
    if args.json:
        print(json.dumps({"AverageReturn": result["average_return"], "AverageEpisodeLength": result["average_episode_length"],
                          "returns": result["returns"], **({"ecdf_png": result["ecdf_png"]} if args.ecdf else {})}))
    else:
        print(f"AverageReturn = {result['average_return']:.2f}")
        print(f"AverageEpisodeLength = {result['average_episode_length']:.1f}")
        if args.ecdf:
            print(f"ECDF of returns: {result['ecdf_png']}")
    return 0


def cmd_video(args) -> int:
    from rlpipe.pipelines.export import load_policy
    from rlpipe.pipelines.video import record_video

    _positive("--episodes", args.episodes)
    run, cfg = _run_config(args.run_dir)
    policy = None if args.random else load_policy(run.policy_dir)[0]
    out = args.out or run.path / ("random-agent.mp4" if args.random else "trained-agent.mp4")
    path = record_video(cfg.env, policy, out, episodes=args.episodes, seed=args.seed)
    print(f"video: {path}")
    return 0


def cmd_plot(args) -> int:
    from rlpipe.pipelines.analysis import plot_return_curves
    from rlpipe.pipelines.rundir import RunDir

    for run_dir in args.run_dirs:
        RunDir.open(run_dir)
    print(f"plot: {plot_return_curves(list(args.run_dirs), args.out)}")
    return 0


def cmd_presets(args) -> int:
    from rlpipe.pipelines import presets, resolve_preset

    for name in presets():
        algo, cfg = resolve_preset(name)
        print(f"{name:22s} {algo:4s} {cfg.env}  ({cfg.num_iterations} iterations)")
    return 0


def main(argv: list[str] | None = None) -> int:
    from rlpipe.envs import EnvError
    from rlpipe.pipelines.errors import InputError

    parser = _parser()
    args, extra = parser.parse_known_args(argv)
    # key=value overrides may come after options too (`--resume RUN num_iterations=40000`).
    if extra and hasattr(args, "overrides") and all("=" in e and not e.startswith("-") for e in extra):
        args.overrides = [*args.overrides, *extra]
    elif extra:
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    commands = {"train": cmd_train, "eval": cmd_eval, "video": cmd_video, "plot": cmd_plot,
                "presets": cmd_presets}
    try:
        if args.command in commands:
            return commands[args.command](args)
        return args.func(args)
    except (InputError, EnvError) as exc:
        print(f"rlpipe: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
