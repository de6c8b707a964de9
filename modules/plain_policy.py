"""Any TensorDict policy as a plain module on observation tensors (what ``torch.export`` takes)."""

from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDict
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type

__all__ = ["TensorDictPolicy", "OnRescaledObservations"]


class TensorDictPolicy(nn.Module):
    """``observation [B, D] -> action``: ``policy`` called on a TensorDict holding the observation
    under ``observation_key``, deterministically (a stochastic policy gives its mode)."""

    def __init__(self, policy: nn.Module, observation_key: str = "observation", action_key: str = "action"):
        super().__init__()
        self.policy = policy
        self.observation_key = observation_key
        self.action_key = action_key

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        td = TensorDict({self.observation_key: observation}, batch_size=observation.shape[:-1])
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            return self.policy(td).get(self.action_key)


class OnRescaledObservations(nn.Module):
    """``observation [B, D] -> module(observation mapped linearly from [low, high] to [-1, 1])``.

    The map is gymnasium's ``RescaleObservation(env, -1, 1)``, with its float32 gradient and intercept
    computed as it computes them, so a policy trained on rescaled observations (``rescale_observations=true``)
    is exported to take the env's own.
    """

    def __init__(self, module: nn.Module, low: np.ndarray, high: np.ndarray):
        super().__init__()
        low, high = np.asarray(low, np.float32), np.asarray(high, np.float32)
        wide = np.longdouble  # gymnasium's high - low is float128 where numpy has it
        gradient = (np.full(low.shape, 2.0, np.float32) / (high.astype(wide) - low.astype(wide))).astype(np.float32)
        intercept = gradient * -low + np.full(low.shape, -1.0, np.float32)
        self.module = module
        self.register_buffer("gradient", torch.from_numpy(gradient))
        self.register_buffer("intercept", torch.from_numpy(intercept.astype(np.float32)))

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return self.module(self.gradient * observation + self.intercept)
