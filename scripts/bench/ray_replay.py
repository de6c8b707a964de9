"""Does a replay buffer as a Ray actor (TorchRL's ``service_backend="ray"``) pay against shipping blocks?

    .venv/bin/python -m rlpipe.scripts.bench.ray_replay

A measurement, not a test. Two ways for collector actors' frames to reach the learner's updates:

* shipping (rlpipe's way): an actor returns a block of 50 frames to the learner, which stores it
  in its own ``ReplayBuffer`` and samples from it in-process;
* a Ray replay buffer, as the tutorial's actors write into Reverb: actors extend the buffer actor
  directly, and the learner asks it for each batch (one Ray call per update).

At the tutorials' one update per collected frame, the learner pays per update: a fiftieth of a
block's transfer and insert plus a local sample, or one remote sample. Prints a Markdown table.
"""

from __future__ import annotations

import functools
import statistics
import time

import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, ReplayBuffer

BLOCK, BATCH, CAPACITY = 50, 256, 100_000
KEYS = ["observation", "action", ("next", "observation"), ("next", "reward"), ("next", "done"), ("next", "terminated")]


def pendulum_block(n: int = BLOCK) -> TensorDict:
    """A block as TD3's collector hands it over on Pendulum (observation 3, action 1, TorchRL's keys)."""
    flags = {k: torch.zeros(n, 1, dtype=torch.bool) for k in ("done", "terminated", "truncated", "is_init")}
    counters = {"step_count": torch.zeros(n, 1, dtype=torch.int64), "episode_reward": torch.zeros(n, 1)}
    return TensorDict({"observation": torch.randn(n, 3), "action": torch.randn(n, 1), **flags, **counters,
                       "next": {"observation": torch.randn(n, 3), "reward": torch.randn(n, 1), **flags, **counters},
                       "collector": {"traj_ids": torch.zeros(n, dtype=torch.int64)}}, batch_size=[n])


def median_ms(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times) * 1e3


def main() -> None:
    import ray

    torch.set_num_threads(1)
    ray.init(address="local", include_dashboard=False, log_to_driver=False, logging_level="error")
    try:
        producer = ray.remote(num_cpus=1)(_Producer).remote()
        ray.get(producer.block.remote())
        ship = median_ms(lambda: ray.get(producer.block.remote()), 200)

        local = ReplayBuffer(storage=LazyTensorStorage(CAPACITY), batch_size=BATCH)
        for _ in range(100):
            local.extend(pendulum_block().select(*KEYS))
        insert = median_ms(lambda: local.extend(pendulum_block().select(*KEYS)), 200)
        sample = median_ms(local.sample, 500)

        remote = ReplayBuffer(storage=functools.partial(LazyTensorStorage, CAPACITY), batch_size=BATCH,
                              service_backend="ray", service_backend_options={"remote_config": {"num_cpus": 0}})
        try:
            for _ in range(100):
                remote.extend(pendulum_block().select(*KEYS))
            remote_sample = median_ms(remote.sample, 500)
            remote_insert = median_ms(lambda: remote.extend(pendulum_block().select(*KEYS)), 200)
        finally:
            remote.shutdown()
    finally:
        ray.shutdown()
    shipping = ship / BLOCK + insert / BLOCK + sample
    print("| the learner's cost per update (1 frame per update) | ms |\n|---|---|")
    print(f"| shipping: {BLOCK}-frame block from an actor ({ship:.2f} ms) + local insert ({insert:.2f} ms), "
          f"per frame, + local sample of {BATCH} ({sample:.2f} ms) | {shipping:.3f} |")
    print(f"| Ray replay buffer: one remote sample of {BATCH} (actors' inserts, {remote_insert:.2f} ms a block, "
          f"off the learner) | {remote_sample:.3f} |")


class _Producer:
    def block(self) -> TensorDict:
        return pendulum_block()


if __name__ == "__main__":
    main()
