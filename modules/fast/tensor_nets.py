"""TorchRL networks run on plain tensors: the fast path that losses share.

TorchRL's losses call their networks through TensorDicts, and for several copies (twin critics)
through ``vmap`` over stacked parameters. For the small MLPs of the tutorials that costs several
times the arithmetic (TD3's stock loss: ~3 ms per forward at batch 256 on a 2-core CPU, for ~0.3 ms
of matmuls). The functions here evaluate a TorchRL ``MLP`` from a flat ``{name: tensor}`` dict of
its parameters (a loss's own ``*_network_params``), one copy (``run_mlp``) or all stacked copies at
once as batched matmuls (``run_stacked_mlp``). TorchRL has no tensor-level entry point for this.
Any network they cannot handle is reported as ``None`` by ``mlp_layers``, and the caller falls
back to TorchRL's TensorDict path.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from tensordict.nn import TensorDictModule
from torchrl.modules import MLP

from rlpipe.modules.critics import EncodedCritic
from rlpipe.modules.normalization import RunningObservationNorm

__all__ = ["ELEMENTWISE", "critic_layers", "importance_weights", "is_plain_module", "mlp_layers", "sequential_layers", "run_mlp", "run_stacked_mlp", "cached_flat_params",
           "transition_tensors", "bootstrap_discount", "module_forward"]

Layers = list[tuple[str, object]]

ELEMENTWISE = (
    torch.nn.ReLU, torch.nn.ReLU6, torch.nn.LeakyReLU, torch.nn.ELU, torch.nn.SELU, torch.nn.CELU, torch.nn.GELU,
    torch.nn.SiLU, torch.nn.Mish, torch.nn.Tanh, torch.nn.Sigmoid, torch.nn.Softplus, torch.nn.Softsign,
    torch.nn.Hardtanh, torch.nn.Hardswish, torch.nn.Hardsigmoid, torch.nn.Tanhshrink, torch.nn.Identity,
    torch.nn.Dropout,
)
"""parameter-free layers that act on each element alone (exact types: a subclass may override ``forward``)"""


def is_plain_module(module) -> bool:
    """A TensorDictModule that only maps its in_keys' tensors through one ``nn.Module``."""
    return (
        isinstance(module, TensorDictModule)
        and type(module).forward is TensorDictModule.forward
        and isinstance(module.module, torch.nn.Module)
    )


def mlp_layers(mlp: torch.nn.Module, prefix: str = "") -> Layers | None:
    """``[("linear", parameter name prefix) | ("other", parameter-free module)]`` of a TorchRL
    ``MLP`` whose parameters are named ``prefix + <layer>.weight/bias``; None for anything else.

    Such a network can be evaluated on tensors from a flat ``{name: tensor}`` dict of parameters
    (``run_mlp``, ``run_stacked_mlp``).
    """
    if type(mlp) is not MLP or getattr(mlp, "_reshape_out", False):
        return None
    layers = []
    for name, layer in mlp.named_children():
        if type(layer) is torch.nn.Linear:
            layers.append(("linear", prefix + name))
        elif not any(True for _ in layer.parameters()) and not any(True for _ in layer.buffers()):
            layers.append(("other", layer))
        else:
            return None
    return layers


def sequential_layers(module: torch.nn.Module) -> Layers | None:
    """``mlp_layers`` of a ``Sequential`` of TorchRL ``MLP``s and parameter-free modules (e.g.
    ``Sequential(MLP, NormalParamExtractor)``, SAC's actor network), or of one ``MLP``; None otherwise.

    Parameter names are the Sequential's (``"0.0.weight"``); the last module may return a tuple.
    """
    if type(module) is not torch.nn.Sequential:
        return mlp_layers(module)
    layers = []
    for name, child in module.named_children():
        if type(child) is MLP:
            inner = mlp_layers(child, f"{name}.")
            if inner is None:
                return None
            layers += inner
        elif (not any(True for _ in child.parameters()) and not any(True for _ in child.buffers())
              or type(child) is RunningObservationNorm):  # its statistics are the learner's, not the loss's
            layers.append(("other", child))
        else:
            return None
    return layers


def critic_layers(module: torch.nn.Module) -> tuple[torch.nn.Module | None, Layers] | None:
    """``(normaliser or None, mlp_layers)`` of a critic network: a TorchRL ``MLP`` over ``cat(observation,
    action)``, or ``EncodedCritic(RunningObservationNorm, MLP)`` (``normalize_observations``: the observation
    normalised first, by the module itself, then joined with the action); None for anything else."""
    if type(module) is EncodedCritic and type(module.encoder) is RunningObservationNorm:
        layers = mlp_layers(module.head, "head.")
        return None if layers is None else (module.encoder, layers)
    layers = mlp_layers(module)
    return None if layers is None else (None, layers)


