"""TorchRL's own faster collector settings against ``GymCollector``, run with ``python -m``.

CartPole-v1, one env, in-process, the ``dqn-cartpole-v1`` collect policy at its final epsilon (0.04):
steps/s of TorchRL's ``Collector`` over ``make_env`` (rlpipe's path with ``collector.direct=false``), over a
bare ``GymEnv``, with ``trust_policy`` and no buffers, with ``compile_policy``, and rlpipe's ``GymCollector``,
each after its first block. Figures: BENCHMARKS.md, "Where TorchRL's ~700 us a step go".
"""

from __future__ import annotations

import time
import warnings


def rate(collector, frames: int = 2000) -> float:
    iterator = iter(collector)
    next(iterator)
    t0, n = time.perf_counter(), 0
    while n < frames:
        n += next(iterator).numel()
    speed = n / (time.perf_counter() - t0)
    collector.shutdown()
    return speed


def main() -> None:
    import torch
    from torchrl.collectors import Collector
    from torchrl.envs import GymEnv

    from rlpipe.envs import make_env
    from rlpipe.pipelines import pipeline_class, resolve_preset
    from rlpipe.pipelines.compat.torchrl import COLLECTOR_KWARGS
    from rlpipe.pipelines.config import apply_overrides
    from rlpipe.pipelines.workers.gym_collector import GymCollector

    warnings.filterwarnings("ignore")
    torch.set_num_threads(1)
    algo, cfg = resolve_preset("dqn-cartpole-v1")
    policy = pipeline_class(algo)(apply_overrides(cfg, [
        "eval_in_background=false", "epsilon_greedy=0.04", "epsilon_greedy_end=null"])).collect_policy
    common = dict(frames_per_batch=50, total_frames=-1, **COLLECTOR_KWARGS)
    tries = {
        "Collector over make_env (today)": lambda: Collector(make_env("CartPole-v1"), policy, **common),
        "Collector, bare GymEnv (no transforms)": lambda: Collector(
            GymEnv("CartPole-v1", categorical_action_encoding=True), policy, **common),
        "Collector, trust_policy + use_buffers=False": lambda: Collector(
            make_env("CartPole-v1"), policy, trust_policy=True, use_buffers=False, **common),
        "Collector, compile_policy": lambda: Collector(make_env("CartPole-v1"), policy, compile_policy=True, **common),
        "GymCollector": lambda: GymCollector(make_env("CartPole-v1"), policy, **common),
    }
    for name, make in tries.items():
        try:
            print(f"{name}: {rate(make()):.0f} steps/s", flush=True)
        except Exception as exc:  # a TorchRL setting that does not run here is a figure too
            print(f"{name}: failed: {type(exc).__name__}: {str(exc).splitlines()[0][:150]}", flush=True)


if __name__ == "__main__":
    main()
