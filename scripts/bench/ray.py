"""``rlpipe bench ray``: collectors as Ray actors against local collector processes.

Three parts, all on this machine, Ray on a local instance the bench starts and shuts down
(``ray.address`` empty):

1. Collect-only env steps/s (no learner) with 1, 2, 4 workers (``--workers``): ``collector.backend=ray``
   (``RayBackend``: TorchRL's ``RayCollector``, one actor per worker, weights pushed to a worker
   each time it is asked for a block, as in training) against ``collector.backend=local``
   (``MultiAsyncCollector``), both made by ``pipeline.make_collector`` of the ``sac`` preset with its
   stochastic actor and ``collector.sync=false``. The rate is timed after the first block; Ray's
   start-up (``ray.init``, placing the actors, connecting the weight sync, the first block) is
   reported on its own.
2. The ``sac`` preset trained with ``collector.backend=ray`` and with its local collector process,
   iterations/s timed over two lengths (``--steps N``: N and N + 2000 iterations after the random
   start-up, or ``--lengths N1 N2``; each a fresh ``rlpipe train`` process), so start-up cancels.
3. The arithmetic of more machines: the learner's ceiling (the SAC update alone, timed as
   ``rlpipe bench floor`` times it) against the env steps one actor gives per second, at the
   preset's updates per env step (``1 / collect_steps_per_iteration``, held by the
   samples-per-insert limiter): N actors saturate the learner at N = ceiling / (steps per actor x
   updates per step).
"""

from __future__ import annotations

import math
import os
import sys
import time
from pathlib import Path

WORKERS = (1, 2, 4)


def collect_run(preset: str, overrides: list[str], backend: str, workers: int, frames: int) -> dict:
    """Collect-only env steps/s of ``workers`` async collectors on ``backend``, and their start-up seconds."""
    from rlpipe.scripts.bench.collect import pipeline_for_collection, timed_blocks

    pipeline = pipeline_for_collection(preset, [*overrides, f"collector.backend={backend}",
                                                f"collector.workers={workers}", "collector.sync=false"])
    try:
        t0 = time.perf_counter()
        # total_frames: more than will be asked for (RayCollector stops at once on -1)
        collector = pipeline.make_collector(total_frames=10**9, init_random_frames=0)
        made_s = time.perf_counter() - t0
        collector.set_seed(pipeline.config.seed)
        result = timed_blocks(collector, frames)  # shuts the collector down (and a local Ray with it)
    finally:
        pipeline.env.close()
        pipeline.eval_env.close()
    return {**result, "made_s": made_s, "startup_s": made_s + result["first_block_s"]}


def update_ceiling(preset: str, overrides: list[str]) -> dict:
    """The learner's updates/s with nothing else to do: the preset's update alone on a replay-sized
    batch (``bench_floor.update_seconds``), on 1 thread and on every core; the ceiling is the faster."""
    import torch

    from rlpipe.pipelines import pipeline_class, resolve_preset
    from rlpipe.pipelines.config import apply_overrides
    from rlpipe.pipelines.system.runtime import keep_freed_memory
    from rlpipe.scripts.bench.floor import update_seconds

    algo, cfg = resolve_preset(preset)
    pipeline = pipeline_class(algo)(apply_overrides(cfg, ["eval_in_background=false", *overrides]))
    keep_freed_memory()  # as the training loop does
    before = torch.get_num_threads()
    per_threads = {}
    try:
        for threads in sorted({1, os.cpu_count() or 1}):
            torch.set_num_threads(threads)
            per_threads[threads] = 1.0 / update_seconds(pipeline)
    finally:
        torch.set_num_threads(before)
        pipeline.env.close()
        pipeline.eval_env.close()
    return {"updates_per_s": max(per_threads.values()), "per_threads": per_threads,
            "updates_per_env_step": 1.0 / pipeline.config.collect_steps_per_iteration}


