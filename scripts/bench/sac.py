"""``rlpipe bench sac``: SAC on Minitaur against TF-Agents' actor-learner tutorial, both run here.

An iteration is the tutorial's: one env step and one update (batch 256, (256, 256) networks).
Both sides are timed over two lengths after the 10,000 random steps (``--steps N``: N and N + 2000
iterations, each run a fresh process), so start-up cancels: iterations/s = (n2 - n1) / (t2 - t1). TF-Agents runs its own
tutorial (``scripts/bench/peers/tfagents.py``: TF-Agents 0.19, TensorFlow 2.15, Reverb 0.14 in a venv of
their own, made on first use), rlpipe its ``sac`` preset (the env in a collector process beside the
learner). Also reported: the raw env's speed, and collect-only env steps/s of TorchRL's collectors
(random policy, no learning) with 1 and 2 workers.
"""

from __future__ import annotations

import functools
import sys
import time
from pathlib import Path


def collect_only_steps_per_s(workers: int, sync: bool, frames: int) -> float:
    """Env steps/s of TorchRL collectors stepping our Minitaur with a random policy (no learning)."""
    from torchrl.collectors import Collector, MultiAsyncCollector, MultiSyncCollector
    from torchrl.envs.utils import RandomPolicy

    from rlpipe.envs import make_env

    env_fn = functools.partial(make_env, "MinitaurBulletEnv-v0")
    env = env_fn()
    policy = RandomPolicy(env.action_spec)
    if workers == 1 and sync:
        collector = Collector(env, policy, frames_per_batch=50, total_frames=-1)
    else:
        cls = MultiSyncCollector if sync else MultiAsyncCollector
        collector = cls([env_fn] * workers, policy, frames_per_batch=50, total_frames=-1)
    n, t0 = 0, None
    try:
        for batch in collector:
            if t0 is None:  # first batch includes process start-up
                t0 = time.perf_counter()
                continue
            n += batch.numel()
            if n >= frames:
                break
    finally:
        collector.shutdown()
    return n / (time.perf_counter() - t0)


def rlpipe_iterations_per_s(iterations: tuple[int, int], out: Path, overrides: list[str]) -> dict:
    """The ``sac`` preset's iterations/s from two runs (fresh processes) of ``iterations`` after its
    10k random steps."""
    from rlpipe.scripts.bench.cleanrl import timed_train

    runs = [timed_train("sac", [f"num_iterations={n}", "eval_interval=0", "num_eval_episodes=1",
                                f"log_interval={max(100, n // 5)}", f"checkpoint_interval={n}",
                                f"policy_save_interval={n}", *overrides], out / f"sac-{n}")
            for n in iterations]
    return {"iterations_per_s": (iterations[1] - iterations[0]) / (runs[1]["wall_s"] - runs[0]["wall_s"]), "runs": runs}


def bench_sac(args, out: Path) -> dict:
    from rlpipe.scripts.bench.minitaur import bench_minitaur_raw
    from rlpipe.scripts.bench.peers import tfagents

    n = args.steps or 500
    iterations = (n, n + 2000)
    raw = bench_minitaur_raw(2000, seed=0)["steps_per_s"]
    collect = {workers: collect_only_steps_per_s(workers, workers == 1, 2000) for workers in (1, 2)}
    ours = rlpipe_iterations_per_s(iterations, out, args.overrides)
    print(f"  rlpipe sac preset: {ours['iterations_per_s']:.1f} it/s", file=sys.stderr)
    peer = tfagents.sac_minitaur_iterations_per_s(iterations)
    print(f"  TF-Agents tutorial: {peer['iterations_per_s']:.1f} it/s", file=sys.stderr)
    ratio = ours["iterations_per_s"] / peer["iterations_per_s"]
    table = "\n".join([
        f"SAC on Minitaur, the tutorial's settings, timed over {iterations[0]} and {iterations[1]} iterations after "
        f"the 10,000 random steps, no evaluations. Raw env: {raw:.0f} steps/s (random actions, resets included).",
        "",
        "| implementation | iterations/s (1 env step + 1 update) | ratio to TF-Agents |",
        "|---|---|---|",
        f"| TF-Agents 0.19 actor-learner tutorial (its own code, same run) | {peer['iterations_per_s']:.1f} | 1.00 |",
        f"| rlpipe `sac` preset (collector process beside the learner) | {ours['iterations_per_s']:.1f} | **{ratio:.2f}** |",
        "",
        f"Collect-only (random policy, no learning): 1 worker in-process {collect[1]:.0f} env steps/s "
        f"({collect[1] / raw:.2f} of raw), 2 workers {collect[2]:.0f} ({collect[2] / raw:.2f} of raw).",
    ])
    return {"raw_env_steps_per_s": raw, "collect_only_steps_per_s": collect, "rlpipe": ours, "tfagents": peer,
            "ratio": ratio, "table": table}
