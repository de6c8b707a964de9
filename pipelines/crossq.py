"""CrossQ on TorchRL parts: SAC without target networks, its critics batch-renormalised.

    from rlpipe.pipelines import crossq
    result = crossq.CrossQ(crossq.preset("crossq-pendulum")).train("runs/crossq-pendulum")

CrossQ (Bhatt et al., ICLR 2024) is SAC's actor and temperature with critics that carry batch
renormalisation (``BatchRenorm1d`` on their input and after each hidden layer) and no target
networks: the critics judge (s, a) and (s', a') in one joint forward pass, so both halves are
normalised with the same batch statistics, which is what lets the target come from the online
critics. TorchRL's ``CrossQLoss`` computes exactly that; this pipeline adds sb3-contrib's settings
(Adam betas (0.5, 0.999), learning rates 1e-3, the actor and temperature updated every
``policy_delay`` critic updates, one update per env step) and critics sized for a CPU.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.objectives import CrossQLoss

from rlpipe.modules.critics import make_batchrenorm_critic
from rlpipe.modules.crossq_loss import LeanCrossQLoss
from rlpipe.modules.optim import LeanAdam
from rlpipe.pipelines.base import Agent, TanhNormalPipeline, observation_key_of, scale_rewards
from rlpipe.pipelines.config import (
    ANNEAL_WINDOW,
    LAYER_SIZES,
    LEARNING_RATE,
    NON_NEGATIVE,
    POSITIVE,
    Check,
    TrainConfig,
    check_learning_rate_schedule,
    checked,
)

__all__ = ["CrossQConfig", "CrossQ", "preset"]


@dataclass
class CrossQConfig(TrainConfig):
    """CrossQ's keys; defaults are sb3-contrib's ``CrossQ`` but for the critic widths (CPU-sized).
    ``target_update_tau`` and ``target_update_period`` are unused: CrossQ has no target networks."""

    # shared keys whose value here differs from TrainConfig's (their rules stay TrainConfig's)
    env: str = "MinitaurBulletEnv-v0"
    """gymnasium env id, or your own env (`my_package.envs:MyArm`, `my_package:MyArm-v0`; see `env_kwargs`), with a continuous (Box) action space"""
    initial_collect_steps: int = 5000
    replay_buffer_capacity: int = 1_000_000
    """transitions kept; the oldest are evicted first"""
    baseline_episodes: int = 5
    """episodes of the random agent played once before training for its baseline return (RUN/baseline.json); -1: num_eval_episodes; 0: none"""
    # CrossQ's own keys
    actor_learning_rate: float = checked(1e-3, LEARNING_RATE)
    """Adam learning rate of the actor"""
    critic_learning_rate: float = checked(1e-3, LEARNING_RATE)
    """Adam learning rate of the twin critics"""
    alpha_learning_rate: float = checked(1e-3, LEARNING_RATE)
    """Adam learning rate of the entropy temperature"""
    adam_beta1: float = checked(0.5, Check(lambda v: 0.0 <= v < 1.0, "a value in [0, 1)"))
    """Adam's first-moment decay for all three optimisers (CrossQ's 0.5; Adam's own default 0.9); beta2 stays 0.999"""
    policy_delay: int = checked(3, POSITIVE)
    """critic updates per actor and temperature update (sb3-contrib's 3)"""
    actor_fc_layer_params: list[int] = checked(check=LAYER_SIZES, factory=lambda: [256, 256])
    """hidden layer sizes of the actor (no batch normalisation, as sb3-contrib's)"""
    critic_fc_layer_params: list[int] = checked(check=LAYER_SIZES, factory=lambda: [256, 256])
    """hidden layer sizes of each critic, each followed by BatchRenorm1d and ReLU (the paper's and TorchRL's 2048x2048, sb3-contrib's 1024x1024: costly on a CPU)"""
    batch_renorm_momentum: float = checked(0.01, Check(lambda v: 0.0 < v <= 1.0, "a momentum in (0, 1]"))
    """how fast BatchRenorm1d's running mean and variance follow the batches"""
    batch_renorm_warmup_steps: int = checked(100_000, NON_NEGATIVE)
    """critic updates during which BatchRenorm1d normalises as plain batch norm, before its running statistics take over (sb3-contrib's 100,000; 0: from the start)"""
    initial_alpha: float = checked(1.0, Check(lambda v: v > 0, "a positive temperature"))
    """initial entropy temperature"""
    target_entropy: float | None = None
    """entropy target of the temperature (null: -|A|)"""
    target_entropy_final: float | None = None
    """move the entropy target linearly from target_entropy to this over target_entropy_anneal's env steps (null: it stays), as SAC's key"""
    target_entropy_anneal: list[int] = checked(check=ANNEAL_WINDOW, factory=lambda: [0, 100_000])
    """env steps (frames collected, random ones included) over which target_entropy_final is approached: [start, end]"""
    learning_rate_final_fraction: float | None = checked(None, Check(lambda v: 0 < v <= 1, "a fraction in (0, 1], or null"))
    """scale every learning rate (actor, critics, temperature) linearly down to this fraction of its value over learning_rate_anneal's env steps (null: they stay)"""
    learning_rate_anneal: list[int] = checked(check=ANNEAL_WINDOW, factory=lambda: [0, 100_000])
    """env steps (frames collected, random ones included) over which learning_rate_final_fraction is approached: [start, end]"""
    policy_average_tau: float | None = checked(None, Check(lambda v: 0 < v <= 1, "a fraction in (0, 1], or null"))
    """act greedily (evaluation, export, a target's confirmation) with a Polyak average of the actor's weights, moved this fraction of the way to the actor's at each actor update (null: the actor itself); collection samples from the actor as trained"""
    reward_scale_factor: float = checked(1.0, Check(lambda v: v != 0, "a non-zero scale"))
    """rewards are multiplied by this in the update (as SAC's key; reported returns stay the env's)"""

    def validate_extra(self) -> None:
        check_learning_rate_schedule(self)


