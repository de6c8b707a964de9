"""A collect policy (a TensorDict module) as a function on one observation tensor.

``tensor_step(policy, observation_key)`` returns ``act(observation) -> {key: tensor}``: what the
policy writes into a TensorDict holding ``observation`` (batch ``[]``: one env), under the current
exploration type. A collector that steps a gymnasium env itself (``pipelines/workers/gym_collector``)
calls it once per env step, so its per-call cost is the point: the built-in collect policies run on
plain tensors here (epsilon-greedy over a Q-network ~25 us, TD3's actor plus Gaussian noise, SAC's
TanhNormal actor), where the same modules through a TensorDict cost 150-300 us on this 2-core CPU.
Each fast path computes what the module's own ``forward`` computes, with its random draws in the
same order; any other policy (a user's actor) is called through a TensorDict, unchanged.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDict
from tensordict.nn import ProbabilisticTensorDictModule, ProbabilisticTensorDictSequential, TensorDictSequential
from torch import nn
from torchrl.data import Bounded, Composite
from torchrl.envs.utils import ExplorationType, exploration_type, set_exploration_type
from torchrl.modules import AdditiveGaussianModule, QValueActor, QValueModule, TanhNormal

from rlpipe.modules.fast.exploration import EGreedyQPolicy
from rlpipe.modules.fast.sac_loss import tanh_normal_rsample
from rlpipe.modules.fast.tensor_nets import is_plain_module, module_forward

__all__ = ["GreedyStep", "TensorStep", "greedy_step", "tensor_step"]

TensorStep = Callable[[torch.Tensor], dict]
"""``act(observation) -> {output key: tensor}`` for one env (no batch dimension)"""

GreedyStep = Callable[[torch.Tensor], torch.Tensor]
"""``act(observation) -> action`` for one env: the policy's action under ``ExplorationType.DETERMINISTIC``"""


def _exploring() -> bool:
    return exploration_type() in (ExplorationType.RANDOM, None)


def tensor_step(policy: nn.Module, observation_key: str = "observation") -> TensorStep:
    """``policy`` as ``act(observation)``: its fast tensor path where it has one, else through a TensorDict."""
    for make in (_egreedy_step, _additive_gaussian_step, _tanh_normal_step):
        step = make(policy, observation_key)
        if step is not None:
            step.inference_safe = True  # it creates no state: a collector may call it under inference mode
            return step
    return _tensordict_step(policy, observation_key)


def _tensordict_step(policy: nn.Module, observation_key: str) -> TensorStep:
    def act(observation: torch.Tensor) -> dict:
        td = policy(TensorDict({observation_key: observation}, batch_size=[]))
        return {k: v for k, v in td.items(include_nested=True, leaves_only=True) if k != observation_key}

    return act


def _egreedy_step(policy: nn.Module, observation_key: str) -> TensorStep | None:
    if not isinstance(policy, EGreedyQPolicy):
        return None
    parts = policy._lean_parts()
    if parts is None or parts[1] != observation_key:
        return None

    def act(observation: torch.Tensor) -> dict:
        action, values, chosen = policy.act(observation, torch.Size([]))
        return {"action": action, "action_value": values, "chosen_action_value": chosen}

    return act


def _additive_gaussian_step(policy: nn.Module, observation_key: str) -> TensorStep | None:
    """``TensorDictSequential(actor on tensors, AdditiveGaussianModule)``: TD3's collect policy."""
    if type(policy) is not TensorDictSequential or len(policy.module) != 2:
        return None
    actor, noise = policy.module
    if not (is_plain_module(actor) and list(actor.in_keys) == [observation_key] and list(actor.out_keys) == ["action"]):
        return None
    if type(noise) is not AdditiveGaussianModule or noise.action_key != "action":
        return None
    spec = noise.spec
    spec = spec["action"] if isinstance(spec, Composite) else spec
    if not isinstance(spec, Bounded) or spec.domain != "continuous":
        return None
    net = module_forward(actor.module)
    bounds = _OnDevice(spec.space.low, spec.space.high)  # the spec stays where the env is

    def act(observation: torch.Tensor) -> dict:
        action = net(observation)
        if _exploring():
            # AdditiveGaussianModule._add_noise: N(mean, std) * sigma, then the spec's projection (a clamp)
            mean, std = noise.mean.expand(action.shape), noise.std.expand(action.shape)
            action = action + torch.normal(mean=mean, std=std) * noise.sigma
            low, high = bounds.on(action.device)
            action = torch.maximum(torch.minimum(action, high), low)
        return {"action": action}

    return act


def _tanh_normal_step(policy: nn.Module, observation_key: str) -> TensorStep | None:
    """A ``ProbabilisticActor`` of a network on tensors and a plain TanhNormal: SAC's collect policy."""
    parts = _tanh_normal_parts(policy, observation_key)
    if parts is None:
        return None
    net, dist, kwargs = parts
    if not kwargs.get("safe_tanh", True) or dist.default_interaction_type is not ExplorationType.RANDOM:
        return None
    low = torch.as_tensor(kwargs.get("low", -1.0), dtype=torch.float32)
    high = torch.as_tensor(kwargs.get("high", 1.0), dtype=torch.float32)
    trivial = bool((low == -1.0).all()) and bool((high == 1.0).all())
    affine = None if trivial else _OnDevice((high + low) / 2, (high - low) / 2)  # center, radius
    log_prob_key = dist.log_prob_key if dist.return_log_prob else None
    module, out_keys = module_forward(net.module), list(net.out_keys)
    deterministic = policy  # anything but sampling goes through the module itself

    def act(observation: torch.Tensor) -> dict:
        if exploration_type() not in (ExplorationType.RANDOM, None):
            return _tensordict_step(deterministic, observation_key)(observation)
        out = dict(zip(out_keys, module(observation), strict=True))
        center, radius = (None, None) if affine is None else affine.on(out["loc"].device)
        action, log_prob = tanh_normal_rsample(out["loc"], out["scale"], center, radius)
        out["action"] = action
        if log_prob_key is not None:
            out[log_prob_key] = log_prob
        return out

    return act


