"""``rlpipe bench td3``: the tutorial's TD3 on Pendulum-v1 against the tutorial's own code, in one run.

rlpipe runs the ``td3`` preset for ``--steps`` env steps (default 30,000: 10,000 start-up + 20,000)
per seed, in-process (``collector.sync=true``) and with collection in a second process overlapping
learning (``collector.sync=false``); the peer is the tutorial's plain-PyTorch TD3 (its ``TD3``
class and loop, reproduced below) for the same steps. Reported: updates per second after the
start-up phase (env steps included) and the final average return over 20 episodes, every policy
played from the same 20 start states (the tutorial's ``reset(seed=10_000 + i)``).
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

import numpy as np


def tutorial_td3(steps: int, seed: int, startup: int = 10_000, eval_episodes: int = 20) -> dict:
    """The tutorial's TD3 (seed 004) as written there: numpy replay, two critics, one loop step per env step."""
    import gymnasium as gym
    import torch
    import torch.nn.functional as F
    from torch import nn

    class Actor(nn.Module):
        def __init__(self, state_dim, hidden, min_action, max_action):
            super().__init__()
            self.l1, self.l3 = nn.Linear(state_dim, hidden), nn.Linear(hidden, len(min_action))
            self.center = torch.FloatTensor((max_action + min_action) / 2)
            self.radius = torch.FloatTensor((max_action - min_action) / 2)

        def forward(self, s):
            return self.center + self.radius * torch.tanh(self.l3(F.relu(self.l1(s))))

    class Critic(nn.Module):
        def __init__(self, state_dim, action_dim, hidden):
            super().__init__()
            self.l1, self.l3 = nn.Linear(state_dim + action_dim, hidden), nn.Linear(hidden, 1)

        def forward(self, s, a):
            return self.l3(F.relu(self.l1(torch.cat([s, a], 1))))

    env = gym.make("Pendulum-v1")
    torch.manual_seed(seed)
    np.random.seed(seed)
    lo, hi = env.action_space.low.astype(np.float64), env.action_space.high.astype(np.float64)
    sd, ad = env.observation_space.shape[0], len(lo)
    actor, c1, c2 = Actor(sd, 256, lo, hi), Critic(sd, ad, 256), Critic(sd, ad, 256)
    actor_t, c1_t, c2_t = (Actor(sd, 256, lo, hi), Critic(sd, ad, 256), Critic(sd, ad, 256))
    actor_t.load_state_dict(actor.state_dict()), c1_t.load_state_dict(c1.state_dict()), c2_t.load_state_dict(c2.state_dict())
    opt_a, opt_1, opt_2 = (torch.optim.Adam(m.parameters(), lr=3e-4) for m in (actor, c1, c2))
    cap = steps
    buf_s, buf_a, buf_n = np.zeros((cap, sd)), np.zeros((cap, ad)), np.zeros((cap, sd))
    buf_r, buf_d = np.zeros((cap, 1)), np.zeros((cap, 1))
    size = ptr = 0
    state, _ = env.reset(seed=seed)
    t_start = None
    updates_after = 0
    for t in range(1, steps + 1):
        if t <= startup:
            action = lo + (hi - lo) * np.random.rand(ad)
        else:
            with torch.no_grad():
                action = actor(torch.FloatTensor(state.reshape(1, -1))).numpy().flatten()
            action = (action + np.random.randn(ad) * 0.05 * (hi - lo)).clip(lo, hi)
        nxt, r, term, trunc, _ = env.step(action)
        buf_s[ptr], buf_a[ptr], buf_n[ptr], buf_r[ptr], buf_d[ptr] = state, action, nxt, r, term
        ptr, size = (ptr + 1) % cap, min(size + 1, cap)
        if t == startup + 1:
            t_start = time.perf_counter()
        if size >= 256:
            ind = np.random.choice(size, 256, replace=False)
            s, a, n = (torch.FloatTensor(x[ind]) for x in (buf_s, buf_a, buf_n))
            rew, done = torch.FloatTensor(buf_r[ind]), torch.FloatTensor(buf_d[ind])
            with torch.no_grad():
                noise = (torch.randn_like(a) * 0.2).clamp(-0.5, 0.5)
                na = (actor_t(n) - actor_t.center) / actor_t.radius
                na = (na + noise).clamp(-1, 1) * actor_t.radius + actor_t.center
                tq = rew + 0.99 * torch.min(c1_t(n, na), c2_t(n, na)) * (1 - done)
            for crit, opt in ((c1, opt_1), (c2, opt_2)):
                loss = F.mse_loss(crit(s, a), tq)
                opt.zero_grad()
                loss.backward()
                opt.step()
            if t % 2 == 0:
                loss = -c1(s, actor(s)).mean()
                opt_a.zero_grad()
                loss.backward()
                opt_a.step()
                for net, tgt in ((c1, c1_t), (c2, c2_t), (actor, actor_t)):
                    for p, tp in zip(net.parameters(), tgt.parameters()):
                        tp.data.copy_(0.005 * p.data + 0.995 * tp.data)
            if t > startup:
                updates_after += 1
        state = nxt
        if term or trunc:
            state, _ = env.reset()
    elapsed = time.perf_counter() - t_start
    final = average_return_on_fixed_starts(lambda obs: actor(torch.FloatTensor(obs.reshape(1, -1))), eval_episodes)
    return {"updates_per_s": updates_after / elapsed, "final_average_return": final}


