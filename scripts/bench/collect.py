"""``rlpipe bench collect``: collection against the env's own speed (issue 9).

For each env: the raw env's steps/s (the gymnasium env stepped with random actions in a plain loop,
resets included; Minitaur: our own env, ``minitaur.bench_minitaur_raw``), then collect-only
env steps/s of the collectors rlpipe builds for training: the pipeline of the env's preset (its
collection policy: DQN's epsilon-greedy, TD3's noisy actor, SAC's stochastic actor) with
``collector.envs_per_worker=N`` (one TorchRL env of batch [N] over gymnasium's ``SyncVectorEnv``,
the policy run once per N env steps), made by ``pipeline.make_collector`` as the training loop
makes it, in-process (``Collector``) and in one collector process (``MultiAsyncCollector``, 1
worker). No learner; the policy in this process on one torch thread (``num_threads=N`` to change).
The clock starts after the first block (process start-up, first env reset,
first policy call) and runs until ``--frames`` more frames (at least 3 blocks) have arrived.

Target (issue 9): collect-only steps/s at least half the raw env's.
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path

# env id -> (preset whose collection policy and settings are used, overrides)
PRESETS = {
    "CartPole-v1": ("dqn-cartpole-v1", []),
    "Pendulum-v1": ("td3", []),
    "HalfCheetah-v5": ("sac-halfcheetah", []),
    "MinitaurBulletEnv-v0": ("sac", []),
}
ENVS_PER_WORKER = (1, 8, 32)
TARGET_FRACTION = 0.5
"""issue 9: collector env steps/s at least half the raw env's"""


def check_args(args) -> None:
    """``InputError`` for options of ``bench collect`` / ``bench ray`` that cannot work (nothing run yet)."""
    from rlpipe.envs import EnvError, resolve_env_id
    from rlpipe.pipelines.errors import InputError

    if args.frames is not None and args.frames <= 0:
        raise InputError(f"--frames={args.frames}: expected a positive number of frames")
    for option, values in (("--envs-per-worker", args.envs_per_worker), ("--workers", args.workers)):
        if values and any(v <= 0 for v in values):
            raise InputError(f"{option} {' '.join(map(str, values))}: expected positive integers")
    if args.target == "ray":
        if args.envs and len(args.envs) > 1:
            raise InputError(f"--envs {' '.join(args.envs)}: bench ray measures one env; expected one env id")
        if args.lengths and not 0 < args.lengths[0] < args.lengths[1]:
            raise InputError(f"--lengths {args.lengths[0]} {args.lengths[1]}: expected two iteration counts, 0 < N1 < N2")
        if args.steps is not None and args.steps <= 0:
            raise InputError(f"--steps={args.steps}: expected a positive number of iterations")
    for env_id in args.envs or []:
        try:
            resolve_env_id(env_id)
        except EnvError as exc:
            raise InputError(f"--envs: {exc}") from exc


def preset_for(env_id: str) -> tuple[str, list[str]]:
    """The preset whose collection policy collects ``env_id`` (another id: ``dqn`` or ``sac`` by its action space)."""
    if env_id in PRESETS:
        return PRESETS[env_id]
    from rlpipe.envs import is_discrete, make_env

    env = make_env(env_id)
    try:
        discrete = is_discrete(env.action_spec_unbatched)
    finally:
        env.close()
    return ("dqn" if discrete else "sac"), [f"env={env_id}"]


def frames_per_batch(preset_frames: int, envs_per_worker: int) -> int:
    """The preset's block size rounded up to whole steps of ``envs_per_worker`` envs (what validate asks)."""
    return envs_per_worker * max(1, math.ceil(preset_frames / envs_per_worker))


def raw_env_steps_per_s(env_id: str, steps: int, seed: int = 0) -> float:
    """Steps/s of the gymnasium env (no TorchRL) under uniform random actions, resets included."""
    import gymnasium

    from rlpipe.envs import MINITAUR_ID, resolve_env_id

    gym_id = resolve_env_id(env_id)
    if gym_id == MINITAUR_ID:
        from rlpipe.scripts.bench.minitaur import bench_minitaur_raw

        return bench_minitaur_raw(steps, seed=seed)["steps_per_s"]
    env = gymnasium.make(gym_id)
    try:
        env.action_space.seed(seed)
        t0 = time.perf_counter()
        env.reset(seed=seed)
        for _ in range(steps):
            _, _, terminated, truncated, _ = env.step(env.action_space.sample())
            if terminated or truncated:
                env.reset()
        return steps / (time.perf_counter() - t0)
    finally:
        env.close()


def timed_blocks(collector, frames: int, min_blocks: int = 3) -> dict:
    """Iterate ``collector`` (shut down at the end): env steps/s after its first block, and that block's wait.

    ``first_block_s`` is from the call to this function to the first block (a collector process's
    start, the first reset); the rate counts the frames of at least ``min_blocks`` later blocks
    and ``frames`` in all.
    """
    n, blocks, t0 = 0, 0, None
    start = time.perf_counter()
    first_block_s = None
    try:
        for batch in collector:
            if t0 is None:
                t0 = time.perf_counter()
                first_block_s = t0 - start
                continue
            n += batch.numel()
            blocks += 1
            if n >= frames and blocks >= min_blocks:
                break
        elapsed = time.perf_counter() - t0
    finally:
        collector.shutdown()
    return {"steps_per_s": n / elapsed, "frames": n, "seconds": elapsed, "first_block_s": first_block_s}


