"""``LeanAdam``: ``torch.optim.Adam(fused=True)`` without the per-call Python of ``Optimizer.step``;
``clip_gradient_norms``: TF-Agents' gradient clipping, one tensor at a time.

Why this exists (TorchRL has no optimisers of its own; torch's is used everywhere else): for the
small networks of the tutorials (TD3 on Pendulum: ~3,600 critic and ~1,300 actor parameters),
``Adam.step`` spends far longer in Python (profiler ``record_function``, hooks, ``_init_group``,
grouping tensors by device and dtype) than in its one fused kernel. Measured on this 2-core CPU:
one step of the TD3 critics' optimiser ~47 us with ``Adam(fused=True)``, ~28 us with this class;
a whole TD3 update ~1.49 -> ~1.40 ms (BENCHMARKS.md, "Pendulum-v1 TD3 to -200", has the run-level figures).

``LeanAdam`` *is* a ``torch.optim.Adam``: its state, ``state_dict``/``load_state_dict``, param
groups and learning-rate schedulers are Adam's own. ``step`` calls the same kernel that
``Adam(fused=True)`` calls, with the same arguments, so the results are bitwise identical (tested);
it falls back to ``Adam.step`` whenever that shortcut would not be Adam's own step: a closure,
step hooks, a parameter whose state is not created yet (the first step), amsgrad, maximize,
differentiable, capturable, decoupled weight decay, a tensor learning rate, complex parameters,
or parameters spread over several devices or dtypes.
"""

from __future__ import annotations

import torch
from torch.optim.optimizer import _global_optimizer_post_hooks, _global_optimizer_pre_hooks

__all__ = ["LeanAdam", "clip_gradient_norms"]


def _adam_step_with_hooks():
    """``Adam.step`` wrapped, once, in ``profile_hook_step`` (hooks and profiler label) for the fallback.

    torch wraps a class's ``step`` when its first instance is made, so ``torch.optim.Adam.step`` is
    wrapped only once some plain ``Adam`` exists; this takes the unwrapped one and wraps it here.
    """
    step = torch.optim.Adam.step
    if getattr(step, "hooked", False):
        step = step.__wrapped__
    return torch.optim.Optimizer.profile_hook_step(step)


_ADAM_STEP = _adam_step_with_hooks()

_PLAIN_GROUP = {"amsgrad": False, "maximize": False, "differentiable": False, "capturable": False,
                "decoupled_weight_decay": False, "fused": True}


class LeanAdam(torch.optim.Adam):
    """``torch.optim.Adam(params, fused=True, ...)`` whose ``step`` and ``zero_grad`` skip the
    per-call Python around the fused kernel (see the module docstring)."""

    def __init__(self, params, lr: float = 1e-3, **kwargs):
        kwargs["fused"] = True
        super().__init__(params, lr=lr, **kwargs)

    def _lean_groups(self) -> list | None:
        """Per group ``(group, params, grads, exp_avgs, exp_avg_sqs, steps)``, or None to fall back."""
        if self._optimizer_step_pre_hooks or self._optimizer_step_post_hooks:
            return None
        if _global_optimizer_pre_hooks or _global_optimizer_post_hooks:
            return None
        groups, kind = [], None
        for group in self.param_groups:
            if any(group.get(k, v) != v for k, v in _PLAIN_GROUP.items()) or torch.is_tensor(group["lr"]):
                return None
            params, grads, exp_avgs, exp_avg_sqs, steps = [], [], [], [], []
            for p in group["params"]:
                if p.grad is None:
                    continue
                state = self.state.get(p)
                if not state or p.grad.is_sparse or p.is_complex():
                    return None
                if kind is None:
                    kind = (p.device, p.dtype)
                elif (p.device, p.dtype) != kind:
                    return None
                params.append(p)
                grads.append(p.grad)
                exp_avgs.append(state["exp_avg"])
                exp_avg_sqs.append(state["exp_avg_sq"])
                steps.append(state["step"])
            if params:
                groups.append((group, params, grads, exp_avgs, exp_avg_sqs, steps))
        return groups

    def step(self, closure=None):
        groups = self._lean_groups() if closure is None else None
        if groups is None:
            return _ADAM_STEP(self, closure)
        with torch.no_grad():
            for group, params, grads, exp_avgs, exp_avg_sqs, steps in groups:
                # what torch.optim.adam._fused_adam does for one device and dtype; torch 2.13's private
                # kernel and arguments (check at each torch upgrade: tests/test_optim.py compares bitwise)
                torch._foreach_add_(steps, 1)
                beta1, beta2 = group["betas"]
                torch._fused_adam_(
                    params, grads, exp_avgs, exp_avg_sqs, [], steps,
                    amsgrad=False, lr=group["lr"], beta1=float(beta1), beta2=float(beta2),
                    weight_decay=group["weight_decay"], eps=group["eps"], maximize=False,
                    grad_scale=None, found_inf=None,
                )
        return None

    # Optimizer.__init__ wraps the class's ``step`` in ``profile_hook_step`` (a profiler
    # record_function and the hooks) unless it is marked as wrapped already: this one hands any
    # step with hooks to Adam's own step, wrapped (``_ADAM_STEP``).
    step.hooked = True

    def zero_grad(self, set_to_none: bool = True) -> None:
        if not set_to_none:
            return super().zero_grad(set_to_none)
        for group in self.param_groups:
            for p in group["params"]:
                p.grad = None


def clip_gradient_norms(params, max_norm: float, stacked: bool = False, fast: bool = True) -> None:
    """Scale each parameter's gradient to a norm of at most ``max_norm``, one tensor at a time
    (``stacked``: each slice along the first dim, one per stacked network).

    TF-Agents' ``eager_utils.clip_gradient_norms`` (``tf.clip_by_norm`` per variable), which
    ``SacAgent``'s and ``DqnAgent``'s ``gradient_clipping`` apply; torch's ``clip_grad_norm_``
    clips the norm of all gradients together instead, a different rule. ``fast=False``: one tensor op at a time
    instead of torch's private ``_foreach`` kernels (the same numbers).
    """
    grads = [p.grad for p in params if p.grad is not None]
    if stacked:
        grads = [g for grad in grads for g in grad.unbind(0)]
    if grads and not fast:
        for grad in grads:
            grad.mul_(torch.clamp(max_norm / (grad.norm() + 1e-6), max=1.0))
    elif grads:
        norms = torch._foreach_norm(grads)
        torch._foreach_mul_(grads, [torch.clamp(max_norm / (n + 1e-6), max=1.0) for n in norms])
