"""Evaluation with the deterministic policy: TF-Agents' AverageReturn and AverageEpisodeLength."""

from __future__ import annotations

import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type

__all__ = ["evaluate"]


@torch.no_grad()
def evaluate(env, policy, num_episodes: int, max_steps: int = 100_000, interrupt=None) -> dict:
    """Run ``num_episodes`` full episodes of ``policy`` (deterministic) on ``env``.

    ``interrupt``, if given, is called before every env step; an exception it raises ends the
    evaluation (the training loop uses it to stop at Ctrl-C in the middle of a long evaluation).

    Returns ``average_return``, ``average_episode_length`` and the per-episode ``returns``.
    Episodes end when the env says done (terminated or truncated by its time limit).
    """
    returns, lengths = [], []
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        for _ in range(num_episodes):
            rollout = env.rollout(max_steps, policy, break_when_any_done=True, auto_cast_to_device=True,
                                  callback=None if interrupt is None else lambda *_: interrupt())
            returns.append(float(rollout["next", "reward"].sum()))
            lengths.append(int(rollout.shape[-1]))
    return {
        "average_return": sum(returns) / len(returns),
        "average_episode_length": sum(lengths) / len(lengths),
        "returns": returns,
    }
