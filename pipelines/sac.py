"""SAC on TorchRL parts: TF-Agents' SAC-on-Minitaur tutorial (actor-learner API) as a pipeline.

    from rlpipe.pipelines import sac
    result = sac.SAC(sac.preset("sac")).train("runs/sac-minitaur")

TF-Agents' actor processes feeding a Reverb table become TorchRL collectors
(``collector.workers=N``, ``collector.sync=false`` for ``MultiAsyncCollector``) feeding a TorchRL
replay buffer; its ``SacAgent`` becomes TorchRL's ``SACLoss`` (TanhNormal actor, twin critics,
learned temperature; ``LeanSACLoss``, the same loss computed on tensors, unless you pass your own)
with a soft target update; its Learner and triggers are the shared loop.

CrossQ (``crossq.CrossQ``) is SAC with other critics and no target networks: it subclasses ``SAC`` and
keeps what this file builds for both (the tanh-normal actor, the entropy and learning-rate schedules, the
averaged greedy policy), with the keys they share in ``SACFamilyConfig``.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.objectives import LossModule, SACLoss

from rlpipe.modules.actors import TanhNormalMode, make_tanh_normal_actor, tanh_normal_head
from rlpipe.modules.critics import INITIALIZERS, make_qvalue_critic
from rlpipe.modules.encoders import FEATURES_KEY
from rlpipe.modules.fast.sac_loss import LeanSACLoss
from rlpipe.modules.fast.target_updates import lerp_
from rlpipe.modules.plain_policy import TensorDictPolicy
from rlpipe.pipelines.base import Agent, OffPolicyPipeline
from rlpipe.pipelines.config import (
    ANNEAL_WINDOW,
    LAYER_SIZES,
    LEARNING_RATE,
    ActorKeys,
    Check,
    ClippedGradientKeys,
    TrainConfig,
    check_learning_rate_schedule,
    checked,
    config_class,
    one_of,
)
from rlpipe.pipelines.errors import InputError
from rlpipe.pipelines.own_parts import observation_key_of

__all__ = ["SACConfig", "SACFamilyConfig", "SAC", "preset", "scale_rewards"]


@config_class(
    env=("MinitaurBulletEnv-v0", "an env with a continuous (Box) action space"),
    baseline_episodes=(5, "rather than num_eval_episodes: 20 random Minitaur episodes are ~70 s before the first "
                          "update, for a baseline the SAC tutorial does not have"),
)
class SACFamilyConfig(ActorKeys, TrainConfig):
    """The keys SAC and CrossQ share, with SAC's defaults."""

    actor_learning_rate: float = checked(3e-4, LEARNING_RATE)
    """Adam learning rate of the actor"""
    critic_learning_rate: float = checked(3e-4, LEARNING_RATE)
    """Adam learning rate of the twin critics"""
    alpha_learning_rate: float = checked(3e-4, LEARNING_RATE)
    """Adam learning rate of the entropy temperature"""
    reward_scale_factor: float = checked(1.0, Check(lambda v: v != 0, "a non-zero scale"))
    """rewards are multiplied by this in the critic's target"""
    initial_alpha: float = checked(1.0, Check(lambda v: v > 0, "a positive temperature"))
    """initial entropy temperature (SacAgent's initial_log_alpha=0)"""
    target_entropy: float | None = None
    """entropy target of the temperature (null: -|A|/2, SacAgent's default)"""
    target_entropy_final: float | None = None
    """move the entropy target linearly from target_entropy to this over target_entropy_anneal's env steps (null: it stays): a policy that learned with much noise then learns to act without it, so that its greedy (mean) action does what its samples did"""
    target_entropy_anneal: list[int] = checked(check=ANNEAL_WINDOW, factory=lambda: [0, 100_000])
    """env steps (frames collected, random ones included) over which target_entropy_final is approached: [start, end]"""
    learning_rate_final_fraction: float | None = checked(None, Check(lambda v: 0 < v <= 1, "a fraction in (0, 1], or null"))
    """scale every learning rate (actor, critics, temperature) linearly down to this fraction of its value over learning_rate_anneal's env steps (null: they stay)"""
    learning_rate_anneal: list[int] = checked(check=ANNEAL_WINDOW, factory=lambda: [0, 100_000])
    """env steps (frames collected, random ones included) over which learning_rate_final_fraction is approached: [start, end]"""
    policy_average_tau: float | None = checked(None, Check(lambda v: 0 < v <= 1, "a fraction in (0, 1], or null"))
    """act greedily (evaluation, export, a target's confirmation) with a Polyak average of the actor's weights, moved this fraction of the way to the actor's at each actor update (null: the actor itself); collection samples from the actor as trained"""

    def validate_extra(self) -> None:
        check_learning_rate_schedule(self)