def pipeline_for_collection(preset: str, overrides: list[str]):
    """The preset's pipeline with ``overrides`` (the collector keys), as ``rlpipe train`` builds it."""
    from rlpipe.pipelines import pipeline_class, resolve_preset
    from rlpipe.pipelines.config import apply_overrides

    algo, cfg = resolve_preset(preset)
    # evaluation is no part of collection: no background evaluator process
    return pipeline_class(algo)(apply_overrides(cfg, ["eval_in_background=false", *overrides]))


def collect_steps_per_s(preset: str, overrides: list[str], envs_per_worker: int, process: bool, frames: int) -> dict:
    """Collect-only env steps/s of the collector the pipeline makes, with its collection policy.

    ``process=False``: ``collector.workers=1 collector.sync=true`` (TorchRL's ``Collector`` in this
    process); ``True``: ``collector.sync=false`` (a ``MultiAsyncCollector`` with one worker process).
    """
    import torch

    from rlpipe.pipelines import resolve_preset

    _, cfg = resolve_preset(preset)
    fpb = frames_per_batch(cfg.collector.frames_per_batch, envs_per_worker)
    pipeline = pipeline_for_collection(preset, [
        *overrides, "collector.backend=local", "collector.workers=1", f"collector.sync={str(not process).lower()}",
        f"collector.envs_per_worker={envs_per_worker}", f"collector.frames_per_batch={fpb}",
    ])
    # The policy in this process runs on num_threads torch threads (-1, not chosen here: 1). Two
    # threads for a policy on <= 32 rows gain nothing, and on a loaded 2-core machine their spinning
    # made the in-process collector up to 5x slower (CartPole, 8 envs: 455 against 2507 steps/s).
    threads = pipeline.config.num_threads if pipeline.config.num_threads >= 0 else 1
    before = torch.get_num_threads()
    try:
        if threads:
            torch.set_num_threads(threads)
        # init_random_frames=0: every block from the collection policy, as after the random start-up;
        # total_frames: more than will be asked for (RayCollector reads -1 as "none")
        collector = pipeline.make_collector(total_frames=10**9, init_random_frames=0)
        collector.set_seed(pipeline.config.seed)
        result = timed_blocks(collector, frames)
    finally:
        torch.set_num_threads(before)
        pipeline.env.close()
        pipeline.eval_env.close()
    return {**result, "frames_per_batch": fpb, "threads": threads or before}


def target_cell(fraction: float) -> str:
    """A table cell: the fraction of the raw env's speed, bold with "met" where it reaches the target."""
    return f"**{fraction:.2f} met**" if fraction >= TARGET_FRACTION else f"{fraction:.2f}"


def collect_table(rows: list[dict], steps: int, overrides: list[str]) -> str:
    """Markdown table of ``rows`` (one per env and envs_per_worker: raw, inproc, process figures)."""
    lines = [
        f"Collect-only env steps/s (no learner) through the collectors rlpipe builds, with each preset's "
        f"collection policy, against the raw gymnasium env (random actions, plain loop, resets included). "
        f"Timed over >= {steps} frames after the first block; the in-process policy on "
        f"{rows[0]['inproc_run']['threads'] if rows else 1} torch thread(s). Target: >= {TARGET_FRACTION:g} of raw "
        f"(\"met\" in bold).{' Overrides: ' + ' '.join(overrides) if overrides else ''}",
        "",
        "| env | preset (collection policy) | raw env steps/s | envs per worker | frames per block | "
        "in-process Collector steps/s | / raw | 1 collector process (MultiAsyncCollector) steps/s | / raw |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['env']} | {r['preset']} | {r['raw']:.0f} | {r['envs_per_worker']} | {r['frames_per_batch']} | "
            f"{r['inproc']:.0f} | {target_cell(r['inproc'] / r['raw'])} | "
            f"{r['process']:.0f} | {target_cell(r['process'] / r['raw'])} |")
    met = [r for r in rows if max(r["inproc"], r["process"]) >= TARGET_FRACTION * r["raw"]]
    by_env = {}
    for r in met:
        by_env.setdefault(r["env"], []).append(r["envs_per_worker"])
    lines += ["", "Target met (either collector) for: " + (
        "; ".join(f"{env} at envs_per_worker={', '.join(map(str, ns))}" for env, ns in by_env.items()) or "none") + "."]
    return "\n".join(lines)


def bench_collect(args, out: Path) -> dict:
    check_args(args)
    steps = 3000 if args.frames is None else args.frames
    envs = args.envs or list(PRESETS)
    counts = args.envs_per_worker or list(ENVS_PER_WORKER)
    rows = []
    for env_id in envs:
        preset, extra = preset_for(env_id)
        raw = raw_env_steps_per_s(env_id, max(steps, 2000))
        print(f"  {env_id} raw env: {raw:.0f} steps/s", file=sys.stderr)
        for n in counts:
            inproc = collect_steps_per_s(preset, [*extra, *args.overrides], n, False, steps)
            process = collect_steps_per_s(preset, [*extra, *args.overrides], n, True, steps)
            print(f"  {env_id} envs_per_worker={n}: in-process {inproc['steps_per_s']:.0f}, "
                  f"collector process {process['steps_per_s']:.0f} steps/s", file=sys.stderr)
            rows.append({"env": env_id, "preset": preset, "raw": raw, "envs_per_worker": n,
                         "frames_per_batch": inproc["frames_per_batch"], "inproc": inproc["steps_per_s"],
                         "process": process["steps_per_s"], "inproc_run": inproc, "process_run": process})
    return {"rows": rows, "steps": steps, "table": collect_table(rows, steps, args.overrides)}
