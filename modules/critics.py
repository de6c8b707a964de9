"""Critics for continuous control, as plain TorchRL modules."""

from __future__ import annotations

from collections.abc import Sequence

from torch import nn
from torchrl.modules import MLP, ValueOperator

__all__ = ["make_qvalue_critic"]


def make_qvalue_critic(
    observation_dim: int,
    action_dim: int,
    hidden_sizes: Sequence[int] = (256,),
    *,
    observation_key: str = "observation",
) -> ValueOperator:
    """Q(s, a): an MLP over ``cat(observation, action)`` writing ``"state_action_value"``.

    One network: TorchRL's ``TD3Loss``/``SACLoss`` make the twin critics themselves
    (``num_qvalue_nets=2``), with freshly drawn weights for each copy.

    Args:
        observation_dim: length of the flat observation vector.
        action_dim: length of the action vector.
        hidden_sizes: hidden layer widths (ReLU); ``(256,)`` is the TD3 tutorial's critic.
        observation_key: the TensorDict key of the observation.
    """
    net = MLP(
        in_features=observation_dim + action_dim,
        out_features=1,
        num_cells=list(hidden_sizes),
        activation_class=nn.ReLU,
        # In place: saves an allocation per layer; Linear's backward never needs its output.
        activation_kwargs={"inplace": True},
    )
    # TorchRL's MLP concatenates several inputs along the last dim, so it takes (obs, action).
    return ValueOperator(net, in_keys=[observation_key, "action"])
