"""CrossQ's loss on tensors: TorchRL's ``CrossQLoss`` with the same numbers at a fraction of the overhead.

``LeanCrossQLoss`` subclasses TorchRL's ``CrossQLoss`` and keeps its parameters, buffers, keys,
temperature, value estimator and ``forward``; ``qvalue_loss`` and ``actor_loss`` (what the CrossQ
pipeline's update calls, and what ``forward`` calls) run on tensors when the networks allow it.
The stock loss copies, selects and concatenates TensorDicts around each network call and runs
the twin critics under ``vmap`` with their stacked parameters and batch statistics. Here

* the actor (a ``ProbabilisticActor`` over a plain module, e.g. ``make_tanh_normal_actor``) runs
  layer by layer on the loss's parameters and its TanhNormal is sampled in a few tensor ops, as
  ``LeanSACLoss`` does (``LeanTanhNormalActor``);
* critics built as ``make_batchrenorm_critic`` builds them (rlpipe's ``BatchRenorm1d``, ``Linear``
  and ``ReLU`` in a row over ``cat(observation, action)``) run for both critics at once: each
  ``Linear`` one batched matmul over the stacked parameters, each ``BatchRenorm1d`` the same
  arithmetic as its own training or eval forward on the stacked statistics, which it moves in place
  exactly as the vmapped modules do.

Measured on this 2-core CPU (one thread, the update on a fixed batch of 256, ``rlpipe bench floor``'s
way): see ``BENCHMARKS.md`` ("CrossQ against SAC, per update"). The random draws come in the stock
loss's order (the next action in ``qvalue_loss``, with ``Normal.sample``'s draw; the actor's in
``actor_loss``, reparameterised), so with the same generator state both return the same values,
gradients and statistics (``tests/test_crossq.py``). Anything else (another critic structure,
TorchRL's own ``BatchRenorm1d``, a value estimator other than TD0, critics whose in_keys are not
(observation, action)) goes through ``CrossQLoss`` unchanged.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.objectives import CrossQLoss
from torchrl.objectives.utils import distance_loss
from torchrl.objectives.value import TD0Estimator

from rlpipe.modules.critics import BatchRenorm1d, _Joined
from rlpipe.modules.fast.sac_loss import LeanTanhNormalActor
from rlpipe.modules.fast.tensor_nets import (
    bootstrap_discount,
    cached_detached_params,
    cached_flat_params,
    is_plain_module,
    transition_tensors,
)

__all__ = ["LeanCrossQLoss", "renorm_critic_layers"]


def renorm_critic_layers(qvalue_network) -> list[tuple[str, str, nn.Module]] | None:
    """``[(kind, name, module)]`` of a critic that is a plain TensorDictModule over a ``Sequential`` of
    rlpipe's ``BatchRenorm1d`` ("renorm"), ``nn.Linear`` ("linear") and ``nn.ReLU`` ("relu") whose
    forward joins its inputs along the last dim (``make_batchrenorm_critic``'s), ending in a Linear;
    None for anything else."""
    if not is_plain_module(qvalue_network):
        return None
    seq = qvalue_network.module
    if type(seq) is not _Joined or seq._forward_hooks or seq._forward_pre_hooks:
        return None
    layers = []
    for name, module in seq.named_children():
        if module._forward_hooks or module._forward_pre_hooks:
            return None
        if type(module) is BatchRenorm1d:
            layers.append(("renorm", name, module))
        elif type(module) is nn.Linear and module.bias is not None:
            layers.append(("linear", name, module))
        elif type(module) is nn.ReLU:
            layers.append(("relu", name, module))
        else:
            return None
    return layers if layers and layers[-1][0] == "linear" else None


class _RenormAffine(torch.autograd.Function):
    """``xhat * a + c`` with ``xhat = (x - mean(x)) / sqrt(var(x) + eps)`` over the last dim (batch norm's
    arithmetic with the batch statistics), its backward written out: five passes over ``x`` each way
    where autograd's of the same formula in elementwise ops takes ~12 (the mul/div/sub of the mean, the
    variance and the affine map were ~1 ms of a 3 ms CrossQ update at 64x64 here). ``x`` is
    ``[copies, features, rows]``, ``a`` and ``c`` ``[copies, features, 1]``; ``mean``/``inv_std`` come in."""

    @staticmethod
    def forward(ctx, x, mean, inv_std, a, c):
        xhat = (x - mean) * inv_std
        ctx.save_for_backward(xhat, inv_std, a)
        return torch.addcmul(c, xhat, a)

    @staticmethod
    def backward(ctx, grad):
        xhat, inv_std, a = ctx.saved_tensors
        sum_g = grad.sum(-1, keepdim=True)
        sum_gx = (grad * xhat).sum(-1, keepdim=True)
        n = grad.shape[-1]
        dx = None
        if ctx.needs_input_grad[0]:  # not for the critics' input layer (observations and actions)
            # d/dx of batch norm: inv_std * a * (g - mean(g) - xhat * mean(g * xhat))
            dx = torch.addcmul(grad - sum_g / n, xhat, sum_gx, value=-1.0 / n).mul_(inv_std * a)
        return dx, None, None, sum_gx, sum_g


def _renorm_train(norm: BatchRenorm1d, params: dict[str, torch.Tensor], name: str, x: torch.Tensor) -> torch.Tensor:
    """``BatchRenorm1d.forward`` in training mode for stacked critics: ``x`` is ``[copies, features, rows]``,
    the parameters and statistics ``[copies, features]`` (the count ``[copies]``), moved in place.

    ``weight * ((x - mean) / std * r + d) + bias`` is batch norm's ``xhat * a + c`` with ``a = weight * r``
    and ``c = bias + weight * d`` (r and d carry no gradient; weight and bias get theirs through a and c).
    """
    weight, bias = params[f"{name}.weight"].unsqueeze(-1), params[f"{name}.bias"].unsqueeze(-1)
    running_mean, running_var = params[f"{name}.running_mean"], params[f"{name}.running_var"]
    count = params[f"{name}.num_batches_tracked"]
    n = x.shape[-1]
    with torch.no_grad():
        b_mean = x.mean(-1, keepdim=True)
        b_var = (x - b_mean).square_().mean(-1, keepdim=True)
        b_std = (b_var + norm.eps).sqrt()
        running_std = (running_var + norm.eps).sqrt().unsqueeze(-1)
        r = (b_std / running_std).clamp(1 / norm.max_r, norm.max_r)
        d = ((b_mean - running_mean.unsqueeze(-1)) / running_std).clamp(-norm.max_d, norm.max_d)
        if norm.warmup_steps > 0:
            held = count.clamp(max=norm.warmup_steps)
            factor = held / norm.warmup_steps if norm.smooth else (held // norm.warmup_steps).to(r.dtype)
            factor = factor.view(-1, 1, 1)
            r = 1.0 + (r - 1.0) * factor
            d = d * factor
        running_var.add_(norm.momentum * (b_var.squeeze(-1) * (n / (n - 1)) - running_var))
        running_mean.add_(norm.momentum * (b_mean.squeeze(-1) - running_mean))
        count.copy_((count + 1).clamp(max=max(norm.warmup_steps, 1)))
    return _RenormAffine.apply(x, b_mean, b_std.reciprocal(), weight * r, bias + weight * d)


def _renorm_eval(norm: BatchRenorm1d, params: dict[str, torch.Tensor], name: str, x: torch.Tensor) -> torch.Tensor:
    """``BatchRenorm1d.forward`` in eval mode (TorchRL's arithmetic) for stacked critics, columns as above."""
    running_std = (params[f"{name}.running_var"] + norm.eps).sqrt().unsqueeze(-1)
    x = (x - params[f"{name}.running_mean"].unsqueeze(-1)) / running_std
    return params[f"{name}.weight"].unsqueeze(-1) * x + params[f"{name}.bias"].unsqueeze(-1)


class LeanCrossQLoss(LeanTanhNormalActor, CrossQLoss):
    """TorchRL's ``CrossQLoss`` whose critic and actor losses are computed on tensors when the networks
    allow it. Same arguments as ``CrossQLoss``; ``lean`` says whether the fast path is taken."""

    def __init__(self, actor_network, qvalue_network, *args, **kwargs):
        super().__init__(actor_network, qvalue_network, *args, **kwargs)
        self._actor_parts = self._lean_actor()
        self._critic_layers = renorm_critic_layers(self.qvalue_network)
        self.value_estimator  # noqa: B018 - built now (TD0, the loss's gamma), as LeanSACLoss does

    @property
    def lean(self) -> bool:
        """True when the losses run on tensors (plain actor, ``make_batchrenorm_critic`` critics, TD0)."""
        return (
            self._actor_parts is not None
            and self._critic_layers is not None
            and type(self.value_estimator) is TD0Estimator
            and list(self.qvalue_network.in_keys) == [self._actor_parts[3], self.tensor_keys.action]
        )

    def qvalues(self, params: dict[str, torch.Tensor], observation: torch.Tensor, action: torch.Tensor,
                training: bool) -> torch.Tensor:
        """All critics at ``(observation, action)`` (``[*batch, dim]`` each): ``[num_qvalue_nets, *batch]``.
        In training mode the batch statistics move, once per call, as one forward of each critic would."""
        x = torch.cat([observation, action], -1)
        batch_shape = x.shape[:-1]
        # columns, [copies, features, rows], as tensor_nets.run_stacked_mlp keeps them
        x = x.reshape(-1, x.shape[-1]).mT.expand(self.num_qvalue_nets, -1, -1)
        renorm = _renorm_train if training else _renorm_eval
        for kind, name, module in self._critic_layers:
            if kind == "linear":
                x = torch.baddbmm(params[f"{name}.bias"].unsqueeze(-1), params[f"{name}.weight"], x)
            elif kind == "relu":
                x = torch.relu(x)
            else:
                x = renorm(module, params, name, x)
        return x.mT.reshape(self.num_qvalue_nets, *batch_shape, -1).squeeze(-1)

    def qvalue_loss(self, tensordict: TensorDictBase):
        if not self.lean:
            return super().qvalue_loss(tensordict)
        observation, action, next_observation, reward, terminated = transition_tensors(
            tensordict, self._actor_parts[3], self.tensor_keys)
        with torch.no_grad():
            next_action, next_log_prob = self.sample_action(next_observation, reparameterize=False)
        batch = observation.shape[0]
        # (s, a) and (s', a') in one pass: both halves normalised with the same batch statistics
        q = self.qvalues(cached_flat_params(self, "qvalue_network_params"),
                         torch.cat([observation, next_observation]), torch.cat([action, next_action]),
                         training=self.qvalue_network.training)
        current, following = q.split(batch, dim=1)
        next_value = (following.amin(0) - self._alpha * next_log_prob).detach()
        not_terminated = (~terminated.squeeze(-1)).int()
        gamma = bootstrap_discount(self, tensordict, next_value)  # gamma ** steps_to_next_obs for n-step transitions
        target = reward.squeeze(-1) + gamma * not_terminated * next_value
        loss = distance_loss(current, target.expand_as(current), loss_function=self.loss_function).sum(0)
        td_error = (current - target).abs().detach().amax(0)
        return self._reduce_loss(loss, tensordict=tensordict), {"td_error": td_error}

    def actor_loss(self, tensordict: TensorDictBase):
        if not self.lean:
            return super().actor_loss(tensordict)
        observation = tensordict.get(self._actor_parts[3])
        action, log_prob = self.sample_action(observation)
        # the critics in eval mode with their parameters detached: the gradient reaches the actor only
        min_q = self.qvalues(cached_detached_params(self, "qvalue_network_params"), observation, action, training=False).amin(0)
        return self._reduce_loss(self._alpha * log_prob - min_q, tensordict=tensordict), {"log_prob": log_prob.detach()}