def cached_flat_params(loss: torch.nn.Module, params_name: str, drop: int = 1) -> dict[str, torch.Tensor]:
    """``{dotted name: tensor}`` of a TorchRL loss's parameter set (``"actor_network_params"``, ...),
    with the first ``drop`` key parts dropped (``("module", ...)`` of a TensorDictModule), cached.

    The tensors are the loss's own parameters/buffers, updated in place by optimisers and target
    updaters, so the cache stays valid; TorchRL's ``LossModule`` erases ``_cache*`` attributes
    when the loss is moved (``.to()``), and the cache is then rebuilt.
    """
    cache = loss.__dict__.setdefault("_cache_flat_params", {})
    flat = cache.get((params_name, drop))
    if flat is None:
        params = getattr(loss, params_name)
        flat = cache[(params_name, drop)] = {".".join(key[drop:]): value for key, value in params.items(True, True)}
    return flat


def cached_detached_params(loss: torch.nn.Module, params_name: str) -> dict[str, torch.Tensor]:
    """``cached_flat_params(loss, params_name)`` detached (a critic read by the actor's loss): detached
    views of tensors updated in place stay current, so they are cached too (erased with the rest)."""
    cache = loss.__dict__.setdefault("_cache_detached_params", {})
    flat = cache.get(params_name)
    if flat is None:
        flat = cache[params_name] = {k: v.detach() for k, v in cached_flat_params(loss, params_name).items()}
    return flat


def transition_tensors(tensordict, observation_key, tensor_keys) -> tuple[torch.Tensor, ...]:
    """``(observation, action, next observation, next reward, next terminated)`` of a replay batch,
    under a TorchRL loss's ``tensor_keys`` (``action``, ``reward``, ``terminated``)."""
    return (
        tensordict.get(observation_key),
        tensordict.get(tensor_keys.action),
        tensordict.get(("next", observation_key)),
        tensordict.get(("next", tensor_keys.reward)),
        tensordict.get(("next", tensor_keys.terminated)),
    )


def bootstrap_discount(loss, tensordict, like: torch.Tensor):
    """The discount of each sample's bootstrapped value, shaped like ``like``: the loss's ``gamma``, or
    ``gamma ** steps_to_next_obs`` where the batch holds n-step transitions (that key, as TorchRL's
    ``TD0Estimator`` reads it: ``loss.value_estimator.tensor_keys.steps_to_next_obs``)."""
    estimator = loss.value_estimator
    steps = tensordict.get(estimator.tensor_keys.steps_to_next_obs, None)
    if steps is None:
        return estimator.gamma
    return estimator.gamma ** steps.to(like.dtype).reshape(like.shape)


def importance_weights(loss, tensordict) -> torch.Tensor | None:
    """A prioritized buffer's importance weights in a replay batch (``[*batch]``), or None: read as
    TorchRL's own losses read them (``loss.tensor_keys.priority_weight``, in TorchRL 0.14
    "priority_weight", the key ``PrioritizedSampler`` writes; none when ``use_prioritized_weights``
    is off), so a loss computed on tensors weighs samples as the TensorDict one does."""
    return loss._maybe_get_priority_weight(tensordict)


def run_mlp(layers: Layers, params: dict[str, torch.Tensor], x: torch.Tensor) -> torch.Tensor:
    """One network of ``mlp_layers`` on ``x``, with the tensors of ``params``."""
    for kind, layer in layers:
        x = layer(x) if kind == "other" else F.linear(x, params[f"{layer}.weight"], params.get(f"{layer}.bias"))
    return x


