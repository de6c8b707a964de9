"""The SAC family (``sac.SAC``, ``crossq.CrossQ``): the keys they share and the pipeline shape they share.

Both learn a tanh-normal actor that explores by sampling (collection) and acts by its mode (evaluation,
export), twin critics and a learned temperature, all held by one TorchRL loss (``SACLoss``, ``CrossQLoss``).
``SACFamilyConfig`` holds their shared keys with SAC's defaults (CrossQ's own defaults for them are in its
``config_class``); ``SACFamilyPipeline`` builds the agent from the algorithm's ``make_qvalue`` and
``make_loss``, and holds the schedules (entropy target, learning rates) and the averaged greedy policy.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import Any

from tensordict import TensorDictBase
from torch import nn
from torchrl.objectives import LossModule

from rlpipe.modules.actors import TanhNormalMode, make_tanh_normal_actor, tanh_normal_head
from rlpipe.modules.encoders import FEATURES_KEY
from rlpipe.modules.fast.target_updates import lerp_
from rlpipe.modules.plain_policy import TensorDictPolicy
from rlpipe.pipelines.base import Agent, OffPolicyPipeline
from rlpipe.pipelines.config import (
    ANNEAL_WINDOW,
    LEARNING_RATE,
    ActorKeys,
    Check,
    TrainConfig,
    check_learning_rate_schedule,
    checked,
    config_class,
)
from rlpipe.pipelines.errors import InputError
from rlpipe.pipelines.own_parts import observation_key_of

__all__ = ["SACFamilyConfig", "SACFamilyPipeline", "scale_rewards"]


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


class SACFamilyPipeline(OffPolicyPipeline):
    """SAC's and CrossQ's shared shape. An algorithm of the family supplies ``make_qvalue()`` (one critic; the
    loss makes the twin), ``make_loss(actor, qvalue)``, ``make_optimizers()`` and ``update``.

    Args:
        config: the algorithm's config (default: its tutorial's preset).
        env: a TorchRL env, or a function making one (needed for collector processes and background
            evaluation); batched envs (``SerialEnv``, ``ParallelEnv``) too. Default: ``config.env``.
        eval_env: the env to evaluate on (an env or a function); default: another ``env()``.
        actor: your stochastic policy (a TorchRL ``ProbabilisticActor``, e.g. TanhNormal) writing
            ``"action"`` and ``"action_log_prob"``.
        qvalue: your critic, ``(observation, action) -> "state_action_value"``; the loss makes the twin.
        loss_module: your TorchRL loss of the algorithm (it holds actor and critics; ``actor`` may name its actor).
        observation_key: the observation entry the networks read (default: the actor's in_key, or
            ``"observation"``).
    """

    config: SACFamilyConfig

    def __init__(self, config: SACFamilyConfig | None = None, *, env=None, eval_env=None,
                 actor: nn.Module | None = None, qvalue: nn.Module | None = None,
                 loss_module: LossModule | None = None, observation_key: str | None = None):
        super().__init__(config, env=env, eval_env=eval_env,
                         observation_key=observation_key or observation_key_of(actor, loss_module))
        # The actor made here (no actor or loss given) exports as TanhNormalMode of its network alone; a
        # user's actor as the TensorDict module it is.
        self.export_network_only = actor is None and loss_module is None
        self.assemble(lambda: self.build(actor=actor, qvalue=qvalue, loss_module=loss_module))

    # --- what an algorithm of the family supplies -----------------------------------------------------

    def make_qvalue(self) -> nn.Module:
        """One critic, ``(observation, action) -> "state_action_value"``; with a shared encoder, ``(features,
        action)``, the features under ``FEATURES_KEY`` (``critic_input``)."""
        raise NotImplementedError

    def make_loss(self, actor: nn.Module, qvalue: nn.Module) -> LossModule:
        """The algorithm's TorchRL loss over ``actor`` and twin copies of ``qvalue``."""
        raise NotImplementedError

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
