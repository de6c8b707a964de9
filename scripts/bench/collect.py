"""``rlpipe bench collect``: collection against the env's own speed and CleanRL's loop.

For each env (default CartPole-v1, Pendulum-v1, MinitaurBulletEnv-v0): the raw env's steps/s (the
gymnasium env stepped with random actions in a plain loop, resets included; Minitaur: our own env,
``minitaur.bench_minitaur_raw``); the plain loop (CleanRL's ``obs -> policy -> env.step``, numpy in
and out, with the same policy network as the preset's collection policy); then collect-only env
steps/s of the collectors rlpipe builds for training: the pipeline of the env's preset (its
collection policy: DQN's epsilon-greedy, TD3's noisy actor, SAC's stochastic actor), made by
``pipeline.make_collector`` as the training loop makes it: in-process, TorchRL's ``Collector``
(``collector.direct=false``) and rlpipe's ``GymCollector`` (``collector.direct=true``), alternated,
and in one collector process (``MultiAsyncCollector``, 1 worker). ``collector.envs_per_worker=N``
(``--envs-per-worker``) makes one TorchRL env of batch [N] (TorchRL's path only). No learner; the
policy in this process on one torch thread (``num_threads=N`` to change). The clock starts after the
first block (process start-up, first env reset, first policy call) and runs until ``--frames`` more
frames (at least 3 blocks) have arrived.

The target: one env per collector at >= half the plain loop's steps/s (BENCHMARKS.md, "Collection only: `rlpipe
bench collect`").
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path

# env id -> (preset whose collection policy and settings are used, overrides)
PRESETS = {
    # epsilon at the preset's end value, as after its decay: at its start (1.0) CleanRL's loop never calls the network
    "CartPole-v1": ("dqn-cartpole-v1", ["epsilon_greedy=0.04", "epsilon_greedy_end=null"]),
    "Pendulum-v1": ("td3", []),
    "HalfCheetah-v5": ("sac-halfcheetah", []),
    "MinitaurBulletEnv-v0": ("sac", []),
}
DEFAULT_ENVS = ("CartPole-v1", "Pendulum-v1", "MinitaurBulletEnv-v0")
"""the envs of the three tutorials' presets"""
ENVS_PER_WORKER = (1,)
TARGET_FRACTION = 0.5
"""the target: one env per collector at least half the plain loop's steps/s (same env, same policy network)"""


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