def run_stacked_mlp(layers: Layers, params: dict[str, torch.Tensor], x: torch.Tensor, copies: int) -> torch.Tensor:
    """All ``copies`` networks of ``mlp_layers`` on the same ``x`` at once: ``[copies, *x.shape[:-1], out]``.

    ``params`` holds stacked tensors (``[copies, ...]``, as a TorchRL loss keeps its twin critics);
    each Linear layer becomes one batched matmul, what the stock losses do with ``vmap``. Gradients
    reach the parameters if they carry them.
    """
    batch_shape = x.shape[:-1]
    # Activations are kept as columns, [copies, features, rows]: each layer is
    # baddbmm(bias, weight, x), whose weight gradient (grad @ x^T) comes out contiguous in the
    # parameter's own [out, in] layout. The row layout (x @ weight^T) hands autograd a transposed
    # gradient that it copies into place for every weight (~0.25 ms per 256x256 pair here).
    x = x.reshape(-1, x.shape[-1]).mT.expand(copies, -1, -1)
    for kind, layer in layers:
        if kind == "other":
            # An elementwise layer (ReLU, Tanh, ...) is indifferent to the layout; any other parameter-free
            # layer acts on the last dim, so it sees rows there, as it would in the network's own forward;
            # a LayerNorm without weights (TorchRL's MLP ``norm_class``) is normalised over the columns.
            if type(layer) in ELEMENTWISE:
                x = layer(x)
            elif _is_plain_layer_norm(layer):
                # normalised over the features where they lie (dim -2): layer(x.mT).mT hands the norm and
                # the ReLU after it transposed activations, copied forward and backward (`rlpipe bench floor`,
                # sac-minitaur's update with LayerNorm critics: 6.10 ms that way, 4.61 ms this
                # way, 3.3 ms without the norm)
                x = _ColumnLayerNorm.apply(x, layer.eps)
            else:
                x = layer(x.mT).mT
        else:
            weight, bias = params[f"{layer}.weight"], params.get(f"{layer}.bias")
            x = torch.matmul(weight, x) if bias is None else torch.baddbmm(bias.unsqueeze(-1), weight, x)
    return x.mT.reshape(copies, *batch_shape, -1)


class _ColumnLayerNorm(torch.autograd.Function):
    """``F.layer_norm`` without weights over dim -2 of ``[copies, features, rows]`` activations, with its
    backward written out: ``dx = (g - mean(g) - y * mean(g * y)) / std`` (sac-minitaur's update ~5% faster
    than with autograd's backward of the same forward ops)."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, eps: float) -> torch.Tensor:
        centred = x - x.mean(dim=-2, keepdim=True)
        inv_std = torch.rsqrt(centred.square().mean(dim=-2, keepdim=True) + eps)
        ctx.save_for_backward(centred, inv_std)  # not y: an in-place activation after the norm changes it
        return centred * inv_std

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        centred, inv_std = ctx.saved_tensors
        y = centred * inv_std
        inner = grad - grad.mean(dim=-2, keepdim=True) - y * (grad * y).mean(dim=-2, keepdim=True)
        return inner * inv_std, None


def _is_plain_layer_norm(layer) -> bool:
    """A LayerNorm over the last dim without weights: what ``make_qvalue_critic(layer_norm=True)`` builds."""
    return (type(layer) is torch.nn.LayerNorm and not layer.elementwise_affine
            and len(layer.normalized_shape) == 1)


def module_forward(module: torch.nn.Module):
    """``module``'s forward as a function of one tensor, without ``nn.Module.__call__`` per layer where it
    is a TorchRL ``MLP`` or a ``Sequential`` of them (``sequential_layers``); ``module`` itself otherwise.

    A collector calls the collect policy once per env step, on one observation: for the tutorials'
    small networks the calls around the arithmetic are a large part of it (DQN's epsilon-greedy step on
    CartPole's 120-84 Q-network, under ``no_grad`` on this 2-core CPU: 47 us with the modules called, 39 us
    layer by layer; ``F.linear`` and ``relu`` are what the modules' own ``forward`` call). The layers' current parameters are read at
    each call (an optimiser, ``load_state_dict`` or TorchRL's weight updaters may replace them), and
    while any module has a forward hook (its own or a global one) the call goes through ``module``.
    """
    layers = sequential_layers(module)
    if layers is None:
        return module
    named = dict(module.named_modules())
    steps = []
    for kind, layer in layers:
        if kind == "linear":
            steps.append(named[layer])  # the Linear's module path is its parameters' prefix
        else:
            steps.append(layer)
    modules = list(named.values())
    relu = torch.nn.ReLU

    def hooked() -> bool:
        mod = torch.nn.modules.module
        return bool(mod._global_forward_hooks or mod._global_forward_pre_hooks
                    or any(m._forward_hooks or m._forward_pre_hooks for m in modules))

    def forward(x: torch.Tensor):
        if hooked():
            return module(x)
        for step in steps:
            if type(step) is torch.nn.Linear:
                x = F.linear(x, step.weight, step.bias)
            elif type(step) is relu and not step.inplace:
                x = torch.relu(x)
            else:
                x = step(x)
        return x

    return forward
