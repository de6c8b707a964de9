"""DQN's loss on tensors: TorchRL's ``DQNLoss`` with the same numbers at a fraction of the overhead.

``LeanDQNLoss`` subclasses TorchRL's ``DQNLoss`` and keeps its parameters, target parameters,
keys, value estimator and checkpoint keys. For a ``QValueActor`` over a TorchRL ``MLP``
(``make_qvalue_actor``) with categorical actions, it runs the Q-network layer by layer on the
loss's parameter tensors instead of through TensorDicts: the stock loss costs ~1.8 ms per update
here (batch 64-128, a 100-unit network) for ~0.01 ms of matmuls. The arithmetic is the stock
loss's: Q(s, a) against ``r + gamma * (1 - terminated) * max_a' Q_target(s', a')`` (Double DQN:
the online network picks ``a'``), the same distance and reduction; ``tests/test_dqn_loss.py``
checks values and gradients against ``DQNLoss``. Anything else goes through ``DQNLoss`` unchanged.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.modules import QValueActor
from torchrl.objectives import DQNLoss
from torchrl.objectives.utils import distance_loss
from torchrl.objectives.value import TD0Estimator

from rlpipe.modules.fast.tensor_nets import (
    bootstrap_discount,
    cached_flat_params,
    is_plain_module,
    mlp_layers,
    run_mlp,
    transition_tensors,
)

__all__ = ["LeanDQNLoss"]

# QValueActor -> ("module", "0", "module", ...): the MLP's own parameter names.
_PREFIX = 3


class LeanDQNLoss(DQNLoss):
    """TorchRL's ``DQNLoss`` computed on tensors when the Q-network allows it (same arguments)."""

    def __init__(self, value_network, *args, **kwargs):
        super().__init__(value_network, *args, **kwargs)
        net = self.value_network.module[0] if isinstance(self.value_network, QValueActor) else None
        plain = net is not None and is_plain_module(net) and len(net.in_keys) == 1
        self._layers = mlp_layers(net.module) if plain else None
        self._observation_key = net.in_keys[0] if plain else None
        self.value_estimator  # noqa: B018  (built now, as the other losses here do)

    @property
    def lean(self) -> bool:
        """True when ``forward`` runs on tensors."""
        return (self._layers is not None and self.action_space == "categorical" and self.reduction == "mean"
                and type(self.value_estimator) is TD0Estimator)

    @property
    def lean_call(self) -> bool:
        """True when ``lean_loss`` may stand for the module call itself: ``lean``, and no forward hook to run."""
        return self.lean and not (self._forward_hooks or self._forward_pre_hooks)

    def _q(self, params_name: str, observation: torch.Tensor) -> torch.Tensor:
        return run_mlp(self._layers, cached_flat_params(self, params_name, _PREFIX), observation)

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        if not self.lean:
            return super().forward(tensordict)
        return TensorDict(loss=self.lean_loss(tensordict))

    def lean_loss(self, tensordict: TensorDictBase) -> torch.Tensor:
        """``forward(tensordict)["loss"]`` without the TensorDict around it (only where ``lean``): what
        rlpipe's DQN update calls, ~15 us less a call than the module call and the TensorDict."""
        keys = self.tensor_keys
        observation, action, next_obs, reward, terminated = transition_tensors(tensordict, self._observation_key, keys)
        q = self._q("value_network_params", observation)
        if action.ndim != q.ndim:
            action = action.unsqueeze(-1)
        predicted = q.gather(-1, action).squeeze(-1)
        with torch.no_grad():
            next_q = self._q("target_value_network_params", next_obs)
            if self.double_dqn:
                next_action = self._q("value_network_params", next_obs).argmax(-1, keepdim=True)
                next_value = next_q.gather(-1, next_action)
            else:
                next_value = next_q.max(-1, keepdim=True).values
            not_terminated = (~terminated).int()
            gamma = bootstrap_discount(self, tensordict, reward)  # gamma ** steps_to_next_obs for n-step transitions
            target = (reward + gamma * not_terminated * next_value).squeeze(-1)
            tensordict.set(keys.priority, (predicted - target).pow(2).unsqueeze(-1), inplace=True)
        loss = distance_loss(predicted, target, self.loss_function)
        weights = None
        if self.use_prioritized_weights in (True, "auto") and keys.priority_weight in tensordict.keys():
            weights = tensordict.get(keys.priority_weight)
        return self._reduce_loss(loss, tensordict=tensordict, weights=weights)
