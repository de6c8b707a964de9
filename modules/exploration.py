"""Exploration wrappers: the collect policy is the evaluation policy plus one of these.

They are TorchRL's own modules; the factories only fix the tutorials' conventions.
"""

from __future__ import annotations

from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torchrl.modules import EGreedyModule

__all__ = ["epsilon_greedy"]


def epsilon_greedy(
    policy: TensorDictModuleBase,
    action_spec,
    epsilon: float = 0.1,
    epsilon_end: float | None = None,
    annealing_steps: int = 1,
) -> TensorDictSequential:
    """``policy`` followed by TorchRL's ``EGreedyModule``.

    With ``epsilon_end=None`` epsilon stays at ``epsilon`` (TF-Agents' ``DqnAgent`` default of 0.1);
    otherwise it decays linearly to ``epsilon_end`` over ``annealing_steps`` calls of ``.step()``.
    The greedy (evaluation) policy is ``policy`` itself, or this one under
    ``ExplorationType.DETERMINISTIC``.
    """
    greedy = EGreedyModule(
        action_spec,
        eps_init=epsilon,
        eps_end=epsilon if epsilon_end is None else epsilon_end,
        annealing_num_steps=annealing_steps,
    )
    return TensorDictSequential(policy, greedy)
