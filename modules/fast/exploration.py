"""Exploration wrappers: the collect policy is the evaluation policy plus one of these.

They are TorchRL's own modules; the factories only fix the tutorials' conventions.
"""

from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torchrl.data import Categorical, Composite
from torchrl.envs.utils import ExplorationType, exploration_type
from torchrl.modules import EGreedyModule, QValueActor, QValueModule

from rlpipe.modules.fast.tensor_nets import is_plain_module, module_forward

__all__ = ["EGreedyQPolicy", "anneal_epsilon", "epsilon_greedy"]


def epsilon_greedy(
    policy: TensorDictModuleBase,
    action_spec,
    epsilon: float = 0.1,
    epsilon_end: float | None = None,
    annealing_steps: int = 1,
    fast: bool = True,
) -> TensorDictSequential:
    """``policy`` followed by TorchRL's ``EGreedyModule``.

    With ``epsilon_end=None`` epsilon stays at ``epsilon`` (TF-Agents' ``DqnAgent`` default of 0.1);
    otherwise it decays linearly to ``epsilon_end`` over ``annealing_steps`` calls of ``.step()``.
    The greedy (evaluation) policy is ``policy`` itself, or this one under
    ``ExplorationType.DETERMINISTIC``. The result is an ``EGreedyQPolicy``: a
    ``TensorDictSequential(policy, greedy)`` that runs on tensors when ``policy`` allows it (``fast=False``: the
    stock ``TensorDictSequential``, the same children and state dict).
    """
    greedy = EGreedyModule(
        action_spec,
        eps_init=epsilon,
        eps_end=epsilon if epsilon_end is None else epsilon_end,
        annealing_num_steps=annealing_steps,
    )
    return (EGreedyQPolicy if fast else TensorDictSequential)(policy, greedy)


class EGreedyQPolicy(TensorDictSequential):
    """``TensorDictSequential(QValueActor, EGreedyModule)`` whose ``forward`` runs on tensors.

    Same children, state dict, keys and numbers as the stock sequence; what it removes is the
    per-call work around them. A collector calls the collect policy once per env step (DQN's
    tutorial: one env step per update), and the stock sequence (the MLP through a
    ``TensorDictModule``, ``QValueModule``'s dispatch and spec checks, ``EGreedyModule``'s spec
    expansion) costs ~0.3 ms per call on this 2-core CPU for a few microseconds of arithmetic: 18% of
    an iteration of the ``dqn`` preset (BENCHMARKS.md, "Collection: env steps per second"). TorchRL has no
    tensor-level epsilon-greedy policy, hence this class.

    The tensor path is taken when the actor is a ``QValueActor`` over a plain module (the Q-network
    on the observation tensor) with a categorical (integer index) action and no action mask; anything else goes through
    ``TensorDictSequential.forward`` unchanged. It writes what the stock sequence writes
    (``action``, ``action_value``, ``chosen_action_value``) and draws its random numbers in the
    same order (``torch.rand`` for the coin, then ``torch.randint`` for the random action, as
    ``EGreedyModule`` and ``Categorical.rand`` do), so with the same generator state both give the
    same actions (``tests/test_dqn.py`` checks it).
    """

    def _lean_parts(self):
        """``(Q-network module, observation key, number of actions, greedy)`` or None; cached."""
        cache = self.__dict__.setdefault("_cache_lean", {})
        if "parts" not in cache:
            cache["parts"] = self._find_lean_parts()
        return cache["parts"]

    def _find_lean_parts(self):
        if len(self.module) != 2:
            return None
        actor, greedy = self.module
        if type(greedy) is not EGreedyModule or greedy.action_mask_key is not None or greedy.action_key != "action":
            return None
        if not isinstance(actor, QValueActor) or len(actor.module) != 2:
            return None
        net, qvalue = actor.module
        if not (is_plain_module(net) and type(qvalue) is QValueModule) or len(net.in_keys) != 1:
            return None
        if (qvalue.action_space != "categorical" or qvalue.action_mask_key is not None
                or list(net.out_keys) != list(qvalue.in_keys)
                or list(qvalue.out_keys) != ["action", "action_value", "chosen_action_value"]):
            return None
        spec = greedy.spec
        spec = spec["action"] if isinstance(spec, Composite) else spec
        if (type(spec) is not Categorical or spec.mask is not None or spec.shape != torch.Size([])
                or spec.dtype != torch.int64):
            return None
        return module_forward(net.module), net.in_keys[0], int(spec.space.n), greedy

    def forward(self, tensordict: TensorDictBase, tensordict_out=None, **kwargs) -> TensorDictBase:
        parts = self._lean_parts() if tensordict_out is None and not kwargs else None
        if parts is None:
            return super().forward(tensordict, tensordict_out, **kwargs)
        action, values, chosen = self.act(tensordict.get(parts[1]), tensordict.shape)
        tensordict.set("chosen_action_value", chosen)
        tensordict.set("action", action)
        tensordict.set("action_value", values)
        return tensordict

    def act(self, observation: torch.Tensor, batch_shape: torch.Size) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(action, action_value, chosen_action_value)`` at ``observation`` (batch ``batch_shape``), as
        ``forward`` writes them; only where the tensor path applies (``_lean_parts()`` is not None)."""
        qnet, _, num_actions, greedy = self._lean_parts()
        values = qnet(observation)
        action = values.argmax(-1)  # QValueModule's categorical action
        # QValueModule's value of its (greedy) action, before EGreedyModule may replace the action
        chosen = values.gather(-1, action.unsqueeze(-1))
        if exploration_type() in (ExplorationType.RANDOM, None):
            # EGreedyModule.forward: a coin per env, then a uniform action from the spec
            eps = greedy.eps
            explore = torch.rand(batch_shape, device=eps.device) < eps
            random_action = torch.randint(0, num_actions, action.shape, device=action.device)
            action = torch.where(explore, random_action, action)
        return action, values, chosen


def anneal_epsilon(module: EGreedyModule, frames: int, fast: bool = True) -> None:
    """``module.step(frames)``: the same float32 values, computed on numpy scalars.

    TorchRL's ``EGreedyModule.step`` loops over the frames with four tensor ops each (~120 us for a
    block of 10 frames on this 2-core CPU: 6% of an iteration of DQN with CleanRL's settings). Here the
    same float32 arithmetic (``max(eps_end, eps - (eps_init - eps_end) / annealing_num_steps)`` per
    frame, each op rounded to float32 as torch rounds it) runs on numpy's float32 scalars and stops at
    the fixed point (epsilon at its end value). Anything but a float32 ``EGreedyModule`` on the CPU
    (or ``fast=False``) goes through ``module.step``.
    """
    eps = module.eps
    if (not fast or type(module).step is not EGreedyModule.step or eps.dtype != torch.float32 or eps.device.type != "cpu"
            or module.eps_end.dtype != torch.float32 or module.eps_init.dtype != torch.float32):
        module.step(frames)
        return
    end = np.float32(module.eps_end.item())
    delta = (np.float32(module.eps_init.item()) - end) / np.float32(module.annealing_num_steps)
    value = start = np.float32(eps.item())
    if np.isnan(value) or np.isnan(delta) or np.isnan(end):  # torch.maximum propagates NaN: the stock path
        module.step(frames)
        return
    for _ in range(frames):
        new = value - delta  # float32 - float32: float32
        new = end if not new > end else new  # torch.maximum(eps_end, new)
        if new == value:
            break
        value = new
    if value != start:
        eps.fill_(float(value))