def greedy_step(policy: nn.Module, observation_key: str = "observation") -> GreedyStep:
    """``policy``'s deterministic action (``ExplorationType.DETERMINISTIC``) as ``act(observation) -> action``.

    What an evaluation plays, one env step at a time (``rlpipe.pipelines.workers.evaluation.evaluate``
    on a gymnasium env): the built-in evaluation policies on tensors, each computing what TorchRL
    computes for it (a ``QValueActor``'s argmax, TD3's actor, SAC's TanhNormal through TorchRL's own
    transforms of ``loc``), so the actions are the same numbers; any other policy through a TensorDict
    under ``ExplorationType.DETERMINISTIC``.
    """
    for make in (_greedy_qvalue_step, _greedy_plain_step, _greedy_tanh_normal_step):
        step = make(policy, observation_key)
        if step is not None:
            return step
    full = _tensordict_step(policy, observation_key)

    def act(observation: torch.Tensor) -> torch.Tensor:
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            return full(observation)["action"]

    return act


def _greedy_qvalue_step(policy: nn.Module, observation_key: str) -> GreedyStep | None:
    """A ``QValueActor`` over a plain Q-network with a categorical action: DQN's greedy policy."""
    if not isinstance(policy, QValueActor) or len(policy.module) != 2:
        return None
    net, qvalue = policy.module
    if not (is_plain_module(net) and type(qvalue) is QValueModule) or list(net.in_keys) != [observation_key]:
        return None
    if (qvalue.action_space != "categorical" or qvalue.action_mask_key is not None
            or list(net.out_keys) != list(qvalue.in_keys) or qvalue.out_keys[0] != "action"):
        return None
    qnet = module_forward(net.module)
    return lambda observation: qnet(observation).argmax(-1)  # QValueModule's categorical action


def _greedy_plain_step(policy: nn.Module, observation_key: str) -> GreedyStep | None:
    """One network from the observation to the action (TD3's deterministic actor)."""
    if not (is_plain_module(policy) and list(policy.in_keys) == [observation_key]
            and list(policy.out_keys) == ["action"]):
        return None
    return module_forward(policy.module)


def _greedy_tanh_normal_step(policy: nn.Module, observation_key: str) -> GreedyStep | None:
    """SAC's actor: TanhNormal's deterministic sample, TorchRL's transforms (safe tanh, then the affine map
    to the bounds) applied to ``loc``, as ``TanhNormal.deterministic_sample`` does."""
    parts = _tanh_normal_parts(policy, observation_key)
    if parts is None:
        return None
    net, _, kwargs = parts
    low = torch.as_tensor(kwargs.get("low", -1.0), dtype=torch.float32)
    # the transforms depend on the bounds only: made once, from a distribution of the action's shape
    transforms = TanhNormal(torch.zeros(low.shape), torch.ones(low.shape), **kwargs).transforms
    module, loc_index = module_forward(net.module), list(net.out_keys).index("loc")

    def act(observation: torch.Tensor) -> torch.Tensor:
        action = module(observation)[loc_index]
        for transform in transforms:
            action = transform(action)
        return action

    return act


class _OnDevice:
    """Constant tensors (an action's bounds) where the actions are: a policy on a GPU acting on bounds read
    from the env's spec on the CPU; copied once per device."""

    def __init__(self, *tensors: torch.Tensor):
        self._copies = {tensors[0].device: tensors}

    def on(self, device: torch.device) -> tuple[torch.Tensor, ...]:
        copies = self._copies.get(device)
        if copies is None:
            copies = self._copies[device] = tuple(t.to(device) for t in next(iter(self._copies.values())))
        return copies


def _tanh_normal_parts(policy: nn.Module, observation_key: str):
    """``(network module, distribution module, TanhNormal's kwargs)`` of a ``ProbabilisticActor`` whose network
    maps ``observation_key`` to ``loc``/``scale`` on tensors and whose distribution is a plain TanhNormal
    sampling ``action`` (no ``tanh_loc``), else None: what both SAC fast paths need."""
    if not isinstance(policy, ProbabilisticTensorDictSequential) or len(policy.module) != 2:
        return None
    net, dist = policy.module
    if not (is_plain_module(net) and isinstance(dist, ProbabilisticTensorDictModule)):
        return None
    if list(net.in_keys) != [observation_key] or list(net.out_keys) != list(dist.in_keys):
        return None
    kwargs = dict(dist.distribution_kwargs)
    if not (dist.distribution_class is TanhNormal and set(kwargs) <= {"low", "high", "tanh_loc", "safe_tanh", "upscale"}
            and not kwargs.get("tanh_loc", False) and sorted(dist.dist_keys) == ["loc", "scale"]
            and list(dist.dist_sample_keys) == ["action"]):
        return None
    return net, dist, kwargs
