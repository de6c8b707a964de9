"""Raw stepping speed of rlpipe's Minitaur environment (no wrappers, no learner).

Usage::

    python -m rlpipe.scripts.bench.minitaur --steps 2000 --seed 0

Uniform random actions; the episode is reset (a hard reset, the default) on termination
or after 1000 steps, like ``rlpipe/MinitaurBullet-v0``'s time limit.  The clock covers the
first reset, every step and every later reset; constructing the env is not timed.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np


def bench_minitaur_raw(steps: int, seed: int = 0, max_episode_steps: int = 1000, **env_kwargs) -> dict:
    """Steps per second of ``MinitaurBulletEnv`` under random actions, resets included.

    Returns ``{"steps_per_s", "steps", "resets", "seconds"}``; ``resets`` counts the first
    one too.  ``env_kwargs`` go to the env's constructor.
    """
    from rlpipe.envs.minitaur import MinitaurBulletEnv

    rng = np.random.default_rng(seed)
    env = MinitaurBulletEnv(**env_kwargs)
    try:
        t0 = time.perf_counter()
        env.reset(seed=seed)
        resets, ep_len = 1, 0
        for _ in range(steps):
            _, _, terminated, _, _ = env.step(rng.uniform(-1.0, 1.0, 8))
            ep_len += 1
            if terminated or ep_len >= max_episode_steps:
                env.reset()
                resets += 1
                ep_len = 0
        elapsed = time.perf_counter() - t0
    finally:
        env.close()
    return {"steps_per_s": steps / elapsed, "steps": steps, "resets": resets, "seconds": elapsed}


def bench_minitaur(args, out) -> dict:
    """``rlpipe bench minitaur``: the raw env's speed over ``--steps`` random steps (default 3000)."""
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


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    print(json.dumps(bench_minitaur_raw(args.steps, args.seed)))


if __name__ == "__main__":
    main()
