"""Running normalisation of vector observations, as SB3's ``VecNormalize(norm_obs=True)``: each entry minus its
running mean, over its running standard deviation, clipped to [-10, 10].

``RunningObservationNorm`` is a module the networks put in front of their heads (as an image's encoder), so
the policy that acts (in collector processes, in evaluations, exported) carries the statistics with it, and a
checkpoint holds them with the networks. Only the learner moves them (``update``, on each collected block's
observations); an evaluation or an exported policy reads them frozen.

Why not TorchRL's ``VecNorm``: it is an env transform, so its statistics live with the env copies (shared
memory between processes on one machine, none across Ray actors) rather than with the policy, an exported
policy would not carry them, and the collectors that step gymnasium directly (``GymCollector``) run no
TorchRL transform. TorchRL's losses copy a critic's buffers into their own stacked parameters (one per twin
critic, and the target copies): ``mirrors`` lists those copies, and ``update`` writes the statistics into
each, so every network reads the same ones.
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["RunningObservationNorm"]

BUFFERS = ("observation_mean", "observation_var", "observation_count")


class RunningObservationNorm(nn.Module):
    """``clamp((x - mean) / sqrt(var + epsilon), -clip, clip)`` over the last dimension, of ``size`` entries."""

    def __init__(self, size: int, clip: float = 10.0, epsilon: float = 1e-8):
        super().__init__()
        self.register_buffer("observation_mean", torch.zeros(size))
        self.register_buffer("observation_var", torch.ones(size))
        self.register_buffer("observation_count", torch.tensor(1e-4))  # SB3's RunningMeanStd starts so
        self.out_features, self.clip, self.epsilon = size, clip, epsilon
        self.mirrors: list[tuple[str, torch.Tensor]] = []

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        scaled = (observation - self.observation_mean) * torch.rsqrt(self.observation_var + self.epsilon)
        return scaled.clamp(-self.clip, self.clip)

    @torch.no_grad()
    def update(self, observations: torch.Tensor) -> None:
        """Merge a batch ``[..., size]`` into the running statistics (Chan et al.'s parallel update, as
        ``RunningMeanStd``), then write them into every mirror."""
        x = observations.reshape(-1, self.out_features).to(self.observation_mean)
        count = x.shape[0]
        if count == 0:
            return
        mean, var = x.mean(0), x.var(0, unbiased=False)
        total = self.observation_count + count
        delta = mean - self.observation_mean
        m2 = self.observation_var * self.observation_count + var * count + delta.square() * self.observation_count * count / total
        self.observation_mean += delta * count / total
        self.observation_var.copy_(m2 / total)
        self.observation_count.copy_(total)
        for name, mirror in self.mirrors:
            mirror.copy_(getattr(self, name).expand_as(mirror))

    def find_mirrors(self, module: nn.Module) -> None:
        """Remember every buffer of ``module`` (a loss) that is a copy of one of these statistics."""
        own = {id(getattr(self, name)) for name in BUFFERS}
        self.mirrors = [(name, buffer) for key, buffer in module.named_buffers()
                        for name in BUFFERS if key.endswith(name) and id(buffer) not in own]