def scale_rewards(batch: TensorDictBase, factor: float) -> TensorDictBase:
    """Multiply the batch's ``("next", "reward")`` by ``factor`` (``reward_scale_factor``: only the learning
    sees it; the returns a run reports stay the env's). The batch's entry is replaced, its tensor untouched."""
    if factor != 1.0:
        batch.set(("next", "reward"), batch.get(("next", "reward")) * factor)
    return batch


def _fraction_done(frames: int, window: list[int]) -> float:
    """How far ``frames`` is through a schedule's ``[start, end]`` window of env steps, in [0, 1]."""
    start, end = window
    return min(1.0, max(0.0, (frames - start) / (end - start)))


@config_class(
    initial_collect_steps=10_000,
    replay_buffer_capacity=(10_000, "the tutorial's Reverb table size"),
    num_eval_episodes=20,
)
class SACConfig(ClippedGradientKeys, SACFamilyConfig):
    """SAC's keys; defaults are the actor-learner tutorial's (``SacAgent`` defaults included)."""

    critic_joint_fc_layer_params: list[int] = checked(check=LAYER_SIZES, factory=lambda: [256, 256])
    """hidden layer sizes of each critic (over observation and action joined)"""
    critic_kernel_initializer: str = checked("torch", one_of(*INITIALIZERS))
    """critic weights: 'torch' (nn.Linear's default) or 'glorot_uniform' with zero biases (the actor-learner tutorial's CriticNetwork)"""
    critic_layer_norm: bool = False
    """normalise each critic hidden layer over its features (LayerNorm without weights, before the ReLU), as DroQ's and RLPD's critics do to keep Q-values from running away"""