def saturation(updates_per_s: float, steps_per_actor_s: float, updates_per_env_step: float,
               actors: tuple[int, ...] = (1, 2, 4, 8, 16)) -> dict:
    """What N actors (each on a core of its own, ``steps_per_actor_s`` env steps/s) give a learner
    that can make ``updates_per_s`` updates/s and owes ``updates_per_env_step`` per env step.

    The limiter holds updates = env steps x ratio, so the system runs at
    ``min(N x steps_per_actor_s, updates_per_s / ratio)`` env steps/s; ``saturating_actors`` is the
    N where the two meet (actors past it wait for the learner).
    """
    if min(updates_per_s, steps_per_actor_s, updates_per_env_step) <= 0:
        raise ValueError("saturation: expected positive rates and ratio")
    env_ceiling = updates_per_s / updates_per_env_step
    n_star = env_ceiling / steps_per_actor_s
    rows = [{"actors": n, "env_steps_per_s": min(n * steps_per_actor_s, env_ceiling),
             "updates_per_s": min(n * steps_per_actor_s, env_ceiling) * updates_per_env_step,
             "learner_bound": n * steps_per_actor_s >= env_ceiling} for n in actors]
    return {"saturating_actors": n_star, "actors_needed": math.ceil(n_star), "env_steps_per_s_ceiling": env_ceiling,
            "rows": rows}


def arithmetic_text(ceiling: dict, steps_per_actor_s: float, measured_it_s: float | None) -> str:
    """The "N machines" paragraph and table, from the ceiling and one actor's env steps/s."""
    r = ceiling["updates_per_env_step"]
    s = saturation(ceiling["updates_per_s"], steps_per_actor_s, r)
    threads = ", ".join(f"{n} thread{'s' if n > 1 else ''}: {u:.0f}" for n, u in ceiling["per_threads"].items())
    lines = [
        f"Learner ceiling: the SAC update alone makes {ceiling['updates_per_s']:.0f} updates/s ({threads}); "
        f"the preset owes {r:g} update(s) per env step, so the learner can use at most "
        f"{s['env_steps_per_s_ceiling']:.0f} env steps/s. One Ray actor gives {steps_per_actor_s:.0f} env steps/s "
        f"(collect-only, above). N actors saturate the learner at N = {ceiling['updates_per_s']:.0f} / "
        f"({steps_per_actor_s:.0f} x {r:g}) = **{s['saturating_actors']:.2f}**, i.e. {s['actors_needed']} "
        f"actor{'s' if s['actors_needed'] > 1 else ''}, each on a core (or machine) of its own; more only wait for "
        "the learner. (One actor's rate here shares this machine's cores with the driver and the other actors; "
        "on a machine of its own it is nearer the raw env's.)",
    ]
    if measured_it_s:
        lines.append("")
        lines.append(f"Measured training here (the sac preset, Ray): {measured_it_s:.1f} iterations/s, "
                     f"{measured_it_s / ceiling['updates_per_s']:.2f} of the ceiling (the rest: sampling, "
                     "inserting, the loop, and sharing 2 cores with the actors).")
    lines += ["", "| actors (one core each) | env steps/s | updates/s | bound by |", "|---|---|---|---|"]
    lines += [f"| {row['actors']} | {row['env_steps_per_s']:.0f} | {row['updates_per_s']:.0f} | "
              f"{'learner' if row['learner_bound'] else 'actors'} |" for row in s["rows"]]
    return "\n".join(lines)


