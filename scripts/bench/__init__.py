"""``rlpipe bench``: speed and learning benchmarks (not tests), each against a named peer in one run.

    rlpipe bench dqn [--seeds 3] [--preset dqn] [key=value ...]
    rlpipe bench td3 [--seeds 3] [--steps 30000]
    rlpipe bench sac [--iterations 2000]
    rlpipe bench minitaur [--steps 3000]
    rlpipe bench floor [key=value ...]
    rlpipe bench cleanrl [--algos sac td3 dqn] [--envs Pendulum-v1 ...] [--lengths N1 N2] [--seed 0]
    rlpipe bench profile PRESET [key=value ...] [--steps N] [--duration 20] [--rate 100]
    rlpipe bench collect [--envs CartPole-v1 ...] [--envs-per-worker 1 8 32] [--frames 3000]
    rlpipe bench ray [--envs MinitaurBulletEnv-v0] [--workers 1 2 4] [--frames 1000] [--steps 500 | --lengths N1 N2]
    rlpipe bench threads [--preset td3] [--steps N] [--seeds 3] [key=value ...]
    rlpipe bench replay-memory [--steps 1000000]
    rlpipe bench time-to-return [--tasks pendulum-sac ...] [--seeds 5] [--peers cleanrl sb3 sbx tfagents torchrl | none]
                                [--threads SIDE=N ...] [--target-return R] [--cap-scale X] [--cap SIDE=STEPS ...]
                                [--side-seeds SIDE=N ...] [--seed FIRST] [--preset P] [--also-preset P] [--no-crossq]
                                [--torchrl-sota DIR] [key=value ...]
    rlpipe bench anytime --envs ID ... [--algos sac] [--budget 10m] [--marks 10] [--peers sbx sb3 | none] [--seeds 3]
                         [--seed FIRST] [--eval-episodes 10] [--threads SIDE=N ...] [--preset P] [key=value ...]

``profile`` is not a comparison: it runs ``rlpipe train PRESET`` under py-spy once learning has
started and prints the share of each part (replay sample, update forward/backward, optimiser,
target update, weight push, waiting, env step, ...) per process (``scripts/bench/profile.py``).
``collect``: collect-only env steps/s of the collectors rlpipe builds (each env's preset, its
collection policy, ``collector.envs_per_worker`` envs as one batch), in-process and in one
collector process, against the raw gymnasium env (issue 9's target: at least half of it).
``ray``: Ray actors against local collector processes, collect-only and training the ``sac``
preset, with the arithmetic of how many actors the learner can use (issue 10).
``threads``: a run's speed on each learner thread count, alone and beside a busy process of its own, with the
count ``num_threads=-1`` chooses marked (``scripts/bench/threads.py``).
``replay-memory``: the resident memory of a full image replay buffer (one million Atari transitions by default),
measured, beside the floor and the stacks stored as they come (``scripts/bench/replay_memory.py``).
``time-to-return``: seconds from launching a command to a trained agent (a target return, judged
the same way for every side), rlpipe's presets against CleanRL, SB3, SBX and TorchRL's own recipes, interleaved over seeds
(``scripts/bench/time_to_return.py``; issue 21).
``anytime``: the greedy return each side has at fixed wall-clock times within ``--budget``, rlpipe's default run
(its exported policy and its last) against SBX/SB3 with RL-Zoo's settings, with 95% bands across seeds
(``scripts/bench/anytime.py``).

Each prints a Markdown table (paste it into BENCHMARKS.md with the command) and, with ``--json``,
writes the raw figures. These machines are shared and noisy: compare the ratios within one run.

One module per target here (``dqn.py`` ... ``ray.py``, each with its ``bench_TARGET(args, out)``),
``runs.py`` for the rlpipe runs they share, ``peers/`` for the peers run in venvs of their own;
``dqn_tries.py``, ``ray_replay.py``, ``collect_tries.py`` and ``dqn_one_env.py`` are measurements run with
``python -m`` (as is ``scripts/fixed_cost.py``, a run's launch-to-first-step and last-step-to-exit per part,
beside the CLI it wraps). A preset's measured time to its target, which ``rlpipe presets`` shows, is in its own
file (``info.measured``), copied there from a ``rlpipe bench time-to-return`` run.
"""

