"""Networks, policies, losses and optimisers as TorchRL parts, usable in any TorchRL project.

This package never imports ``rlpipe.pipelines``: everything here is a plain TorchRL/torch object.

    actors, critics, qnetworks   policies and value networks (TensorDict modules); critics also holds CrossQ's
                      batch-renormalised critic and a faster BatchRenorm1d
    plain_policy      any TensorDict policy as a plain module on observation tensors (what torch.export takes)
    td3_loss          TorchRL's TD3Loss with TD3's six ingredients as switches, and one TD3 step
    encoders, frames, hindsight, normalization   images, frame-stacking replay, HER, running observation norms
    fast/             the parts that re-implement a TorchRL or torch part for speed, each the stock part's equal,
                      with their table and checks (``rlpipe.modules.fast``): the lean SAC, CrossQ and DQN losses,
                      LeanAdam, ForeachSoftUpdate, the replay sample, the epsilon-greedy policy on tensors,
                      collect policies as tensor functions, TorchRL MLPs on tensors
"""

from rlpipe.modules.actors import (
    TanhBoundedMLP,
    TanhNormalMode,
    make_deterministic_actor,
    make_exploration_policy,
    make_gaussian_actor,
    make_tanh_normal_actor,
)
from rlpipe.modules.critics import BatchRenorm1d, make_batchrenorm_critic, make_qvalue_critic
from rlpipe.modules.fast.exploration import EGreedyQPolicy, epsilon_greedy
from rlpipe.modules.fast.optim import LeanAdam, clip_gradient_norms
from rlpipe.modules.fast.target_updates import ForeachSoftUpdate, make_target_updater
from rlpipe.modules.qnetworks import make_qvalue_actor
from rlpipe.modules.td3_loss import TD3AblationLoss, td3_update

__all__ = [
    "BatchRenorm1d",
    "EGreedyQPolicy",
    "ForeachSoftUpdate",
    "LeanAdam",
    "TD3AblationLoss",
    "TanhBoundedMLP",
    "TanhNormalMode",
    "clip_gradient_norms",
    "epsilon_greedy",
    "make_deterministic_actor",
    "make_exploration_policy",
    "make_batchrenorm_critic",
    "make_gaussian_actor",
    "make_qvalue_actor",
    "make_qvalue_critic",
    "make_tanh_normal_actor",
    "make_target_updater",
    "td3_update",
]
