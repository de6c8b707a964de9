"""The one place that picks a collector backend from ``collector.backend`` (no other module asks which
backend a run has: everything else talks to ``backend.CollectorBackend``)."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn
from torchrl.envs import EnvBase

from rlpipe.pipelines.config import TrainConfig
from rlpipe.pipelines.workers.backend import CollectorBackend

__all__ = ["backend_class", "make_backend"]


def _local() -> type[CollectorBackend]:
    from rlpipe.pipelines.workers.local import LocalBackend

    return LocalBackend


def _ray() -> type[CollectorBackend]:
    from rlpipe.pipelines.workers.ray import RayBackend  # Ray is an extra: imported only when asked for

    return RayBackend


_BACKENDS: dict[str, Callable[[], type[CollectorBackend]]] = {"local": _local, "ray": _ray}
"""``collector.backend`` -> the backend class (config validation has checked the name)"""


def backend_class(config: TrainConfig) -> type[CollectorBackend]:
    """The ``CollectorBackend`` subclass ``config.collector.backend`` names."""
    return _BACKENDS[config.collector.backend]()


def make_backend(config: TrainConfig, *, policy: nn.Module, env_fn: Callable[[], EnvBase] | None,
                 env: EnvBase | None = None, device: torch.device | str = "cpu",
                 learner_version: Callable[[], int] = lambda: 0) -> CollectorBackend:
    """The backend ``config.collector.backend`` names, not started yet: ``policy`` collects, on envs made
    by ``env_fn`` (``env``: the learner's own, stepped in its process with one in-process worker)."""
    return backend_class(config)(config, policy=policy, env_fn=env_fn, env=env, device=device,
                                 learner_version=learner_version)
