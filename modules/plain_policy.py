"""Any TensorDict policy as a plain module on observation tensors (what ``torch.export`` takes)."""

from __future__ import annotations

import torch
from tensordict import TensorDict
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type

__all__ = ["TensorDictPolicy"]


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
