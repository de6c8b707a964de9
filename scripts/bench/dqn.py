"""``rlpipe bench dqn``: the ``dqn`` preset against a plain-PyTorch DQN and TF-Agents' DQN tutorial, in one run."""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

from rlpipe.scripts.bench.runs import first_reaching, train_seeds


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
    if preset == "dqn":  # the TF-Agents DQN tutorial itself, in its own venv (scripts/bench/peers/tfagents.py)
        from rlpipe.scripts.bench.peers import tfagents

        tf_agents = tfagents.dqn_cartpole_iterations_per_s((1000, 4000))
        print(f"  TF-Agents DQN tutorial: {tf_agents['iterations_per_s']:.1f} it/s", file=sys.stderr)
    results = train_seeds(preset, args.overrides, args.seeds, out)
    rows, speeds, reached = [], [], []
    for seed, r in enumerate(results):
        s = r.summary
        first_it = first_reaching(r.evaluations, threshold)
        first_frames = first_reaching(r.evaluations, threshold, "frames")
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
