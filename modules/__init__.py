"""Networks, policies, losses and optimisers as TorchRL parts, usable in any TorchRL project.

This package never imports ``rlpipe.pipelines``: everything here is a plain TorchRL/torch object.

    actors, critics, qnetworks, exploration   policies and value networks (TensorDict modules); critics
                      also holds CrossQ's batch-renormalised critic and a faster BatchRenorm1d
    plain_policy      any TensorDict policy as a plain module on observation tensors (what torch.export takes)
    tensor_policy     a collect policy as a function on one observation tensor (a collector's per-step call)
    td3_loss          TorchRL's TD3Loss with TD3's six ingredients as switches, and one TD3 step
    sac_loss          TorchRL's SACLoss terms on plain tensors (LeanSACLoss), importance weights included
    crossq_loss       TorchRL's CrossQLoss on plain tensors (LeanCrossQLoss), batch-renorm statistics included
    dqn_loss          TorchRL's DQNLoss on plain tensors (LeanDQNLoss)
    target_updates    SoftUpdate with a one-kernel step, for any loss with target networks
    optim             LeanAdam: fused Adam without Optimizer.step's per-call Python;
                      clip_gradient_norms: TF-Agents' per-tensor gradient clipping
    tensor_nets       TorchRL MLPs run on plain tensors (one copy, or stacked twin critics at once)
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
from rlpipe.modules.exploration import EGreedyQPolicy, epsilon_greedy
from rlpipe.modules.optim import LeanAdam, clip_gradient_norms
from rlpipe.modules.qnetworks import make_qvalue_actor
from rlpipe.modules.target_updates import ForeachSoftUpdate, make_target_updater
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
