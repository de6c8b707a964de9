"""What decides a run's float arithmetic besides its config and seed: the learner's threads (the summation
order of every matrix product), its device, the float paths torch takes on this CPU, and the versions of the
libraries that compute the updates and the envs.

A run records them when it starts and in every checkpoint; a resume where any differs says so in one line
and marks the run not exact (``summary.json``: ``"exact": false`` and why), as does a resume that changes a
config key the arithmetic depends on. Only what a run can equal an uninterrupted one under keeps
``"exact": true``.
"""

from __future__ import annotations

from importlib import metadata
from typing import Any

import torch

from rlpipe.pipelines.config import TrainConfig

__all__ = ["NOT_ARITHMETIC", "arithmetic_record", "changed_arithmetic"]

_LIBRARIES = ("torch", "torchrl", "tensordict", "numpy", "gymnasium", "mujoco", "pybullet")

NOT_ARITHMETIC = frozenset({
    "num_iterations", "log_interval", "checkpoint_interval", "checkpoint_keep", "policy_save_interval", "policy_keep",
    "video", "live_report", "eval_timeout", "collector.timeout", "collector.max_restarts", "time_budget", "plateau",
    "plateau_evaluations", "plateau_min_iterations", "keep_best",
})
"""config keys that say how long a run goes on and how it is recorded or supervised, never what it computes:
a resume may change them and stay exact (checkpoints and log rows are written at safe points)"""


def arithmetic_record(cfg: TrainConfig) -> dict[str, Any]:
    """The facts besides ``cfg`` and its seed that decide the run's floats, as the run will compute them here."""
    record: dict[str, Any] = {
        "threads": cfg.num_threads if cfg.num_threads > 0 else torch.get_num_threads(),
        "device": _device_name(cfg.device),
        "cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "default_dtype": str(torch.get_default_dtype()).removeprefix("torch."),
        "float32_matmul_precision": torch.get_float32_matmul_precision(),
        "deterministic_algorithms": torch.are_deterministic_algorithms_enabled(),
    }
    for name in _LIBRARIES:
        try:
            record[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            record[name] = None
    return record


def changed_arithmetic(saved: dict[str, Any] | None, now: dict[str, Any]) -> list[str]:
    """What differs between the record a checkpoint saved and ``now``'s, as ``'threads 1 -> 2'``; a checkpoint
    that holds no record: ``['its arithmetic record (the checkpoint holds none)']``."""
    if saved is None:
        return ["its arithmetic record (the checkpoint holds none)"]
    return [f"{key} {saved.get(key)} -> {value}" for key, value in now.items() if saved.get(key) != value]


def _device_name(device: str) -> str:
    """``device`` with the GPU's model where it is one (two GPU models compute the same kernels differently)."""
    d = torch.device(device)
    if d.type == "cuda" and torch.cuda.is_available():
        return f"{device} ({torch.cuda.get_device_name(d)})"
    return str(device)
