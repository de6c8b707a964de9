"""Q-networks for discrete actions, as TorchRL ``QValueActor``s.

``make_qvalue_actor`` is TF-Agents' ``QNetwork`` (fully connected layers, one output per action)
wrapped so that it writes ``action_value``, ``chosen_action_value`` and a greedy ``action``:
exactly what TorchRL's ``DQNLoss`` and collectors expect.
"""

from __future__ import annotations

from collections.abc import Sequence

from torch import nn
from torchrl.modules import MLP, QValueActor

__all__ = ["make_qvalue_actor"]


def make_qvalue_actor(
    observation_dim: int,
    action_spec,
    hidden_sizes: Sequence[int] = (100,),
    activation: type[nn.Module] = nn.ReLU,
    *,
    observation_key: str = "observation",
    encoder: nn.Module | None = None,
) -> QValueActor:
    """Greedy Q-value policy over an MLP: ``observation`` (or ``observation_key``) -> ``action`` (an integer index).

    ``encoder``: a network in front of the MLP (an image's, ``modules.encoders``), whose ``out_features``
    is ``observation_dim``."""
    net = MLP(
        in_features=observation_dim,
        out_features=action_spec.space.n,
        num_cells=list(hidden_sizes),
        activation_class=activation,
    )
    if encoder is not None:
        net = nn.Sequential(encoder, net)
    # The action encoding (integer index or one-hot) is the spec's own.
    return QValueActor(net, in_keys=[observation_key], spec=action_spec)
