"""What a run will allocate, checked against the memory this machine has before anything is written.

TorchRL's ``LazyTensorStorage`` allocates the whole replay buffer at the first insert, and torch
the networks as they are built: a capacity or a layer size that does not fit ends in an allocator
traceback, or in the kernel's out-of-memory killer minutes into the run. Neither TorchRL nor torch
says beforehand what a config will take, so the estimate is made here, from the env's specs:
bytes per stored transition times the capacity, the collectors' blocks, the networks with their
gradients, Adam moments and target copies, and one process per collector worker.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import torch
from torchrl.envs import EnvBase

from rlpipe.pipelines.errors import InputError

__all__ = ["available_bytes", "check_memory", "transition_bytes"]

# Copies of each network's parameters a run keeps: the parameters, their gradients, Adam's two
# moments, a target copy; and SAC's/TD3's twin critics double the critic.
_COPIES_PER_PARAMETER = 5 * 2


def _read_int(path: str) -> int | None:  # a number alone in a file (cgroup's memory.max, memory.current)
    try:
        text = Path(path).read_text().strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None


def available_bytes(device: torch.device | str = "cpu") -> int | None:
    """Memory a new allocation on ``device`` can still have (None: unknown).

    On the CPU: the kernel's MemAvailable, or less where a cgroup (a container's memory limit)
    leaves less; on CUDA, the device's free memory.
    """
    device = torch.device(device)
    if device.type == "cuda":
        return int(torch.cuda.mem_get_info(device)[0])
    if device.type != "cpu":
        return None
    found = []
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                found.append(int(line.split()[1]) * 1024)
    except (OSError, ValueError, IndexError):
        pass
    limit, used = _read_int("/sys/fs/cgroup/memory.max"), _read_int("/sys/fs/cgroup/memory.current")
    if limit is not None and used is not None:
        found.append(max(0, limit - used))
    if not found and hasattr(os, "sysconf"):
        try:
            found.append(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
        except (ValueError, OSError):
            pass
    return min(found) if found else None


def transition_bytes(env: EnvBase, keys: list | None = None) -> int:
    """Bytes of one transition of ``env`` (one env copy of a batched env), of ``keys`` or all its entries."""
    fake = env.fake_tensordict()
    copies = max(1, math.prod(env.batch_size))
    if keys is not None:
        fake = fake.select(*keys, strict=False)
    total = sum(t.numel() * t.element_size() for t in fake.values(include_nested=True, leaves_only=True))
    return max(1, total // copies)


def _mlp_parameters(widths: list[int]) -> int:
    return sum((a + 1) * b for a, b in zip(widths, widths[1:]))


def _human(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB", "TB", "PB"):
        if n < 1024 or unit == "PB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} PB"


# A collector worker: a process with torch, TorchRL, gymnasium and one env imported (~370 MB
# resident measured here for Pendulum); its own env and copy of the policy come on top.
_WORKER_PROCESS_BYTES = 350 << 20


def check_memory(cfg, env: EnvBase, observation_key: str, action_dim: int, device: torch.device, *,
                 stored: list | None, networks: dict[str, list[int]], frame_bytes: int | None = None) -> None:
    """Raise ``InputError`` if the run ``cfg`` describes cannot fit in this machine's memory.

    ``stored``: the keys the replay buffer keeps of each transition (None: all); ``networks``: the
    config keys giving hidden layer sizes, with their values. The line names the key whose value
    takes the most, what the run would need, what the machine has available, and the largest value
    that would fit where that is one number. ``frame_bytes``: a frame-stacking buffer's bytes of frames per
    transition (``modules.frames``), which then stores the observations in place of ``stored``'s.
    """
    available = available_bytes(device)
    if available is None:
        return
    obs = observation_key
    if frame_bytes is None:
        per_transition = transition_bytes(env, stored)
    else:
        rest = [k for k in (stored or env.fake_tensordict().keys(True, True)) if k not in (obs, ("next", obs))]
        per_transition = transition_bytes(env, rest) + frame_bytes
    per_block_transition = transition_bytes(env)
    obs_dim = int(env.observation_spec[obs].shape[-1]) if obs in env.observation_spec.keys() else 1
    c = cfg.collector
    # a memory-mapped buffer (replay_buffer_storage=memmap) lives on disk: the page cache holds what it can
    in_memory = getattr(cfg, "replay_buffer_storage", "memory") == "memory"
    parts: list[tuple[str, str, int]] = [
        ("replay_buffer_capacity", f"the replay buffer ({cfg.replay_buffer_capacity} transitions of "
         f"{_human(per_transition)})", cfg.replay_buffer_capacity * per_transition if in_memory else 0),
        ("batch_size", f"the sampled batches ({cfg.batch_size} transitions)", 2 * cfg.batch_size * per_transition),
        ("collector.frames_per_batch", f"the collected blocks ({c.frames_per_batch} env steps per block)",
         (c.workers + 1) * c.frames_per_batch * per_block_transition),
    ]
    if c.workers > 1 or not c.sync:
        parts.append(("collector.workers", f"{c.workers} collector processes", c.workers * _WORKER_PROCESS_BYTES))
    for key, sizes in networks.items():
        widths = [obs_dim + action_dim, *sizes, max(2 * action_dim, 1)]
        parameters = _mlp_parameters(widths)
        parts.append((key, f"the networks of {key}={sizes} ({parameters} parameters, with gradients, "
                      "optimiser moments and target copies)", parameters * 4 * _COPIES_PER_PARAMETER))
    total = sum(b for _, _, b in parts)
    if total <= available:
        return
    key, what, need = max(parts, key=lambda p: p[2])
    where = "this machine" if device.type == "cpu" else str(device)
    if key == "replay_buffer_capacity":
        fits = max(0, available - (total - need)) // per_transition
        expected = f"expected replay_buffer_storage=memmap (on disk), or replay_buffer_capacity at most about {fits}"
    else:
        expected = "expected smaller values"
    if key in networks:
        value = networks[key]
    else:
        value = getattr(cfg, key) if "." not in key else getattr(cfg.collector, key.split(".")[1])
    raise InputError(f"{key}={value}: {what} would take {_human(need)}, the run {_human(total)} in all; {where} has "
                     f"{_human(available)} available; {expected}")