def collect_steps_per_s(preset: str, overrides: list[str], envs_per_worker: int, process: bool, frames: int,
                        direct: bool = False) -> dict:
    """Collect-only env steps/s of the collector the pipeline makes, with its collection policy.

    ``process=False``: ``collector.workers=1 collector.sync=true`` (in this process); ``True``:
    ``collector.sync=false`` (a ``MultiAsyncCollector`` with one worker process). ``direct``: each
    collector is rlpipe's ``GymCollector`` (``collector.direct=true``), else TorchRL's ``Collector``.
    """
    import torch

    from rlpipe.pipelines import resolve_preset
    from rlpipe.pipelines.config import apply_overrides

    _, cfg = resolve_preset(preset)
    cfg = apply_overrides(cfg, list(overrides))  # a collector.frames_per_batch=N given on the command line counts
    fpb = frames_per_batch(cfg.collector.frames_per_batch, envs_per_worker)
    pipeline = pipeline_for_collection(preset, [
        *overrides, "collector.backend=local", "collector.workers=1", f"collector.sync={str(not process).lower()}",
        f"collector.envs_per_worker={envs_per_worker}", f"collector.frames_per_batch={fpb}",
        f"collector.direct={str(direct).lower()}",
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
        result["collector"] = type(collector).__name__
    finally:
        torch.set_num_threads(before)
        pipeline.env.close()
        pipeline.eval_env.close()
    return {**result, "frames_per_batch": fpb, "threads": threads or before}


def plain_loop_steps_per_s(preset: str, overrides: list[str], steps: int, seed: int = 0) -> dict:
    """CleanRL's loop (``obs -> policy -> env.step``, numpy in and out) over the same gymnasium env with the
    same policy network as the preset's collection policy, exploring as CleanRL's scripts do: dqn.py's
    epsilon-greedy (``random.random() < epsilon``), td3_continuous_action.py's Gaussian noise then clip,
    sac_continuous_action.py's ``get_action`` (a Normal sample through tanh, its log-probability). On one
    torch thread, resets included."""
    import random

    import torch

    from rlpipe.modules.fast.exploration import EGreedyQPolicy

    pipeline = pipeline_for_collection(preset, [*overrides, "collector.backend=local", "collector.workers=1",
                                                "collector.sync=true", "collector.envs_per_worker=1"])
    env = pipeline.env.base_env._env  # the gymnasium env under TorchRL's GymEnv: the same object ours steps
    policy = pipeline.collect_policy
    low = high = None
    if isinstance(policy, EGreedyQPolicy):
        qnet, epsilon = policy.module[0].module[0].module, float(policy._lean_parts()[3].eps)  # the nn.Module

        def act(obs):
            if random.random() < epsilon:
                return env.action_space.sample()
            return int(torch.argmax(qnet(torch.Tensor(obs)), dim=-1).cpu().numpy())
    elif hasattr(policy, "module") and type(policy.module[-1]).__name__ == "AdditiveGaussianModule":
        net, noise = policy.module[0].module, policy.module[-1]
        low, high = env.action_space.low, env.action_space.high
        noise_std = (noise.std * noise.sigma).expand(int(low.shape[-1]))

        def act(obs):
            action = net(torch.Tensor(obs))
            action += torch.normal(0.0, noise_std)
            return action.cpu().numpy().clip(low, high)
    else:  # SAC's TanhNormal actor: the network, then CleanRL's get_action
        net = policy.module[0].module
        low, high = env.action_space.low, env.action_space.high
        scale_ = torch.as_tensor((high - low) / 2, dtype=torch.float32)
        bias_ = torch.as_tensor((high + low) / 2, dtype=torch.float32)

        def act(obs):
            loc, scale = net(torch.Tensor(obs))
            normal = torch.distributions.Normal(loc, scale)
            x_t = normal.rsample()
            y_t = torch.tanh(x_t)
            action = y_t * scale_ + bias_
            log_prob = normal.log_prob(x_t) - torch.log(scale_ * (1 - y_t.pow(2)) + 1e-6)
            log_prob.sum(-1)
            return action.cpu().numpy()
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        random.seed(seed)
        env.action_space.seed(seed)
        obs, _ = env.reset(seed=seed)
        with torch.no_grad():
            for _ in range(min(100, steps)):  # first calls (lazy initialisations) untimed
                obs, _, term, trunc, _ = env.step(act(obs))
                if term or trunc:
                    obs, _ = env.reset()
            t0 = time.perf_counter()
            for _ in range(steps):
                obs, _, term, trunc, _ = env.step(act(obs))
                if term or trunc:
                    obs, _ = env.reset()
            elapsed = time.perf_counter() - t0
    finally:
        torch.set_num_threads(before)
        pipeline.env.close()
        pipeline.eval_env.close()
    return {"steps_per_s": steps / elapsed, "frames": steps, "seconds": elapsed}


def target_cell(fraction: float) -> str:
    """A table cell: the fraction of the raw env's speed, bold with "met" where it reaches the target."""
    return f"**{fraction:.2f} met**" if fraction >= TARGET_FRACTION else f"{fraction:.2f}"


def _runs_cell(xs: list[float]) -> str:
    return " / ".join(f"{x:.0f}" for x in xs) if xs else "-"


def _ratio_cell(xs: list[float], plain: float, target: bool = False) -> str:
    if not xs:
        return "-"
    return target_cell(_mean(xs) / plain) if target else f"{_mean(xs) / plain:.2f}"


COLUMNS = (("torchrl", "TorchRL Collector, in-process"), ("ours", "rlpipe GymCollector, in-process"),
           ("torchrl_process", "TorchRL, 1 collector process"), ("ours_process", "rlpipe, 1 collector process"))
"""the collectors measured (row key, column title): TorchRL's over GymEnv (collector.direct=false) and rlpipe's
GymCollector (collector.direct=true), in the learner's process (Collector) and in one worker (MultiAsyncCollector)"""


def collect_table(rows: list[dict], steps: int, overrides: list[str]) -> str:
    """Markdown table of ``rows`` (one per env and envs_per_worker): raw env, plain loop, then each collector's
    runs (alternated) and their mean's ratio to the plain loop."""
    lines = [
        f"Collect-only env steps/s (no learner), each preset's collection policy, on one torch thread, over >= {steps} "
        f"frames after the first block. Raw env: the gymnasium env under random actions. Plain loop: CleanRL's loop "
        f"(obs -> policy -> env.step, numpy in and out) with the same policy network. The collectors' runs alternate "
        f"TorchRL's path (collector.direct=false: `Collector` over `GymEnv`) and rlpipe's (collector.direct=true: "
        f"`GymCollector`); each run is listed, ratios from their means. Target: rlpipe's >= {TARGET_FRACTION:g} of "
        f"the plain loop (\"met\" in bold).{' Overrides: ' + ' '.join(overrides) if overrides else ''}",
        "",
        "| env | preset (collection policy) | raw env | plain loop | envs per worker | frames per block | "
        + " | ".join(f"{title} | / plain" for _, title in COLUMNS) + " |",
        "|---|---|---|---|---|---|" + "---|---|" * len(COLUMNS),
    ]
    for r in rows:
        cells = " | ".join(f"{_runs_cell(r.get(key, []))} | {_ratio_cell(r.get(key, []), r['plain'], key.startswith('ours'))}"
                           for key, _ in COLUMNS)
        lines.append(f"| {r['env']} | {r['preset']} | {r['raw']:.0f} | {r['plain']:.0f} | {r['envs_per_worker']} | "
                     f"{r['frames_per_batch']} | {cells} |")
    met = [r for r in rows if r.get("ours") and _mean(r["ours"]) >= TARGET_FRACTION * r["plain"]]
    lines += ["", "Target met (rlpipe in-process) for: " + (
        "; ".join(f"{r['env']} at envs_per_worker={r['envs_per_worker']}" for r in met) or "none") + "."]
    return "\n".join(lines)


def _mean(xs: list[float]) -> float:
    return sum(xs) / len(xs)


REPEATS = 2
"""runs of each collector, alternated (TorchRL's, rlpipe's, TorchRL's, ...)"""


def bench_collect(args, out: Path) -> dict:
    check_args(args)
    steps = 3000 if args.frames is None else args.frames
    envs = args.envs or list(DEFAULT_ENVS)
    counts = args.envs_per_worker or list(ENVS_PER_WORKER)
    rows = []
    for env_id in envs:
        preset, extra = preset_for(env_id)
        overrides = [*extra, *args.overrides]
        raw = raw_env_steps_per_s(env_id, max(steps, 2000))
        plain = plain_loop_steps_per_s(preset, overrides, steps)["steps_per_s"]
        print(f"  {env_id} raw env: {raw:.0f} steps/s; plain loop, same policy network: {plain:.0f}", file=sys.stderr)
        for n in counts:
            runs: dict[str, list[dict]] = {key: [] for key, _ in COLUMNS}
            for _ in range(REPEATS):
                for process in (False, True):
                    suffix = "_process" if process else ""
                    runs["torchrl" + suffix].append(collect_steps_per_s(preset, overrides, n, process, steps, direct=False))
                    if n == 1:  # GymCollector steps one env; a vector of them is TorchRL's path
                        runs["ours" + suffix].append(collect_steps_per_s(preset, overrides, n, process, steps, direct=True))
            speeds = {key: [r["steps_per_s"] for r in rs] for key, rs in runs.items()}
            print(f"  {env_id} envs_per_worker={n}: " + "; ".join(
                f"{title} {_runs_cell(speeds[key])}" for key, title in COLUMNS) + " steps/s", file=sys.stderr)
            rows.append({"env": env_id, "preset": preset, "raw": raw, "plain": plain, "envs_per_worker": n,
                         "frames_per_batch": runs["torchrl"][0]["frames_per_batch"], **speeds, "runs": runs})
    return {"rows": rows, "steps": steps, "table": collect_table(rows, steps, args.overrides)}