from __future__ import annotations

import importlib
import json
import signal
import sys
import tempfile
from pathlib import Path


def add_parser(sub) -> None:
    bench = sub.add_parser("bench", help="benchmarks: speed and learning against named peers")
    bench.add_argument("target", choices=["dqn", "td3", "sac", "minitaur", "floor", "cleanrl", "gpu", "profile",
                                          "collect", "ray", "time-to-return", "threads", "replay-memory",
                                          "anytime"])
    bench.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides for the rlpipe runs (profile: PRESET first)")
    bench.add_argument("--seeds", type=int, help="seeds per side (default 3; time-to-return: 5)")
    bench.add_argument("--preset", help="preset to run (default: the target's tutorial preset)")
    bench.add_argument("--also-preset", metavar="P", help="time-to-return: a second rlpipe side, preset, that plays P "
                       "(e.g. the file rlpipe tune wrote) beside rlpipe's own, seed by seed against the same peers")
    bench.add_argument("--steps", type=int, help="env steps (td3, minitaur) or iterations (sac, profile: default 100000; "
                       "ray: the shorter timed run)")
    bench.add_argument("--duration", type=int, default=20, help="profile: seconds sampled after learning starts")
    bench.add_argument("--rate", type=int, default=100, help="profile: py-spy samples per second")
    bench.add_argument("--out", type=Path, help="keep the runs here (default: a temporary folder)")
    bench.add_argument("--json", type=Path, help="also write the figures as JSON here")
    bench.add_argument("--peer-iterations", type=int, default=3000, help="iterations timed for the plain-PyTorch peer")
    bench.add_argument("--algos", nargs="+", choices=["sac", "td3", "dqn"], help="cleanrl: algorithms to compare (default: "
                       "all); time-to-return with --envs: the one algorithm (default: SAC for a Box action space, DQN for "
                       "a Discrete one)")
    bench.add_argument("--envs", nargs="+", help="cleanrl: env ids (default: Pendulum-v1 and HalfCheetah-v5; CartPole-v1 for "
                       "dqn); collect: default CartPole-v1 Pendulum-v1 MinitaurBulletEnv-v0; ray: "
                       "the one env (default MinitaurBulletEnv-v0); time-to-return: your own envs, each a task (an id, "
                       "my_package.envs:MyArm or my_package:MyArm-v0; env_kwargs.KEY=VALUE for its constructor), rlpipe's "
                       "sized default (or --preset) against SB3/SBX, with --target-return")
    bench.add_argument("--envs-per-worker", nargs="+", type=int, help="collect: collector.envs_per_worker values (default: 1)")
    bench.add_argument("--workers", nargs="+", type=int, help="ray: collector workers (default: 1 2 4)")
    bench.add_argument("--frames", type=int, help="collect, ray: collect-only frames timed per measurement "
                       "(default 3000; ray 1000)")
    bench.add_argument("--lengths", nargs=2, type=int, metavar=("N1", "N2"),
                       help="cleanrl: env steps after learning_starts of the two timed runs; ray: iterations of the "
                       "two timed training runs (default: --steps and 2000 more)")
    bench.add_argument("--parts", nargs="+", choices=["updates", "training"], default=["updates", "training"],
                       help="gpu: which tables to measure (default: both)")
    bench.add_argument("--modes", nargs="+", choices=["step", "blocks", "cpu-copy", "process"],
                       help="gpu: the training table's loop modes (default: all; scripts/bench/gpu.py TRAIN_MODES)")
    bench.add_argument("--seed", type=int, default=0, help="cleanrl, gpu: seed of both sides; time-to-return: the first "
                       "seed (seeds SEED to SEED+--seeds-1; default 0; the sized presets were tuned on seeds from 0)")
    bench.add_argument("--tasks", nargs="+", help="time-to-return: tasks to run (default: all; see "
                       "scripts/bench/time_to_return.py TASKS)")
    bench.add_argument("--peers", nargs="+", help="time-to-return: peers beside rlpipe (cleanrl sb3 sbx tfagents torchrl; "
                       "default: cleanrl sb3 sbx, and torchrl with --torchrl-sota; none: rlpipe only)")
    bench.add_argument("--torchrl-sota", type=Path, metavar="DIR", help="time-to-return: a checkout of pytorch/rl at "
                       "the installed torchrl's tag, whose sota-implementations scripts and configs the torchrl peer runs")
    bench.add_argument("--threads", nargs="+", metavar="SIDE=N", help="time-to-return: a side's thread count "
                       "(default: rlpipe the preset's, cleanrl and sb3 1, sbx JAX's)")
    bench.add_argument("--target-return", type=float, help="time-to-return: one target return for every task chosen "
                       "instead of the task's (a quick check); with --envs, the target on your envs")
    bench.add_argument("--cap-scale", type=float, help="time-to-return: scale every task's env-step cap")
    bench.add_argument("--cap", nargs="+", metavar="SIDE=STEPS", help="time-to-return: one side's env-step cap, "
                       "instead of the task's (e.g. tfagents=110000: the Minitaur tutorial's whole run, its 10,000 random "
                       "steps and 100,000 iterations)")
    bench.add_argument("--side-seeds", nargs="+", metavar="SIDE=N", help="time-to-return: one side's own count of "
                       "seeds (its first N of --seeds), for a peer too slow to run every seed in one sitting (e.g. "
                       "tfagents=1: the Minitaur tutorial's run, timed once per page revision as issue 21 allows)")
    bench.add_argument("--no-crossq", action="store_true", help="time-to-return: leave out the CrossQ side "
                       "(played by default on every task that has a CrossQ preset)")
    bench.add_argument("--budget", default="10m", help="anytime: each run's wall-clock time (600, 90s, 10m, 2h; "
                       "default 10m)")
    bench.add_argument("--marks", type=int, default=10, help="anytime: evaluation times, evenly spaced over --budget "
                       "(default 10)")
    bench.add_argument("--eval-episodes", type=int, default=10, help="anytime: greedy episodes per evaluation (default 10)")
    bench.set_defaults(func=run)


