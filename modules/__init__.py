"""Networks and policies as TensorDict modules, usable in any TorchRL project."""

from rlpipe.modules.actors import (
    TanhBoundedMLP,
    TanhNormalMode,
    make_deterministic_actor,
    make_exploration_policy,
    make_gaussian_actor,
    make_tanh_normal_actor,
)
from rlpipe.modules.critics import make_qvalue_critic
from rlpipe.modules.exploration import epsilon_greedy
from rlpipe.modules.qnetworks import make_qvalue_actor

__all__ = [
    "TanhBoundedMLP",
    "TanhNormalMode",
    "epsilon_greedy",
    "make_deterministic_actor",
    "make_exploration_policy",
    "make_gaussian_actor",
    "make_qvalue_actor",
    "make_qvalue_critic",
    "make_tanh_normal_actor",
]