def bench_ray(args, out: Path) -> dict:
    from rlpipe.scripts.bench.collect import check_args
    from rlpipe.scripts.bench.sac import rlpipe_iterations_per_s

    check_args(args)
    workers = args.workers or list(WORKERS)
    env_id = (args.envs or ["MinitaurBulletEnv-v0"])[0]
    preset = args.preset or "sac"
    env_override = [] if env_id == "MinitaurBulletEnv-v0" and preset == "sac" else [f"env={env_id}"]
    overrides = [*env_override, *args.overrides]
    frames = 1000 if args.frames is None else args.frames
    collect = {}
    for w in workers:
        for backend in ("local", "ray"):
            collect[(backend, w)] = run = collect_run(preset, overrides, backend, w, frames)
            print(f"  collect-only {backend} workers={w}: {run['steps_per_s']:.0f} env steps/s "
                  f"(start-up {run['startup_s']:.1f} s)", file=sys.stderr)
    n = args.steps or 500
    iterations = tuple(args.lengths) if args.lengths else (n, n + 2000)
    training = {}
    for backend in ("local", "ray"):
        training[backend] = rlpipe_iterations_per_s(iterations, out / backend, [*overrides, f"collector.backend={backend}"])
        print(f"  sac preset, collector.backend={backend}: {training[backend]['iterations_per_s']:.1f} it/s",
              file=sys.stderr)
    ceiling = update_ceiling(preset, overrides)
    from rlpipe.pipelines import resolve_preset
    from rlpipe.pipelines.config import apply_overrides

    trained = apply_overrides(resolve_preset(preset)[1], overrides).collector
    w1 = min(workers)  # per actor: the fewest workers' rate, shared out
    ray1, local1 = collect[("ray", w1)]["steps_per_s"] / w1, collect[("local", w1)]["steps_per_s"] / w1
    ray_it, local_it = training["ray"]["iterations_per_s"], training["local"]["iterations_per_s"]
    rows = [f"| {w} | {collect[('local', w)]['steps_per_s']:.0f} | {collect[('ray', w)]['steps_per_s']:.0f} | "
            f"{collect[('ray', w)]['steps_per_s'] / collect[('local', w)]['steps_per_s']:.2f} | "
            f"{collect[('local', w)]['startup_s']:.1f} | {collect[('ray', w)]['startup_s']:.1f} |" for w in workers]
    table = "\n".join([
        f"Ray collectors against local ones on this machine ({os.cpu_count()} cores): preset `{preset}`, env {env_id}, "
        f"async collection, the preset's stochastic actor, {frames}+ frames timed after the first block.",
        "",
        "| workers | local MultiAsyncCollector env steps/s | Ray actors env steps/s | Ray / local | "
        "local start-up s (to first block) | Ray start-up s (ray.init, actors, weight sync, first block) |",
        "|---|---|---|---|---|---|",
        *rows,
        "",
        f"Ray's cost per env step here ({w1} worker{'s' if w1 > 1 else ''}, per worker): {1e3 / ray1:.2f} ms against {1e3 / local1:.2f} ms locally, "
        f"{1e3 * (1 / ray1 - 1 / local1):+.2f} ms per step.",
        "",
        f"Training, the `{preset}` preset, timed over {iterations[0]} and {iterations[1]} iterations (fresh processes, "
        "start-up cancels):",
        "",
        "| collector.backend | iterations/s (1 env step + 1 update) | ms per iteration |",
        "|---|---|---|",
        f"| local ({trained.workers} collector process{'es' if trained.workers > 1 else ''}, sync={str(trained.sync).lower()}) | {local_it:.1f} | "
        f"{1e3 / local_it:.1f} |",
        f"| ray ({trained.workers} actor{'s' if trained.workers > 1 else ''}, sync={str(trained.sync).lower()}) | {ray_it:.1f} | {1e3 / ray_it:.1f} |",
        "",
        f"Ray / local: {ray_it / local_it:.2f} ({1e3 * (1 / ray_it - 1 / local_it):+.1f} ms per iteration).",
        "",
        arithmetic_text(ceiling, ray1, ray_it),
    ])
    return {"collect": {f"{b}-{w}": v for (b, w), v in collect.items()}, "training": training,
            "ceiling": ceiling, "saturation": saturation(ceiling["updates_per_s"], ray1, ceiling["updates_per_env_step"]),
            "table": table}
