"""SAC on TorchRL parts: TF-Agents' SAC-on-Minitaur tutorial (actor-learner API) as a pipeline.

    from rlpipe.pipelines import sac
    result = sac.SAC(sac.preset("sac")).train("runs/sac-minitaur")

TF-Agents' actor processes feeding a Reverb table become TorchRL collectors
(``collector.workers=N``, ``collector.sync=false`` for ``MultiAsyncCollector``) feeding a TorchRL
replay buffer; its ``SacAgent`` becomes TorchRL's ``SACLoss`` (TanhNormal actor, twin critics,
learned temperature; ``LeanSACLoss``, the same loss computed on tensors, unless you pass your own)
with a soft target update; its Learner and triggers are the shared loop.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.objectives import SACLoss

from rlpipe.modules import optim
from rlpipe.modules.critics import INITIALIZERS, make_qvalue_critic
from rlpipe.modules.optim import LeanAdam
from rlpipe.modules.sac_loss import LeanSACLoss
from rlpipe.modules.target_updates import make_target_updater
from rlpipe.modules.tensor_nets import bootstrap_discount, importance_weights
from rlpipe.pipelines.base import Agent, TanhNormalPipeline, observation_key_of, scale_rewards
from rlpipe.pipelines.config import (
    ANNEAL_WINDOW,
    GRADIENT_CLIPPING,
    LAYER_SIZES,
    LEARNING_RATE,
    POSITIVE,
    Check,
    TrainConfig,
    check_learning_rate_schedule,
    checked,
    one_of,
)

__all__ = ["SACConfig", "SAC", "preset"]


@dataclass
class SACConfig(TrainConfig):
    """SAC's keys; defaults are the actor-learner tutorial's (``SacAgent`` defaults included)."""

    # shared keys whose value here differs from TrainConfig's (their rules stay TrainConfig's)
    env: str = "MinitaurBulletEnv-v0"
    """gymnasium env id, or your own env (`my_package.envs:MyArm`, `my_package:MyArm-v0`; see `env_kwargs`), with a continuous (Box) action space"""
    initial_collect_steps: int = 10_000
    replay_buffer_capacity: int = 10_000
    """transitions kept; the oldest are evicted first (the tutorial's Reverb table size)"""
    num_eval_episodes: int = 20
    baseline_episodes: int = 5
    """episodes of the random agent played once before training for its baseline return (RUN/baseline.json); 5 rather than num_eval_episodes: 20 random Minitaur episodes are ~70 s before the first update, for a baseline the SAC tutorial does not have; -1: num_eval_episodes; 0: none"""
    # SAC's own keys
    actor_learning_rate: float = checked(3e-4, LEARNING_RATE)
    """Adam learning rate of the actor"""
    critic_learning_rate: float = checked(3e-4, LEARNING_RATE)
    """Adam learning rate of the twin critics"""
    alpha_learning_rate: float = checked(3e-4, LEARNING_RATE)
    """Adam learning rate of the entropy temperature"""
    reward_scale_factor: float = checked(1.0, Check(lambda v: v != 0, "a non-zero scale"))
    """rewards are multiplied by this in the critic's target"""
    actor_fc_layer_params: list[int] = checked(check=LAYER_SIZES, factory=lambda: [256, 256])
    """hidden layer sizes of the actor"""
    critic_joint_fc_layer_params: list[int] = checked(check=LAYER_SIZES, factory=lambda: [256, 256])
    """hidden layer sizes of each critic (over observation and action joined)"""
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
    gradient_clipping: float | None = checked(None, GRADIENT_CLIPPING)
    """clip each gradient tensor's norm to this value before the optimisers step, as SacAgent's gradient_clipping does (TF-Agents' clip_gradient_norms); null: no clipping"""
    critic_kernel_initializer: str = checked("torch", one_of(*INITIALIZERS))
    """critic weights: 'torch' (nn.Linear's default) or 'glorot_uniform' with zero biases (the actor-learner tutorial's CriticNetwork)"""
    critic_layer_norm: bool = False
    """normalise each critic hidden layer over its features (LayerNorm without weights, before the ReLU), as DroQ's and RLPD's critics do to keep Q-values from running away"""
    policy_delay: int = checked(1, POSITIVE)
    """update the actor and the temperature (and the averaged greedy policy) on every policy_delay-th update only, the critics on every one (TD3's delayed policy updates, CrossQ's policy_delay); 1: every update, as SAC and the tutorial do"""

    def validate_extra(self) -> None:
        check_learning_rate_schedule(self)


class SAC(TanhNormalPipeline):
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
    """

    algo = "sac"
    Config = SACConfig
    action_space = "continuous"
    loss_names = ("actor", "qvalue", "alpha", "alpha_value", "entropy")

    def __init__(self, config: SACConfig | None = None, *, env=None, eval_env=None, actor: nn.Module | None = None,
                 qvalue: nn.Module | None = None, loss_module: SACLoss | None = None, observation_key: str | None = None):
        super().__init__(config, env=env, eval_env=eval_env,
                         observation_key=observation_key or observation_key_of(actor, loss_module))
        self.assemble(lambda: self.build(actor=actor, qvalue=qvalue, loss_module=loss_module))

    def build(self, *, actor=None, qvalue=None, loss_module=None) -> Agent:
        cfg, key = self.config, self.observation_key
        action_dim = int(self.action_spec.shape[-1])
        target_entropy = cfg.target_entropy if cfg.target_entropy is not None else -action_dim / 2
        return self.build_agent(
            actor=actor, qvalue=qvalue, loss_module=loss_module,
            make_qvalue=lambda: make_qvalue_critic(self.observation_dim, action_dim, cfg.critic_joint_fc_layer_params,
                                                   observation_key=key, init=cfg.critic_kernel_initializer,
                                                   layer_norm=cfg.critic_layer_norm),
            make_loss=lambda actor, qvalue: LeanSACLoss(actor_network=actor, qvalue_network=qvalue, num_qvalue_nets=2,
                                                        loss_function="l2", alpha_init=cfg.initial_alpha,
                                                        target_entropy=target_entropy, delay_qvalue=True))

    def make_optimizers(self) -> dict[str, torch.optim.Optimizer]:
        # Adam's fused kernel without Optimizer.step's per-call Python (modules/optim.py); the
        # same arithmetic as torch.optim.Adam(fused=True).
        cfg, loss = self.config, self.loss_module
        return {
            "actor": LeanAdam(list(loss.actor_network_params.flatten_keys().values()), lr=cfg.actor_learning_rate),
            "qvalue": LeanAdam(list(loss.qvalue_network_params.flatten_keys().values()), lr=cfg.critic_learning_rate),
            "alpha": LeanAdam([loss.log_alpha], lr=cfg.alpha_learning_rate),
        }

    def make_target_updater(self):
        return make_target_updater(self.loss_module, self.config.target_update_tau)

    def update_periods(self) -> list[int]:
        return [self.config.policy_delay, self.config.target_update_period]

    def update(self, batch: TensorDictBase, update_index: int) -> dict[str, torch.Tensor]:
        cfg, loss_module = self.config, self.loss_module
        # update_index is a Python int: under torch.compile the delay picks one of two graphs
        actor_step = update_index % cfg.policy_delay == 0
        if isinstance(loss_module, LeanSACLoss) and loss_module.lean:
            obs, action, next_obs, reward, terminated = loss_module.tensors_from(batch)
            if cfg.reward_scale_factor != 1.0:
                reward = reward * cfg.reward_scale_factor
            out = loss_module.losses(obs, action, next_obs, reward, terminated,
                                     weights=importance_weights(loss_module, batch), actor=actor_step,
                                     discount=bootstrap_discount(loss_module, batch, reward.squeeze(-1)))
        else:
            # a stock SACLoss computes every loss; off the actor's steps only the critics' is used (its
            # target is computed without gradients, so nothing reaches the actor or the temperature)
            out = loss_module(scale_rewards(batch, cfg.reward_scale_factor))
        names = ("actor", "qvalue", "alpha") if actor_step else ("qvalue",)
        sum(out[f"loss_{name}"] for name in names).backward()
        for name in names:
            opt = self.optimizers[name]
            if cfg.gradient_clipping is not None:
                params = [p for group in opt.param_groups for p in group["params"]]
                # the twin critics' parameters are stacked [2, ...]: each critic's tensor on its own
                optim.clip_gradient_norms(params, cfg.gradient_clipping, stacked=name == "qvalue")
            opt.step()
            opt.zero_grad(set_to_none=True)
        if actor_step:
            self.average_policy()
        if update_index % cfg.target_update_period == 0:
            self.target_updater.step()
        if not actor_step:
            return {"qvalue": out["loss_qvalue"].detach()}
        return {"actor": out["loss_actor"].detach(), "qvalue": out["loss_qvalue"].detach(),
                "alpha": out["loss_alpha"].detach(), "alpha_value": out["alpha"].detach(),
                "entropy": out["entropy"].detach()}


preset = SAC.preset
