"""n-step returns: each collected transition rewritten to look n env steps ahead before it is stored.

A stored transition ``(s_t, a_t, r, s')`` becomes ``(s_t, a_t, r_t + gamma r_{t+1} + ... + gamma^(k-1) r_{t+k-1},
s_{t+k})`` with ``k = min(n, steps to the end of its episode or of its collected block)``, the ``("next", ...)``
entries (done, terminated and truncated flags included) those of step ``t+k-1``, and ``steps_to_next_obs = k``.
A loss bootstraps with ``gamma ** steps_to_next_obs``: TorchRL's ``TD0Estimator`` reads that key itself (so a
stock ``SACLoss``, ``TD3Loss`` or ``DQNLoss`` learns from these transitions unchanged), and rlpipe's lean losses
read it through ``modules.tensor_nets.bootstrap_discount``.

Why not TorchRL's ``MultiStepTransform`` (or the ``MultiStep`` postproc): it gathers every ``("next", ...)``
entry to step ``t+k-1`` except the done keys, which stay step ``t``'s. A window that ends in a termination
then keeps ``terminated=False`` and bootstraps from the terminal observation (TorchRL 0.14.1: a block of 8
steps terminating at its 6th, n=3, gives ``terminated`` False for all five rows it returns, two of whose next
observations are the terminal one). Its windows also run across the blocks it is given, one stream of them:
blocks of several collector processes arrive interleaved, so it would join steps of different envs.

Windows here stay inside one collected block and one trajectory (``("collector", "traj_ids")`` where the
block has them, and the done flags; the loop hands over each block flattened, ``[envs * T]`` with each env's steps
in order, and the ids keep the envs apart): nothing is carried from block to block, so a resumed run stores what an
uninterrupted one would. The last ``n-1`` steps of a block look fewer steps ahead (``k < n``); with blocks of
``collector.frames_per_batch`` steps that is ``(n-1)/frames_per_batch`` of the transitions (4% at n=3 and 50).
As with every uncorrected n-step return, the rewards after the first come from the policy that collected them,
not the one being learned: a bias that grows with ``n`` and the replay's age, traded for faster propagation of
reward (why locomotion agents use n=3 to 5).
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

__all__ = ["STEPS_KEY", "n_step_transitions"]

STEPS_KEY = "steps_to_next_obs"
"""TorchRL's key for a transition's look-ahead (``TD0Estimator.tensor_keys.steps_to_next_obs``)"""

_TRAJ_IDS = ("collector", "traj_ids")


def n_step_transitions(batch: TensorDictBase, n: int, gamma: float) -> TensorDictBase:
    """``batch`` (a collected block, time its last dimension) with ``n``-step transitions (module docstring);
    a new TensorDict, ``batch`` itself is left as it is. ``n == 1`` returns ``batch``."""
    if n == 1:
        return batch
    shape = batch.batch_size
    steps_t = shape[-1]
    nxt = batch.get("next")
    reward = nxt.get("reward")
    rewards = reward.reshape(shape)  # one reward per step (TorchRL's [*batch, 1])
    done = nxt.get("done").reshape(shape)
    ids = batch.get(_TRAJ_IDS, None)
    ids = ids.reshape(shape) if ids is not None and ids.numel() == done.numel() else None
    t = torch.arange(steps_t, device=done.device)
    total = rewards.clone()
    last = t.expand(shape).clone()  # the step whose ("next", ...) entries end each window
    open_ = ~done  # the window can take the step after
    for k in range(1, n):
        ahead = (t + k).clamp_max(steps_t - 1)
        take = open_ & (t + k < steps_t)
        if ids is not None:
            take = take & (ids[..., ahead] == ids)
        total = total + (gamma ** k) * take.to(rewards.dtype) * rewards[..., ahead]
        last = torch.where(take, t + k, last)
        open_ = take & ~done[..., ahead]
    out = batch.clone(False)
    ahead_next = nxt.gather(len(shape) - 1, last) if len(shape) > 1 else nxt[last]
    ahead_next.set("reward", total.reshape(reward.shape))
    out.set("next", ahead_next)
    out.set(STEPS_KEY, last - t + 1)
    return out
