"""``rlpipe bench replay-memory``: the resident memory of an image replay buffer, measured, not computed.

Fills the buffer an image run makes (``modules.frames.FrameReplayBuffer``: each frame once, uint8) with
``--steps`` transitions (default one million) of Atari-shaped observations (4 stacked 84x84 grey frames, episodes
of 1,000 steps in blocks of 1,000, as one collector gives them) and reads the process's resident memory before and
after (psutil), beside the floor (one uint8 frame per transition) and what the stacks would take stored as they
come (two uint8 stacks per transition) and as float32. The frames are random bytes: the memory is the same.
Then times ``sample()`` of batch 32.
"""

from __future__ import annotations

import time

__all__ = ["bench_replay_memory"]

_SHAPE = (84, 84)
_STACK = 4
_EPISODE = 1000


def bench_replay_memory(args, out) -> dict:
    import psutil
    import torch
    from tensordict import TensorDict
    from torchrl.data import LazyTensorStorage

    from rlpipe.modules.frames import TRAJ_IDS, FrameReplayBuffer

    steps = args.steps or 1_000_000
    process = psutil.Process()
    before = process.memory_info().rss
    rb = FrameReplayBuffer(storage=LazyTensorStorage(steps), batch_size=32, capacity=steps, frame_stack=_STACK,
                           channels=1)
    generator = torch.Generator().manual_seed(0)
    started = time.perf_counter()
    written = 0
    while written < steps:
        length = min(_EPISODE, steps - written)
        frames = torch.randint(0, 256, (length + _STACK, *_SHAPE), dtype=torch.uint8, generator=generator)
        windows = frames.unfold(0, _STACK, 1).permute(0, 3, 1, 2)  # [length + 1, 4, 84, 84]
        done = torch.zeros(length, 1, dtype=torch.bool)
        done[-1] = True
        block = TensorDict({
            "observation": windows[:length].contiguous(), "action": torch.zeros(length, dtype=torch.long),
            TRAJ_IDS: torch.full((length,), written // _EPISODE),
            "next": {"observation": windows[1:length + 1].contiguous(), "reward": torch.zeros(length, 1),
                     "done": done, "terminated": done.clone()},
        }, batch_size=[length])
        rb.extend(block)
        written += length
    fill_s = time.perf_counter() - started
    after = process.memory_info().rss
    timings = []
    for _ in range(200):
        start = time.perf_counter()
        rb.sample()
        timings.append(time.perf_counter() - start)
    sample_us = sorted(timings)[len(timings) // 2] * 1e6
    frame = _SHAPE[0] * _SHAPE[1]
    gb = 1e9
    figures = {
        "steps": steps, "resident_before_gb": before / gb, "resident_after_gb": after / gb,
        "buffer_resident_gb": (after - before) / gb, "floor_gb": steps * frame / gb,
        "two_uint8_stacks_gb": steps * 2 * _STACK * frame / gb, "two_float32_stacks_gb": steps * 8 * _STACK * frame / gb,
        "fill_s": fill_s, "sample_us": sample_us,
    }
    figures["table"] = "\n".join([
        f"Replay buffer of {steps:,} Atari transitions (4 x 84x84 uint8 frames each), resident memory (psutil RSS):",
        "",
        "| | GB |",
        "|---|---|",
        f"| the process before the buffer | {figures['resident_before_gb']:.2f} |",
        f"| the process with the buffer full | {figures['resident_after_gb']:.2f} |",
        f"| **the buffer (measured: after less before)** | **{figures['buffer_resident_gb']:.2f}** |",
        f"| the floor: one uint8 frame per transition (computed) | {figures['floor_gb']:.2f} |",
        f"| both stacks stored as uint8 (computed) | {figures['two_uint8_stacks_gb']:.2f} |",
        f"| both stacks stored as float32 (computed) | {figures['two_float32_stacks_gb']:.2f} |",
        "",
        f"filled in {fill_s:.0f} s; sample() of 32 transitions: {sample_us:.0f} us (median of 200)",
    ])
    return figures
