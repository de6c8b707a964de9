"""Any TensorDict policy as a plain module on observation tensors (what ``torch.export`` takes)."""

from __future__ import annotations

import numpy as np
import torch
from gymnasium import spaces
from gymnasium.wrappers.utils import rescale_box
from tensordict import TensorDict
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type

__all__ = ["TensorDictPolicy", "OnRescaledObservations"]


class TensorDictPolicy(nn.Module):
    """``observation [B, D] -> action``: ``policy`` called on a TensorDict holding the observation
    under ``observation_key``, deterministically (a stochastic policy gives its mode). ``observation_ndim``:
    the dimensions of one observation (3 for an image ``[C, H, W]``)."""

    def __init__(self, policy: nn.Module, observation_key: str = "observation", action_key: str = "action",
                 observation_ndim: int = 1):
        super().__init__()
        self.policy = policy
        self.observation_key = observation_key
        self.action_key = action_key
        self.observation_ndim = observation_ndim

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        td = TensorDict({self.observation_key: observation},
                        batch_size=observation.shape[:observation.ndim - self.observation_ndim])
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            return self.policy(td).get(self.action_key)


class OnRescaledObservations(nn.Module):
    """``observation [B, D] -> module(observation mapped linearly from [low, high] to [-1, 1])``.

    The map is gymnasium's own (``rescale_box``, what ``RescaleObservation(env, -1, 1)`` applies), read
    off as its intercept (the image of 0) and gradient (of 1, less the intercept), so a policy trained on
    rescaled observations (``rescale_observations=true``) is exported to take the env's own.
    """

    def __init__(self, module: nn.Module, low: np.ndarray, high: np.ndarray):
        super().__init__()
        box = spaces.Box(np.asarray(low, np.float32), np.asarray(high, np.float32), dtype=np.float32)
        to_unit = rescale_box(box, np.float32(-1.0), np.float32(1.0))[1]
        intercept = to_unit(np.zeros(box.shape, np.float32))
        gradient = to_unit(np.ones(box.shape, np.float32)) - intercept
        self.module = module
        self.register_buffer("gradient", torch.from_numpy(gradient))
        self.register_buffer("intercept", torch.from_numpy(intercept))

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return self.module(self.gradient * observation + self.intercept)
