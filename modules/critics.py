"""Critics for continuous control, as plain TorchRL modules."""

from __future__ import annotations

from collections.abc import Sequence

from torch import nn
from torchrl.modules import MLP, ValueOperator

__all__ = ["INITIALIZERS", "make_qvalue_critic"]

INITIALIZERS = ("torch", "glorot_uniform")
"""weight initialisations of the critics: torch's default (``nn.Linear``'s), or TF-Agents' tutorial choice"""


def make_qvalue_critic(
    observation_dim: int,
    action_dim: int,
    hidden_sizes: Sequence[int] = (256,),
    *,
    observation_key: str = "observation",
    init: str = "torch",
) -> ValueOperator:
    """Q(s, a): an MLP over ``cat(observation, action)`` writing ``"state_action_value"``.

    One network: TorchRL's ``TD3Loss``/``SACLoss`` make the twin critics themselves
    (``num_qvalue_nets=2``), with freshly drawn weights for each copy.

    Args:
        observation_dim: length of the flat observation vector.
        action_dim: length of the action vector.
        hidden_sizes: hidden layer widths (ReLU); ``(256,)`` is the TD3 tutorial's critic.
        observation_key: the TensorDict key of the observation.
        init: ``"torch"`` (``nn.Linear``'s default) or ``"glorot_uniform"``: every layer's weights
            Glorot-uniform and its biases zero, as Keras' Dense layers with
            ``kernel_initializer='glorot_uniform'`` (the SAC actor-learner tutorial's critic,
            ``last_kernel_initializer`` included). TorchRL's twin copies are redrawn uniformly
            within the first copy's range, so they stay Glorot-uniform.
    """
    if init not in INITIALIZERS:
        raise ValueError(f"init={init!r}: expected one of {', '.join(INITIALIZERS)}")
    net = MLP(
        in_features=observation_dim + action_dim,
        out_features=1,
        num_cells=list(hidden_sizes),
        activation_class=nn.ReLU,
        # In place: saves an allocation per layer; Linear's backward never needs its output.
        activation_kwargs={"inplace": True},
    )
    if init == "glorot_uniform":
        for layer in net.modules():
            if isinstance(layer, nn.Linear):
                nn.init.xavier_uniform_(layer.weight)
                nn.init.zeros_(layer.bias)
    # TorchRL's MLP concatenates several inputs along the last dim, so it takes (obs, action).
    return ValueOperator(net, in_keys=[observation_key, "action"])
