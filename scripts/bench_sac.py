"""``rlpipe bench sac``: SAC on Minitaur, iterations per second with 1 and 2 collector workers,
sync and async, and collect-only env steps per second against the raw env, in one run.

An iteration is the tutorial's: one env step and one update (batch 256, (256, 256) networks).
The TF-Agents actor-learner tutorial does ~21 iterations/s on this machine (0.048 s each); it
cannot run here (it needs the dead ``gym`` package), so its figure is quoted, not re-measured.
"""

from __future__ import annotations

import functools
import sys
import time
from pathlib import Path

TUTORIAL_ITERATIONS_PER_S = 21.0


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


def bench_sac(args, out: Path) -> dict:
    from rlpipe.pipelines import resolve_preset
    from rlpipe.pipelines.config import apply_overrides
    from rlpipe.pipelines.sac import SAC
    from rlpipe.scripts.bench_minitaur import bench_minitaur_raw
    from rlpipe.scripts.bench_td3 import _after_startup_updates_per_s

    iterations = args.steps or 2000
    raw = bench_minitaur_raw(2000, seed=0)["steps_per_s"]
    rows, figures = [], {"raw_env_steps_per_s": raw}
    for workers, sync in ((1, True), (2, True), (1, False), (2, False)):
        collect = collect_only_steps_per_s(workers, sync, 2000)
        _, cfg = resolve_preset("sac")
        cfg = apply_overrides(cfg, [
            "initial_collect_steps=1000", f"num_iterations={iterations}", "eval_interval=0", "num_eval_episodes=1",
            f"log_interval={max(100, iterations // 5)}", f"checkpoint_interval={iterations}",
            f"collector.workers={workers}", f"collector.sync={str(sync).lower()}", *args.overrides,
        ])
        result = SAC(cfg).train(out / f"sac-w{workers}-{'sync' if sync else 'async'}", progress=False)
        speed = _after_startup_updates_per_s(result.metrics)
        figures[f"workers={workers} sync={sync}"] = {"iterations_per_s": speed, "collect_only_steps_per_s": collect,
                                                    "summary": result.summary}
        print(f"  workers={workers} sync={sync}: {speed:.1f} it/s, collect-only {collect:.0f} steps/s", file=sys.stderr)
        rows.append(f"| {workers} | {'MultiSyncCollector' if sync and workers > 1 else 'Collector (in-process)' if sync else 'MultiAsyncCollector'} "
                    f"| {speed:.1f} | {speed / TUTORIAL_ITERATIONS_PER_S:.2f} | {collect:.0f} | {collect / raw:.2f} |")
    table = "\n".join([
        f"SAC benchmark: Minitaur (rlpipe/MinitaurBullet-v0), tutorial settings, {iterations} iterations after "
        f"1000 random steps, no evaluations. Raw env: {raw:.0f} steps/s (random actions, resets included).",
        "",
        "| workers | collector | iterations/s (1 step + 1 update) | x TF-Agents tutorial (21 it/s, quoted) | collect-only env steps/s | collect-only / raw env |",
        "|---|---|---|---|---|---|",
        *rows,
    ])
    return {**figures, "table": table}