class CrossQ(TanhNormalPipeline):
    """CrossQ: TorchRL's ``CrossQLoss`` (TanhNormal actor, twin batch-renormalised critics, learned
    temperature, no target networks), the actor and temperature updated every ``policy_delay`` updates.

    Args:
        config: a ``CrossQConfig`` (default: the Minitaur preset, ``preset("crossq")``).
        env: a TorchRL env, or a function making one (needed for collector processes and background
            evaluation); batched envs (``SerialEnv``, ``ParallelEnv``) too. Default: ``config.env``.
        eval_env: the env to evaluate on (an env or a function); default: another ``env()``.
        actor: your stochastic policy (a TorchRL ``ProbabilisticActor``, e.g. TanhNormal) writing
            ``"action"`` and ``"action_log_prob"``; it acts in training mode when collecting, so leave
            batch normalisation out of it (CrossQ's own actor has none).
        qvalue: your critic, ``(observation, action) -> "state_action_value"`` (batch-normalised or
            not); CrossQLoss makes the twin.
        loss_module: your TorchRL ``CrossQLoss`` (it holds actor and critics; ``actor`` may name its actor).
        observation_key: the observation entry the networks read (default: the actor's in_key, or
            ``"observation"``).
    """

    algo = "crossq"
    Config = CrossQConfig
    action_space = "continuous"
    loss_names = ("qvalue", "actor", "alpha", "alpha_value", "entropy")

    def __init__(self, config: CrossQConfig | None = None, *, env=None, eval_env=None, actor: nn.Module | None = None,
                 qvalue: nn.Module | None = None, loss_module: CrossQLoss | None = None,
                 observation_key: str | None = None):
        super().__init__(config, env=env, eval_env=eval_env,
                         observation_key=observation_key or observation_key_of(actor, loss_module))
        self.assemble(lambda: self.build(actor=actor, qvalue=qvalue, loss_module=loss_module))

    def build(self, *, actor=None, qvalue=None, loss_module=None) -> Agent:
        cfg, spec = self.config, self.action_spec
        action_dim = int(spec.shape[-1])
        target_entropy = cfg.target_entropy if cfg.target_entropy is not None else -float(action_dim)
        return self.build_agent(
            actor=actor, qvalue=qvalue, loss_module=loss_module,
            make_qvalue=lambda: make_batchrenorm_critic(self.observation_dim, action_dim, cfg.critic_fc_layer_params,
                                                        observation_key=self.observation_key,
                                                        momentum=cfg.batch_renorm_momentum,
                                                        warmup_steps=cfg.batch_renorm_warmup_steps),
            make_loss=lambda actor, qvalue: LeanCrossQLoss(actor, qvalue, num_qvalue_nets=2, loss_function="l2",
                                                           alpha_init=cfg.initial_alpha, target_entropy=target_entropy,
                                                           action_spec=spec))

    def make_optimizers(self) -> dict[str, torch.optim.Optimizer]:
        cfg, loss = self.config, self.loss_module
        betas = (cfg.adam_beta1, 0.999)
        # parameters() only: the critics' BatchRenorm statistics are buffers, moved by the forward pass
        return {
            "actor": LeanAdam(list(loss.actor_network_params.parameters()), lr=cfg.actor_learning_rate, betas=betas),
            "qvalue": LeanAdam(list(loss.qvalue_network_params.parameters()), lr=cfg.critic_learning_rate,
                               betas=betas),
            "alpha": LeanAdam([loss.log_alpha], lr=cfg.alpha_learning_rate, betas=betas),
        }

    def update_periods(self) -> list[int]:
        return [self.config.policy_delay]

    def update(self, batch: TensorDictBase, update_index: int) -> dict[str, torch.Tensor]:
        loss = self.loss_module
        loss_qvalue, _ = loss.qvalue_loss(scale_rewards(batch, self.config.reward_scale_factor))
        out = {"qvalue": loss_qvalue.detach()}
        if update_index % self.config.policy_delay:
            loss_qvalue.backward()
            names = ("qvalue",)
        else:
            # The actor's loss reads the critics (eval mode, detached parameters) before they step.
            loss_actor, meta = loss.actor_loss(batch)
            loss_alpha = loss.alpha_loss(meta["log_prob"], tensordict=batch)
            (loss_qvalue + loss_actor + loss_alpha).backward()
            names = ("qvalue", "actor", "alpha")
            out.update(actor=loss_actor.detach(), alpha=loss_alpha.detach(), alpha_value=loss.log_alpha.detach().exp(),
                       entropy=-meta["log_prob"].mean())
        for name in names:
            self.optimizers[name].step()
            self.optimizers[name].zero_grad(set_to_none=True)
        if len(names) > 1:
            self.average_policy()
        return out


preset = CrossQ.preset