def average_return_on_fixed_starts(act, episodes: int = 20) -> float:
    """Mean return of ``act`` (numpy observation -> action tensor) on Pendulum-v1 episodes that start
    from ``reset(seed=10_000 + i)``: the same starts for every implementation and seed, so that the
    final returns compare policies, not the luck of the start states."""
    import gymnasium as gym
    import torch

    env = gym.make("Pendulum-v1")
    returns = []
    for i in range(episodes):
        s, _ = env.reset(seed=10_000 + i)
        total, done = 0.0, False
        while not done:
            with torch.no_grad():
                a = act(s).numpy().reshape(-1)
            s, r, term, trunc, _ = env.step(a)
            total += r
            done = term or trunc
        returns.append(total)
    env.close()
    return float(np.mean(returns))


def rlpipe_policy_return(policy, episodes: int = 20) -> float:
    """``average_return_on_fixed_starts`` of a trained rlpipe policy (its deterministic action)."""
    import torch
    from tensordict import TensorDict
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    def act(obs):
        td = TensorDict(observation=torch.as_tensor(obs, dtype=torch.float32)[None], batch_size=[1])
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            return policy(td)["action"]

    return average_return_on_fixed_starts(act, episodes)


def _after_startup_updates_per_s(metrics: list[dict]) -> float:
    """Mean updates/s of the log rows after the first (which spans the random start-up)."""
    rows = [float(r["updates_per_s"]) for r in metrics if r.get("updates_per_s") not in ("", None)]
    rows = rows[1:] or rows
    return statistics.mean(rows)


def bench_td3(args, out: Path) -> dict:
    from rlpipe.scripts.bench.runs import train_seeds

    steps = args.steps or 30_000
    startup = 10_000 if steps > 20_000 else steps // 3
    budget = [f"initial_collect_steps={startup}", f"num_iterations={steps - startup}", "eval_interval=0",
              "num_eval_episodes=20", "log_interval=1000", f"checkpoint_interval={steps}", *args.overrides]
    lines, figures = [], {}
    peer = [tutorial_td3(steps, seed, startup) for seed in range(args.seeds)]
    for s, p in enumerate(peer):
        print(f"  tutorial seed {s}: {p}", file=sys.stderr)
    figures["tutorial"] = peer
    peer_speed = statistics.mean(p["updates_per_s"] for p in peer)
    peer_return = statistics.mean(p["final_average_return"] for p in peer)
    lines.append(f"| tutorial's plain PyTorch (peer) | {peer_speed:.0f} | 1.00 | {peer_return:.1f} | "
                 f"{', '.join(format(p['final_average_return'], '.0f') for p in peer)} |")
    for label, extra in (("rlpipe, in-process collection", ["collector.sync=true"]),
                         ("rlpipe, the td3 preset (env stepped in a second process)", ["collector.sync=false"])):
        results = train_seeds("td3", budget + extra, args.seeds, out / extra[0].replace("=", "-"))
        speeds = [_after_startup_updates_per_s(r.metrics) for r in results]
        finals = [rlpipe_policy_return(r.policy) for r in results]
        figures[label] = {"updates_per_s": speeds, "final_average_return": finals,
                          "own_final_evaluation": [r.summary["final_average_return"] for r in results]}
        lines.append(f"| {label} | {statistics.mean(speeds):.0f} | {statistics.mean(speeds) / peer_speed:.2f} | "
                     f"{statistics.mean(finals):.1f} | {', '.join(f'{f:.0f}' for f in finals)} |")
    table = "\n".join([
        f"TD3 benchmark: Pendulum-v1, tutorial settings, {steps} env steps ({startup} start-up), {args.seeds} seeds",
        "",
        "| implementation | updates/s after start-up (env steps included) | ratio to tutorial | final AverageReturn (20 episodes, same starts for all), mean | per seed |",
        "|---|---|---|---|---|",
        *lines,
    ])
    return {**figures, "table": table}
