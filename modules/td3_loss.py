"""TD3's loss with its six ingredients switchable, and one TD3 gradient step.

The reference algorithm is ``TD3.train`` of the TD3 tutorial (Fujimoto et al.'s code, Pendulum-v1),
which asks the reader to switch off TD3's six ingredients one at a time:

=========================  =====================================  ===========================
ingredient                 switched off means                      honoured by
=========================  =====================================  ===========================
deterministic_policy       a stochastic (Gaussian) actor that      ``TD3AblationLoss``
                           explores by sampling
experience_replay          buffer of 1, batch of 1                 the pipeline's replay buffer
target_networks            targets = online networks (tau = 1)     ``make_target_updater`` (target_updates)
target_policy_smoothing    no noise on the target action           ``TD3AblationLoss``
delayed_policy_updates     actor updated on every critic update    ``td3_update``
clipped_double_q           target uses Q1 alone, not min(Q1, Q2)   ``TD3AblationLoss``
=========================  =====================================  ===========================

``TD3AblationLoss`` subclasses TorchRL's ``TD3Loss`` and keeps its parameters, target parameters,
keys, value estimator (``gamma``), ``forward`` and compatibility with ``SoftUpdate``. It replaces
``value_loss``/``actor_loss`` for three reasons besides the switches:

* speed: the stock loss builds, selects, expands and vmaps TensorDicts (~3 ms per forward at batch
  256 on this machine, for ~0.3 ms of arithmetic). Here networks run on tensors (``tensor_nets``):
  a critic that is a TorchRL ``MLP`` is evaluated for both critics at once as batched matmuls over
  the loss's stacked parameters, and an actor that is a ``TanhBoundedMLP`` (``make_deterministic_actor``)
  layer by layer on the online or target parameters (``torch.func.functional_call`` costs ~60 us
  more per call, for ~35 us of arithmetic). Other plain actors go through ``functional_call``,
  anything else through TensorDicts;
* the tutorial's target noise is in normalised action units (see ``target_action``), the stock
  loss adds it in raw action units;
* the stock actor loss evaluates both critics and keeps Q1; this one evaluates Q1 only.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import ProbabilisticTensorDictSequential, TensorDictModule
from torch.func import functional_call
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.objectives import SoftUpdate, TD3Loss, ValueEstimators
from torchrl.objectives.utils import distance_loss

from rlpipe.modules.actors import TanhBoundedMLP
from rlpipe.modules.fast.tensor_nets import (
    bootstrap_discount,
    cached_flat_params,
    importance_weights,
    is_plain_module,
    mlp_layers,
    run_mlp,
    run_stacked_mlp,
    transition_tensors,
)

__all__ = ["TD3AblationLoss", "td3_update"]


class TD3AblationLoss(TD3Loss):
    """TorchRL's ``TD3Loss`` with TD3's loss-side ingredients as switches (all on = standard TD3).

    Args:
        actor_network: the policy, ``"observation"`` -> ``"action"``. A deterministic one (e.g.
            ``rlpipe.modules.actors.make_deterministic_actor``) or, with
            ``deterministic_policy=False``, a ``ProbabilisticActor`` (``make_gaussian_actor``).
        qvalue_network: one critic, ``("observation", "action")`` -> ``"state_action_value"``
            (``make_qvalue_critic``); TD3Loss makes ``num_qvalue_nets`` copies of it, each with
            freshly drawn weights.

    Keyword Args:
        action_spec: the env's ``Bounded`` action spec (or ``bounds=(low, high)``).
        deterministic_policy: True: the actor is used deterministically (a stochastic actor is
            evaluated at its deterministic sample). False: the actor must be stochastic; the
            actor loss uses a reparameterised sample ``-Q1(s, a~pi(s))`` and the target action is
            a sample of the target actor (an unbiased one-sample estimate of
            ``E_{a'~pi}[Q(s', a')]``, i.e. the target of the policy that is actually followed).
        target_policy_smoothing: add clipped Gaussian noise to the target action (TD3's
            smoothing). Off: the target action is the target actor's action unchanged.
        clipped_double_q: the target uses ``min(Q1_target, Q2_target)``. Off: ``Q1_target``
            alone; both critics are still trained toward it.
        policy_noise: std of the target action noise, in normalised action units (fraction of
            the half action range), as in the tutorial. Default 0.2.
        noise_clip: the noise is clamped to ``[-noise_clip, noise_clip]``, normalised units.
            Default 0.5.
        loss_function: critic regression loss; ``"l2"`` (the tutorial's MSE, default),
            ``"smooth_l1"`` (TD3Loss's default) or ``"l1"``.
        num_qvalue_nets: number of critics (2 for TD3).
        on_tensors: run plain networks on tensors (``rlpipe.modules.fast.tensor_nets``); False: every network
            through TensorDicts, as TorchRL's ``TD3Loss`` calls them (the same numbers, slower).
        **td3_kwargs: passed on to ``TD3Loss`` (``delay_actor``, ``delay_qvalue``, ...).

    The discount is TorchRL's: ``loss.make_value_estimator(ValueEstimators.TD0, gamma=0.99)``
    (0.99 if not called). Only TD0 is supported, as in TD3.
    """

    def __init__(
        self,
        actor_network: TensorDictModule,
        qvalue_network: TensorDictModule,
        *,
        deterministic_policy: bool = True,
        target_policy_smoothing: bool = True,
        clipped_double_q: bool = True,
        policy_noise: float = 0.2,
        noise_clip: float = 0.5,
        loss_function: str = "l2",
        num_qvalue_nets: int = 2,
        on_tensors: bool = True,
        **td3_kwargs,
    ) -> None:
        stochastic_actor = isinstance(actor_network, ProbabilisticTensorDictSequential)
        if not deterministic_policy and not stochastic_actor:
            raise ValueError(
                "deterministic_policy=False needs a stochastic actor (a ProbabilisticActor, "
                f"e.g. rlpipe.modules.actors.make_gaussian_actor); got {type(actor_network)}."
            )
        if td3_kwargs.get("reduction", "mean") != "mean":
            raise ValueError("TD3AblationLoss only implements reduction='mean'.")
        super().__init__(
            actor_network,
            qvalue_network,
            num_qvalue_nets=num_qvalue_nets,
            policy_noise=policy_noise,
            noise_clip=noise_clip,
            loss_function=loss_function,
            **td3_kwargs,
        )
        self.deterministic_policy = deterministic_policy
        self.target_policy_smoothing = target_policy_smoothing
        self.clipped_double_q = clipped_double_q
        # Converts normalised noise to action units, as the tutorial's (a - center) / radius does.
        self.register_buffer("action_radius", (self.max_action - self.min_action) / 2)
        # Plain modules are called on tensors (fast); anything else, or every module with on_tensors=False
        # (the pipelines' fast=false), through TensorDicts.
        self._actor_on_tensors = on_tensors and is_plain_module(self.actor_network)
        self._actor_layers = (
            mlp_layers(self.actor_network.module.mlp, "mlp.")
            if self._actor_on_tensors and type(self.actor_network.module) is TanhBoundedMLP
            else None
        )
        self._critic_layers = (
            mlp_layers(self.qvalue_network.module) if on_tensors and is_plain_module(self.qvalue_network) else None
        )
        if len(self.actor_network.in_keys) != 1:
            raise ValueError(
                f"the actor must read one observation key, got {self.actor_network.in_keys}"
            )
        self._observation_key = self.actor_network.in_keys[0]
        # Build the (default, gamma=0.99) TD0 estimator now rather than on first use, so a
        # compiled loss does not see a new submodule appear and recompile.
        self.value_estimator  # noqa: B018

    def make_value_estimator(self, value_type: ValueEstimators = None, **hyperparams):
        # value_target below is TD3's one-step target; other estimators would be silently ignored.
        if value_type not in (None, ValueEstimators.TD0):
            raise NotImplementedError("TD3AblationLoss only supports the TD0 value estimator.")
        return super().make_value_estimator(value_type, **hyperparams)

    # -- networks on tensors ------------------------------------------------------------------

    def _flat_params(self, params_name: str) -> dict[str, torch.Tensor]:
        """``{name inside module.module: tensor}`` of a parameter set, cached (``cached_flat_params``).

        Keys start with "module" (TensorDictModule.module), which functional_call is given.
        """
        return cached_flat_params(self, params_name)

    def _critic_slice(self, params_name: str, index: int) -> dict[str, torch.Tensor]:
        """Critic ``index``'s tensors out of the stacked ones, detached, cached.

        Detached views of in-place-updated tensors stay current, so they can be cached; slices
        that must carry gradient would need a fresh autograd node per call, so those are never
        taken (``_qvalues`` evaluates all critics at once instead).
        """
        key = (params_name, index)
        cache = self.__dict__.get("_cache_critic_slices")
        if cache is None:
            cache = self.__dict__["_cache_critic_slices"] = {}
        sliced = cache.get(key)
        if sliced is None:
            flat = self._flat_params(params_name)
            sliced = cache[key] = {name: value.detach()[index] for name, value in flat.items()}
        return sliced

    def _actor(self, params_name: str, observation: torch.Tensor) -> torch.Tensor:
        """The action of the actor with parameters ``params_name`` (online or target)."""
        net = self.actor_network
        if self._actor_layers is not None:
            # TanhBoundedMLP.forward, with these parameters
            params = self._flat_params(params_name)
            out = torch.tanh(run_mlp(self._actor_layers, params, observation))
            return params["center"] + params["radius"] * out
        if self._actor_on_tensors:
            return functional_call(net.module, self._flat_params(params_name), (observation,), tie_weights=False)
        # Stochastic actors sample (rsample: differentiable) unless the policy is deterministic.
        deterministic = self.deterministic_policy
        mode = ExplorationType.DETERMINISTIC if deterministic else ExplorationType.RANDOM
        # no batch size: an observation may be a picture ([*batch, C, H, W]), whose batch its last dim does not end
        td = TensorDict({self._observation_key: observation}, batch_size=[])
        # preserve_module_state=False as in TD3Loss: otherwise to_module turns the target
        # buffers into grad-requiring parameters, which SoftUpdate then refuses.
        params = getattr(self, params_name)
        with set_exploration_type(mode), params.to_module(net, preserve_module_state=False):
            return net(td).get(self.tensor_keys.action)

    def _qvalues(
        self,
        params_name: str,
        observation: torch.Tensor,
        action: torch.Tensor,
        index: int | None = None,
    ) -> torch.Tensor:
        """Q-values of the online or target critics at ``(observation, action)``.

        ``index=None``: all critics, shape ``[num_qvalue_nets, *batch, 1]``, with gradient to the
        parameters if they have one. ``index=i``: critic ``i`` alone, ``[*batch, 1]``, with
        detached parameters (the actor loss; gradient still flows to ``action``).
        """
        if self._critic_layers is not None:
            # TorchRL's MLP concatenates its inputs; its Linear layers become batched matmuls
            # over the [num_qvalue_nets, ...] stacked parameters (what TD3Loss does with vmap).
            inputs = {self._observation_key: observation, self.tensor_keys.action: action}
            x = torch.cat([inputs[k] for k in self.qvalue_network.in_keys], -1)
            if index is not None:
                return run_mlp(self._critic_layers, self._critic_slice(params_name, index), x)
            return run_stacked_mlp(self._critic_layers, self._flat_params(params_name), x, self.num_qvalue_nets)
        # Any other critic: TorchRL's way, one TensorDict call per critic.
        net = self.qvalue_network
        td = TensorDict(
            {self._observation_key: observation, self.tensor_keys.action: action},
            batch_size=action.shape[:-1],  # an observation may be a picture: the action's batch is the batch
        )
        params = getattr(self, params_name)
        outputs = []
        for i in range(self.num_qvalue_nets) if index is None else (index,):
            critic_params = params[i].detach() if index is not None else params[i]
            with critic_params.to_module(net, preserve_module_state=False):
                outputs.append(net(td.copy()).get(self.tensor_keys.state_action_value))
        return torch.stack(outputs) if index is None else outputs[0]

    # -- TD3 on tensors -----------------------------------------------------------------------

    @torch.no_grad()
    def target_action(self, next_observation: torch.Tensor) -> torch.Tensor:
        """a' = target actor's action at s', plus TD3's clipped noise if smoothing is on.

        The tutorial normalises the action to [-1, 1] (``(a - center) / radius``), adds
        ``clamp(randn * policy_noise, -noise_clip, noise_clip)``, clamps to [-1, 1] and maps back;
        ``a + radius * noise`` clamped to ``[low, high]`` is the same map. (The stock TD3Loss adds
        the noise in raw action units, i.e. half as much on Pendulum, whose radius is 2.)
        """
        action = self._actor("target_actor_network_params", next_observation)
        if self.target_policy_smoothing:
            noise = (torch.randn_like(action) * self.policy_noise).clamp(
                -self.noise_clip, self.noise_clip
            )
            action = (action + self.action_radius * noise).clamp(self.min_action, self.max_action)
        return action

    @torch.no_grad()
    def value_target(
        self,
        next_observation: torch.Tensor,
        reward: torch.Tensor,
        terminated: torch.Tensor,
        discount: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``(r + gamma * (1 - terminated) * Q_target(s', a'), Q_target(s', a'))``, shaped like r.

        Q_target is the min over the target critics (clipped double Q), or the first target
        critic alone when ``clipped_double_q`` is off (then the other critics are not evaluated).
        ``discount`` (shaped like r, or None: ``gamma``) replaces ``gamma`` per sample: ``gamma **
        steps_to_next_obs`` for n-step transitions (``tensor_nets.bootstrap_discount``).
        """
        next_action = self.target_action(next_observation)
        if self.clipped_double_q:
            next_q = self._qvalues("target_qvalue_network_params", next_observation, next_action)
            next_q = next_q.amin(0)
        else:
            next_q = self._qvalues(
                "target_qvalue_network_params", next_observation, next_action, index=0
            )
        gamma = self.value_estimator.gamma if discount is None else discount
        not_terminated = 1 - terminated.to(reward.dtype)
        return reward + gamma * not_terminated * next_q, next_q

    def qvalue_loss_from_tensors(
        self,
        observation: torch.Tensor,
        action: torch.Tensor,
        next_observation: torch.Tensor,
        reward: torch.Tensor,
        terminated: torch.Tensor,
        weights: torch.Tensor | None = None,
        discount: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Critic loss: every critic regresses on the shared target.

        Returns ``(loss, predictions [n_critics, *reward.shape], target, next_q)``. The loss is
        the sum over critics of each one's mean loss: the critics share no parameters, so the
        gradients are the tutorial's two separate ``mse_loss`` backward passes.
        ``weights`` (importance weights of a prioritized buffer, shape of ``reward`` without its
        last dim) make each critic's mean a weighted one, as TD3Loss's. ``discount``: as in ``value_target``.
        """
        target, next_q = self.value_target(next_observation, reward, terminated, discount)
        predictions = self._qvalues("qvalue_network_params", observation, action)
        per_sample = distance_loss(
            predictions, target.expand_as(predictions), loss_function=self.loss_function
        )
        per_critic = tuple(range(1, per_sample.ndim))
        if weights is None:
            loss = per_sample.mean(dim=per_critic).sum()
        else:  # TorchRL's weighted mean (LossModule._reduce_loss): sum(w * loss) / sum(w)
            w = weights.unsqueeze(-1)
            loss = ((per_sample * w).sum(dim=per_critic) / w.sum()).sum()
        return loss, predictions, target, next_q

    def actor_loss_from_tensors(
        self, observation: torch.Tensor, weights: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``-Q1(s, pi(s)).mean()`` as in the tutorial; returns ``(loss, Q1(s, pi(s)))``.

        The critic's parameters are detached: the gradient reaches the actor only (the tutorial
        computes the critic's gradient too and discards it with ``zero_grad``).
        """
        action = self._actor("actor_network_params", observation)
        q1 = self._qvalues("qvalue_network_params", observation, action, index=0)
        if weights is None:
            return -q1.mean(), q1
        w = weights.unsqueeze(-1)
        return -(q1 * w).sum() / w.sum(), q1  # TD3Loss's weighted mean

    def tensors_from(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, ...]:
        """(observation, action, next observation, next reward, next terminated) of a batch."""
        return transition_tensors(tensordict, self._observation_key, self.tensor_keys)

    # -- TorchRL's TensorDict interface (TD3Loss.forward calls these) ---------------------------

    def value_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict]:
        weights = self._maybe_get_priority_weight(tensordict)
        tensors = self.tensors_from(tensordict)
        loss, predictions, target, next_q = self.qvalue_loss_from_tensors(
            *tensors, weights=weights, discount=bootstrap_discount(self, tensordict, tensors[3])
        )
        predictions, target = predictions.squeeze(-1), target.squeeze(-1)
        metadata = {
            "td_error": (predictions - target).pow(2).detach(),
            "next_state_value": next_q.squeeze(-1),
            "pred_value": predictions.detach(),
            "target_value": target,
        }
        return loss, metadata

    def actor_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict]:
        weights = self._maybe_get_priority_weight(tensordict)
        loss, q1 = self.actor_loss_from_tensors(tensordict.get(self._observation_key), weights)
        return loss, {"state_action_value_actor": q1.squeeze(-1).detach()}


def td3_update(
    loss: TD3Loss,
    batch: TensorDictBase,
    critic_optimizer: torch.optim.Optimizer,
    actor_optimizer: torch.optim.Optimizer,
    target_updater: SoftUpdate,
    update_index: int,
    policy_delay: int = 2,
    delayed_policy_updates: bool = True,
    target_update_period: int = 1,
) -> dict[str, torch.Tensor]:
    """One TD3 gradient step, the tutorial's ``TD3.train`` after sampling the batch.

    The critics are updated on every call; the actor and the target networks when
    ``update_index % policy_delay == 0`` (the tutorial's ``total_itr % policy_freq``, counted
    from 1), or on every call when ``delayed_policy_updates`` is False; the targets only on every
    ``target_update_period``-th of those. As in the tutorial the actor loss is computed after the
    critic step, i.e. with the updated critic.

    Args:
        loss: a ``TD3AblationLoss`` (fast, on tensors) or any TorchRL ``TD3Loss`` (through its
            own ``value_loss``/``actor_loss``).
        batch: a replay-buffer sample with the loss's keys (observation, action, ("next", ...));
            a prioritized buffer's importance weights in it weigh the losses, as in ``TD3Loss``.
        critic_optimizer: optimiser over ``loss.qvalue_network_params.parameters()`` (the
            tutorial: ``torch.optim.Adam(..., lr=3e-4)``; ``rlpipe.modules.fast.optim.LeanAdam``,
            the same fused Adam with less Python per step, is what the TD3 pipeline uses).
        actor_optimizer: optimiser over ``loss.actor_network_params.parameters()``
            (``.parameters()`` leaves out the actor's bound buffers).
        target_updater: ``rlpipe.modules.fast.target_updates.make_target_updater(loss, ...)``.
        update_index: number of this update (1, 2, ...); a Python int, so under ``torch.compile``
            the delay decision selects one of two graphs instead of branching on a tensor.
        policy_delay: the tutorial's ``policy_freq`` (2).
        delayed_policy_updates: False updates the actor on every call.
        target_update_period: actor updates between target updates (1: each of them).

    Returns:
        ``{"loss_qvalue": ..., "loss_actor": ...}`` as detached tensors (no host sync); the actor
        entry only on steps that updated the actor.

    ``torch.compile(td3_update)`` works (graph breaks at ``backward`` and in the optimisers are
    expected) but measured no faster than eager on this 2-core CPU, after ~55 s of compiling;
    compiling only ``loss.qvalue_loss_from_tensors`` (instance attribute) gains a few percent.
    """
    fast = isinstance(loss, TD3AblationLoss)
    if fast:
        observation, action, next_observation, reward, terminated = loss.tensors_from(batch)
        weights = importance_weights(loss, batch)
        critic_loss = loss.qvalue_loss_from_tensors(observation, action, next_observation, reward, terminated,
                                                    weights, bootstrap_discount(loss, batch, reward))[0]
    else:
        critic_loss = loss.value_loss(batch)[0]
    critic_optimizer.zero_grad(set_to_none=True)
    critic_loss.backward()
    critic_optimizer.step()
    out = {"loss_qvalue": critic_loss.detach()}

    actor_every = policy_delay if delayed_policy_updates else 1
    if update_index % actor_every == 0:
        actor_loss = loss.actor_loss_from_tensors(observation, weights)[0] if fast else loss.actor_loss(batch)[0]
        actor_optimizer.zero_grad(set_to_none=True)
        actor_loss.backward()
        actor_optimizer.step()
        if update_index % (actor_every * target_update_period) == 0:
            target_updater.step()
        out["loss_actor"] = actor_loss.detach()
    return out
