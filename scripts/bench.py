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

``profile`` is not a comparison: it runs ``rlpipe train PRESET`` under py-spy once learning has
started and prints the share of each part (replay sample, update forward/backward, optimiser,
target update, weight push, waiting, env step, ...) per process (``scripts/bench_profile.py``).
``collect``: collect-only env steps/s of the collectors rlpipe builds (each env's preset, its
collection policy, ``collector.envs_per_worker`` envs as one batch), in-process and in one
collector process, against the raw gymnasium env (issue 9's target: at least half of it).
``ray``: Ray actors against local collector processes, collect-only and training the ``sac``
preset, with the arithmetic of how many actors the learner can use (issue 10).

Each prints a Markdown table (paste it into BENCHMARKS.md with the command) and, with ``--json``,
writes the raw figures. These machines are shared and noisy: compare the ratios within one run.
"""

from __future__ import annotations

import importlib
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path


def add_parser(sub) -> None:
    bench = sub.add_parser("bench", help="benchmarks: speed and learning against named peers")
    bench.add_argument("target", choices=["dqn", "td3", "sac", "minitaur", "floor", "cleanrl", "gpu", "profile",
                                          "collect", "ray"])
    bench.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides for the rlpipe runs (profile: PRESET first)")
    bench.add_argument("--seeds", type=int, default=3)
    bench.add_argument("--preset", help="preset to run (default: the target's tutorial preset)")
    bench.add_argument("--steps", type=int, help="env steps (td3, minitaur) or iterations (sac, profile: default 100000; "
                       "ray: the shorter timed run)")
    bench.add_argument("--duration", type=int, default=20, help="profile: seconds sampled after learning starts")
    bench.add_argument("--rate", type=int, default=100, help="profile: py-spy samples per second")
    bench.add_argument("--out", type=Path, help="keep the runs here (default: a temporary folder)")
    bench.add_argument("--json", type=Path, help="also write the figures as JSON here")
    bench.add_argument("--peer-iterations", type=int, default=3000, help="iterations timed for the plain-PyTorch peer")
    bench.add_argument("--algos", nargs="+", choices=["sac", "td3", "dqn"], help="cleanrl: algorithms to compare (default: all)")
    bench.add_argument("--envs", nargs="+", help="cleanrl: env ids (default: Pendulum-v1 and HalfCheetah-v5; CartPole-v1 for "
                       "dqn); collect: default CartPole-v1 Pendulum-v1 HalfCheetah-v5 MinitaurBulletEnv-v0; ray: "
                       "the one env (default MinitaurBulletEnv-v0)")
    bench.add_argument("--envs-per-worker", nargs="+", type=int, help="collect: collector.envs_per_worker values (default: 1 8 32)")
    bench.add_argument("--workers", nargs="+", type=int, help="ray: collector workers (default: 1 2 4)")
    bench.add_argument("--frames", type=int, help="collect, ray: collect-only frames timed per measurement "
                       "(default 3000; ray 1000)")
    bench.add_argument("--lengths", nargs=2, type=int, metavar=("N1", "N2"),
                       help="cleanrl: env steps after learning_starts of the two timed runs; ray: iterations of the "
                       "two timed training runs (default: --steps and 2000 more)")
    bench.add_argument("--parts", nargs="+", choices=["updates", "training"], default=["updates", "training"],
                       help="gpu: which tables to measure (default: both)")
    bench.add_argument("--seed", type=int, default=0, help="cleanrl: seed of both sides")
    bench.set_defaults(func=run)


def run(args) -> int:
    from rlpipe.pipelines.errors import InputError

    if args.seeds <= 0:
        raise InputError(f"--seeds={args.seeds}: expected a positive integer")
    if args.target == "profile":  # its preset and overrides, refused before any folder is made
        from rlpipe.scripts.bench_profile import check_args

        check_args(args)
    if args.target in ("collect", "ray"):  # refused before anything is written
        from rlpipe.scripts.bench_collect import check_args as check_collect_args

        check_collect_args(args)
    out = args.out or Path(tempfile.mkdtemp(prefix=f"rlpipe-bench-{args.target}-"))
    if args.out is not None and args.out.exists() and any(args.out.iterdir()):
        raise InputError(f"--out {args.out}: not empty; expected a new or empty directory for the benchmark runs")
    figures = {"dqn": bench_dqn, "td3": bench_td3, "minitaur": bench_minitaur}.get(args.target)
    if figures is None:  # each other target is scripts/bench_TARGET.py's bench_TARGET, imported when asked for
        figures = getattr(importlib.import_module(f"rlpipe.scripts.bench_{args.target}"), f"bench_{args.target}")
    figures = figures(args, out)
    print(figures.pop("table"))
    if args.json:
        args.json.write_text(json.dumps(figures, indent=2) + "\n")
    return 0


def _train_seeds(preset: str, overrides: list[str], seeds: int, out: Path) -> list[dict]:
    from rlpipe.pipelines import pipeline_class, resolve_preset
    from rlpipe.pipelines.config import apply_overrides

    results = []
    for seed in range(seeds):
        algo, cfg = resolve_preset(preset)
        cfg = apply_overrides(cfg, [*overrides, f"seed={seed}"])
        result = pipeline_class(algo)(cfg).train(out / f"{preset}-seed{seed}", progress=False)
        results.append(result)
        print(f"  seed {seed}: {json.dumps(result.summary)}", file=sys.stderr)
    return results


def _first_reaching(evaluations: list[dict], threshold: float, key: str = "step") -> int | None:
    for e in evaluations:
        if e["average_return"] >= threshold:
            return e[key]
    return None


# --- DQN ------------------------------------------------------------------------------------------


def plain_pytorch_dqn_iterations_per_s(iterations: int, seed: int = 0) -> float:
    """The peer: a lean plain-PyTorch DQN (gymnasium env, tensor ring buffer, 1 step + 1 update).

    Same network, batch, optimiser and loss as the ``dqn`` preset; no TorchRL. It is what the
    tutorial's loop costs without any framework, the floor rlpipe's overheads are measured against.
    """
    import gymnasium
    import numpy as np
    import torch
    from torch import nn

    torch.manual_seed(seed)
    env = gymnasium.make("CartPole-v0")
    q = nn.Sequential(nn.Linear(4, 100), nn.ReLU(), nn.Linear(100, 2))
    opt = torch.optim.Adam(q.parameters(), lr=1e-3)
    cap = 100_000
    obs_buf = torch.zeros(cap, 4)
    next_buf = torch.zeros(cap, 4)
    act_buf = torch.zeros(cap, dtype=torch.long)
    rew_buf = torch.zeros(cap)
    done_buf = torch.zeros(cap)
    rng = np.random.default_rng(seed)
    obs, _ = env.reset(seed=seed)
    n = 0

    def step(explore: bool) -> None:
        nonlocal obs, n
        if explore or rng.random() < 0.1:
            a = int(env.action_space.sample())
        else:
            with torch.no_grad():
                a = int(q(torch.as_tensor(obs, dtype=torch.float32)).argmax())
        nxt, r, term, trunc, _ = env.step(a)
        i = n % cap
        obs_buf[i] = torch.as_tensor(obs)
        next_buf[i] = torch.as_tensor(nxt)
        act_buf[i], rew_buf[i], done_buf[i] = a, r, float(term)
        n += 1
        obs = env.reset()[0] if term or trunc else nxt

    for _ in range(1000):
        step(True)
    t0 = time.perf_counter()
    for _ in range(iterations):
        step(False)
        idx = torch.randint(0, min(n, cap), (64,))
        with torch.no_grad():
            target = rew_buf[idx] + (1 - done_buf[idx]) * q(next_buf[idx]).max(-1).values
        pred = q(obs_buf[idx]).gather(-1, act_buf[idx, None]).squeeze(-1)
        loss = ((pred - target) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    return iterations / (time.perf_counter() - t0)


def plain_dqn_best_threads(iterations: int, seed: int = 0) -> tuple[float, dict[int, float]]:
    """The plain loop on one torch thread and on torch's default count: ``(best rate, {threads: rate})``.

    Each side of a comparison is timed on its best thread setting. For this loop's tiny matmuls
    one thread is usually best: on torch's default two threads on this shared 2-core machine under
    load (~12) it ran at 23 it/s against 237 on one, its OpenMP threads waiting for each other.
    """
    import torch

    before = torch.get_num_threads()
    rates = {}
    try:
        for threads in sorted({1, before}):
            torch.set_num_threads(threads)
            rates[threads] = plain_pytorch_dqn_iterations_per_s(iterations, seed=seed)
    finally:
        torch.set_num_threads(before)
    return max(rates.values()), rates


def bench_dqn(args, out: Path) -> dict:
    preset = args.preset or "dqn"
    threshold = 195.0 if preset == "dqn" else 475.0
    peer, peer_rates = plain_dqn_best_threads(args.peer_iterations)
    tf_agents = None
    if preset == "dqn":  # the TF-Agents DQN tutorial itself, in its own venv (scripts/peers/tfagents.py)
        from rlpipe.scripts.peers import tfagents

        tf_agents = tfagents.dqn_cartpole_iterations_per_s((1000, 4000))
        print(f"  TF-Agents DQN tutorial: {tf_agents['iterations_per_s']:.1f} it/s", file=sys.stderr)
    results = _train_seeds(preset, args.overrides, args.seeds, out)
    rows, speeds, reached = [], [], []
    for seed, r in enumerate(results):
        s = r.summary
        first_it = _first_reaching(r.evaluations, threshold)
        first_frames = _first_reaching(r.evaluations, threshold, "frames")
        speeds.append(s["updates_per_s"])
        reached.append(first_it)
        rows.append(f"| {seed} | {s['updates_per_s']:.0f} | {s['env_steps_per_s']:.0f} | {first_it} | {first_frames} | "
                    f"{s['final_average_return']:.1f} | {s['train_time_s']:.0f} | {s['wall_time_s']:.0f} |")
    mean_speed = statistics.mean(speeds)
    table = "\n".join([
        f"DQN benchmark: preset `{preset}` {' '.join(args.overrides)}, {args.seeds} seeds, threshold {threshold:g}",
        "",
        "| seed | updates/s (train, evals excluded) | env steps/s | first iteration with AverageReturn >= threshold | env steps then | final AverageReturn | train s | wall s |",
        "|---|---|---|---|---|---|---|---|",
        *rows,
        "",
        f"Mean training speed: {mean_speed:.0f} iterations/s. Peer in the same run, plain PyTorch DQN "
        f"(1 step + 1 update, no framework), its best thread setting: {peer:.0f} iterations/s "
        f"({', '.join(f'{rate:.0f} on {t} thread(s)' for t, rate in peer_rates.items())}); "
        f"ratio rlpipe/peer = {mean_speed / peer:.2f}.",
        f"Reached {threshold:g} on {sum(x is not None for x in reached)}/{len(reached)} seeds.",
        *([] if tf_agents is None else [
            f"TF-Agents' DQN tutorial (its own code, TF-Agents 0.19, same run, timed over 1000 and 4000 iterations): "
            f"{tf_agents['iterations_per_s']:.1f} iterations/s; ratio rlpipe/TF-Agents = "
            f"**{mean_speed / tf_agents['iterations_per_s']:.1f}**."]),
    ])
    return {"preset": preset, "peer_iterations_per_s": peer, "peer_by_threads": peer_rates, "tfagents": tf_agents, "iterations_per_s": speeds,
            "first_iteration_reaching": reached, "summaries": [r.summary for r in results], "table": table}


def bench_td3(args, out: Path) -> dict:
    from rlpipe.scripts.bench_td3 import bench_td3 as run_td3

    return run_td3(args, out, _train_seeds)









def bench_minitaur(args, out: Path) -> dict:
    from rlpipe.scripts.bench_minitaur import bench_minitaur_raw

    steps = args.steps or 3000
    ours = bench_minitaur_raw(steps, seed=0)
    table = "\n".join([
        f"Minitaur raw env speed ({steps} random steps, resets included)",
        "",
        "| env | steps/s |",
        "|---|---|",
        f"| rlpipe/MinitaurBullet-v0 | {ours['steps_per_s']:.0f} |",
    ])
    return {"ours": ours, "table": table}