class SAC(OffPolicyPipeline):
    """Soft actor-critic with learned temperature: TorchRL's ``SACLoss`` + ``SoftUpdate``.

    Args:
        config: a ``SACConfig`` (default: the Minitaur tutorial's, ``preset("sac")``).
        env: a TorchRL env, or a function making one (needed for collector processes and background
            evaluation); batched envs (``SerialEnv``, ``ParallelEnv``) too. Default: ``config.env``.
        eval_env: the env to evaluate on (an env or a function); default: another ``env()``.
        actor: your stochastic policy (a TorchRL ``ProbabilisticActor``, e.g. TanhNormal) writing
            ``"action"`` and ``"action_log_prob"``.
        qvalue: your critic, ``(observation, action) -> "state_action_value"``; SACLoss makes the twin.
        loss_module: your TorchRL ``SACLoss`` (it holds actor and critics; ``actor`` may name its actor).
        observation_key: the observation entry the networks read (default: the actor's in_key, or
            ``"observation"``).

    ``CrossQ`` subclasses it with its own ``make_qvalue``, ``make_loss``, ``make_optimizers``,
    ``make_target_updater`` and ``update``; the agent's shape, the schedules and the averaged policy are these.
    """

    algo = "sac"
    Config = SACConfig
    action_space = "continuous"
    loss_names = ("actor", "qvalue", "alpha", "alpha_value", "entropy")
    config: SACConfig
    loss_module: SACLoss

    def __init__(self, config: SACConfig | None = None, *, env=None, eval_env=None,
                 actor: nn.Module | None = None, qvalue: nn.Module | None = None,
                 loss_module: LossModule | None = None, observation_key: str | None = None):
        super().__init__(config, env=env, eval_env=eval_env,
                         observation_key=observation_key or observation_key_of(actor, loss_module))
        # The actor made here (no actor or loss given) exports as TanhNormalMode of its network alone; a
        # user's actor as the TensorDict module it is.
        self.export_network_only = actor is None and loss_module is None
        self.assemble(lambda: self.build(actor=actor, qvalue=qvalue, loss_module=loss_module))

    # --- the agent ----------------------------------------------------------------------------------

    def build(self, *, actor=None, qvalue=None, loss_module=None) -> Agent:
        """The agent from a user's ``loss_module`` (its actor, unless ``actor`` names another), or from
        ``actor`` and ``qvalue`` (each made here when not given) in ``make_loss`` with the config's discount.
        With ``policy_average_tau`` the greedy policy is a copy of the actor that ``average_policy`` moves."""
        cfg = self.config
        if loss_module is not None:
            if qvalue is not None:
                raise InputError("qvalue is unused when loss_module is given (the loss holds its critics); pass one of them")
            actor = actor if actor is not None else loss_module.actor_network
        else:
            loss_actor = actor
            if actor is None:
                encoder = self.make_encoder()
                actor = loss_actor = make_tanh_normal_actor(self.observation_dim, self.action_spec,
                                                            cfg.actor_fc_layer_params,
                                                            observation_key=self.observation_key, encoder=encoder)
                if qvalue is None and self.shares_encoder():
                    # the loss holds the actor's head on the features the update computes (update)
                    self.shared_encoder, loss_actor = encoder, tanh_normal_head(actor, FEATURES_KEY, self.action_spec)
            loss_module = self.make_loss(loss_actor, qvalue if qvalue is not None else self.make_qvalue())
            loss_module.make_value_estimator(gamma=cfg.gamma)
        greedy = actor if cfg.policy_average_tau is None else copy.deepcopy(actor)
        return Agent(policy=greedy, collect_policy=actor, loss_module=loss_module)

    def assemble(self, build: Callable[[], Agent]) -> None:
        super().assemble(build)
        # Where the schedules start: the loss's entropy target and the optimisers' learning rates as built,
        # before a resume loads moved ones (a user's own loss may carry its own target).
        cfg = self.config
        if cfg.target_entropy_final is not None:
            self._target_entropy_start = float(self.loss_module.target_entropy)
        self._learning_rates = {name: [group["lr"] for group in opt.param_groups]
                                for name, opt in self.optimizers.items()}
        # the greedy policy's parameters and the actor's, paired for average_policy
        self._averaged = (None if cfg.policy_average_tau is None
                          else (list(self.policy.parameters()), list(self.collect_policy.parameters())))

    def export_module(self) -> nn.Module:
        if self.export_network_only:
            return TanhNormalMode.from_actor(self.policy, self.action_spec)
        return TensorDictPolicy(copy.deepcopy(self.policy).cpu(), self.observation_key,
                                observation_ndim=len(self.observation_shape))

    # --- between and after updates ---------------------------------------------------------------------

    def average_policy(self) -> None:
        """Move the averaged greedy policy's weights ``policy_average_tau`` of the way to the actor's
        (the updates call it after each actor step; nothing without ``policy_average_tau``)."""
        if self._averaged is not None:
            lerp_(*self._averaged, self.config.policy_average_tau, fast=self.config.fast)

    def on_frames(self, frames: int) -> None:
        # The schedules, functions of the frames collected (so a resumed run sets the same values), set
        # between updates: outside the update, so that a compiled or graphed update reads the entropy
        # target's buffer rather than baking it in (the learning rates are Python floats the optimiser
        # step reads each time).
        cfg, now = self.config, self.state.frames + frames
        if cfg.target_entropy_final is not None:
            done = _fraction_done(now, cfg.target_entropy_anneal)
            start = self._target_entropy_start
            self.loss_module.target_entropy.fill_(start + done * (cfg.target_entropy_final - start))
        if cfg.learning_rate_final_fraction is not None:
            scale = 1.0 + _fraction_done(now, cfg.learning_rate_anneal) * (cfg.learning_rate_final_fraction - 1.0)
            for name, opt in self.optimizers.items():
                for group, lr in zip(opt.param_groups, self._learning_rates[name]):
                    group["lr"] = lr * scale

    # --- checkpoint state: the averaged policy too ------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        state = super().state_dict()
        if self.config.policy_average_tau is not None:
            state["policy_average"] = self.policy.state_dict()
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        if self.config.policy_average_tau is not None:
            if "policy_average" not in state:
                raise InputError(f"checkpoint does not fit this {self.algo} pipeline and config: it has no averaged "
                                 "policy (policy_average_tau was null when it was written); expected one")
            self.policy.load_state_dict(state["policy_average"])

    # --- SAC's networks, loss and update ------------------------------------------------------------------

    def make_qvalue(self) -> nn.Module:
        cfg = self.config
        key, encoder = self.critic_input()
        return make_qvalue_critic(self.observation_dim, int(self.action_spec.shape[-1]),
                                  cfg.critic_joint_fc_layer_params, observation_key=key,
                                  init=cfg.critic_kernel_initializer, layer_norm=cfg.critic_layer_norm,
                                  encoder=encoder)

    def make_loss(self, actor: nn.Module, qvalue: nn.Module) -> SACLoss:
        cfg = self.config
        # SacAgent's default entropy target: -|A|/2
        target_entropy = cfg.target_entropy if cfg.target_entropy is not None else -self.action_spec.shape[-1] / 2
        return (LeanSACLoss if cfg.fast else SACLoss)(
            actor_network=actor, qvalue_network=qvalue, num_qvalue_nets=2, loss_function="l2",
            alpha_init=cfg.initial_alpha, target_entropy=target_entropy, delay_qvalue=True)

    def make_optimizers(self) -> dict[str, torch.optim.Optimizer]:
        cfg, loss = self.config, self.loss_module
        return {
            "actor": self.adam(loss.actor_network_params.flatten_keys().values(), lr=cfg.actor_learning_rate),
            "qvalue": self.adam(loss.qvalue_network_params.flatten_keys().values(), lr=cfg.critic_learning_rate),
            "alpha": self.adam([loss.log_alpha], lr=cfg.alpha_learning_rate),
            # the shared encoder learns with the critics, at their rate
            **({"encoder": self.adam(self.shared_encoder.parameters(), lr=cfg.critic_learning_rate)}
               if self.shared_encoder is not None else {}),
        }

    def make_target_updater(self):
        return self.soft_update(self.config.target_update_tau)

    def update_periods(self) -> list[int]:
        return [self.config.policy_delay, self.config.target_update_period]

    def update(self, batch: TensorDictBase, update_index: int) -> dict[str, torch.Tensor]:
        """The critics on every update, the actor and the temperature on every ``policy_delay``-th (on the
        others only the critics' loss is computed), then the target critics every ``target_update_period``.
        With a shared encoder (``share_encoder``), its features first (``encode``); it steps with the critics."""
        cfg, loss = self.config, self.loss_module
        batch = scale_rewards(batch, cfg.reward_scale_factor)
        # update_index is a Python int: under torch.compile the delay picks one of two graphs
        actor_step = update_index % cfg.policy_delay == 0
        extras = {}
        if self.shared_encoder is not None:
            batch, features = self.encode(batch)
            losses = {"qvalue": loss.qvalue_v2_loss(batch)[0]}
            if actor_step:
                # the actor's loss reads the features detached: only the critics' loss trains the encoder (DrQ)
                losses["actor"], actor_out = loss.actor_loss(batch.clone(False).set(FEATURES_KEY, features.detach()))
                losses["alpha"] = loss.alpha_loss(actor_out["log_prob"]).mean()
                extras = {"alpha_value": loss.log_alpha.exp(), "entropy": -actor_out["log_prob"].mean()}
        elif actor_step:
            out = loss(batch)
            losses = {"actor": out["loss_actor"], "qvalue": out["loss_qvalue"], "alpha": out["loss_alpha"]}
            extras = {"alpha_value": out["alpha"], "entropy": out["entropy"]}
        else:
            losses = {"qvalue": loss.qvalue_v2_loss(batch)[0]}
        sum(losses.values()).backward()
        stepping = [*losses, "encoder"] if self.shared_encoder is not None else list(losses)
        for name in stepping:  # each gradient tensor clipped (gradient_clipping), then each optimiser's step
            self.clip_gradients(name, cfg.gradient_clipping, stacked=name == "qvalue")
            self.optimizers[name].step()
            self.optimizers[name].zero_grad(set_to_none=True)
        stepped = {name: value.detach() for name, value in losses.items()}
        if actor_step:
            self.average_policy()
            stepped.update({name: value.detach() for name, value in extras.items()})
        if update_index % cfg.target_update_period == 0:
            self.target_updater.step()
        return stepped

preset = SAC.preset