def run(args) -> int:
    from rlpipe.pipelines.errors import InputError

    if args.seeds is None:
        args.seeds = 5 if args.target == "time-to-return" else 3
    if args.target == "anytime":  # refused before anything is built or written
        from rlpipe.scripts.bench.anytime import check_args as check_anytime_args

        check_anytime_args(args)
    if args.seeds <= 0:
        raise InputError(f"--seeds={args.seeds}: expected a positive integer")
    if args.target == "time-to-return":  # refused before anything is built or written
        from rlpipe.scripts.bench.time_to_return import check_args as check_ttr_args

        check_ttr_args(args)
    if args.target == "profile":  # its preset and overrides, refused before any folder is made
        from rlpipe.scripts.bench.profile import check_args

        check_args(args)
    if args.target in ("collect", "ray"):  # refused before anything is written
        from rlpipe.scripts.bench.collect import check_args as check_collect_args

        check_collect_args(args)
    out = args.out or Path(tempfile.mkdtemp(prefix=f"rlpipe-bench-{args.target}-"))
    if args.out is not None and args.out.exists() and any(args.out.iterdir()):
        raise InputError(f"--out {args.out}: not empty; expected a new or empty directory for the benchmark runs")
    # each target is scripts/bench/TARGET.py's bench_TARGET, imported when asked for
    name = args.target.replace("-", "_")
    figures = getattr(importlib.import_module(f"{__name__}.{name}"), f"bench_{name}")(args, out)
    print(figures.pop("table"))
    if args.json:
        args.json.write_text(json.dumps(figures, indent=2) + "\n")
    if figures.get("interrupted"):  # the finished runs are written; the exit says the command did not finish
        signum = getattr(signal, figures["interrupted"]["signal"], signal.SIGINT)
        print(f"rlpipe: interrupted by {signal.Signals(signum).name}; the runs finished before it are above"
              + (f" and in {args.json}" if args.json else ""), file=sys.stderr)
        return 128 + int(signum)
    return 0

