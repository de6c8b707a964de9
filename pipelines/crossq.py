"""CrossQ on TorchRL parts: SAC without target networks, its critics batch-renormalised.

    from rlpipe.pipelines import crossq
    result = crossq.CrossQ(crossq.preset("crossq-pendulum")).train("runs/crossq-pendulum")

CrossQ (Bhatt et al., ICLR 2024) is SAC's actor and temperature with critics that carry batch
renormalisation (``BatchRenorm1d`` on their input and after each hidden layer) and no target
networks: the critics judge (s, a) and (s', a') in one joint forward pass, so both halves are
normalised with the same batch statistics, which is what lets the target come from the online
critics. TorchRL's ``CrossQLoss`` computes exactly that; this pipeline adds sb3-contrib's settings
(Adam betas (0.5, 0.999), learning rates 1e-3, the actor and temperature updated every
``policy_delay`` critic updates, one update per env step) and critics sized for a CPU. The pipeline is
``sac.SAC`` (its actor, schedules and averaged greedy policy) with the critics, the loss, the optimisers and
the update replaced.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.objectives import CrossQLoss

from rlpipe.modules.critics import make_batchrenorm_critic
from rlpipe.modules.fast.crossq_loss import LeanCrossQLoss
from rlpipe.pipelines.config import NON_NEGATIVE, Check, CriticKeys, checked, config_class
from rlpipe.pipelines.errors import InputError
from rlpipe.pipelines.sac import SAC, SACFamilyConfig, scale_rewards

__all__ = ["CrossQConfig", "CrossQ", "preset"]


@config_class(
    initial_collect_steps=5000,
    replay_buffer_capacity=1_000_000,
    actor_learning_rate=1e-3,
    critic_learning_rate=1e-3,
    alpha_learning_rate=1e-3,
    policy_delay=(3, "sb3-contrib's 3"),
    target_entropy=(None, "null: -|A|, as sb3-contrib's"),
    critic_fc_layer_params=([256, 256], "each layer followed by BatchRenorm1d and ReLU; the paper's and TorchRL's "
                                        "2048x2048, sb3-contrib's 1024x1024, are costly on a CPU"),
)
class CrossQConfig(CriticKeys, SACFamilyConfig):
    """CrossQ's keys; defaults are sb3-contrib's ``CrossQ`` but for the critic widths (CPU-sized).
    ``target_update_tau`` and ``target_update_period`` are unused: CrossQ has no target networks."""

    # CrossQ's own keys
    adam_beta1: float = checked(0.5, Check(lambda v: 0.0 <= v < 1.0, "a value in [0, 1)"))
    """Adam's first-moment decay for all three optimisers (CrossQ's 0.5; Adam's own default 0.9); beta2 stays 0.999"""
    batch_renorm_momentum: float = checked(0.01, Check(lambda v: 0.0 < v <= 1.0, "a momentum in (0, 1]"))
    """how fast BatchRenorm1d's running mean and variance follow the batches"""
    batch_renorm_warmup_steps: int = checked(100_000, NON_NEGATIVE)
    """critic updates during which BatchRenorm1d normalises as plain batch norm, before its running statistics take over (sb3-contrib's 100,000; 0: from the start)"""


class CrossQ(SAC):
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
    config: CrossQConfig  # type: ignore[assignment]  # SAC's shape, CrossQ's keys
    loss_module: CrossQLoss

    def make_qvalue(self) -> nn.Module:
        cfg = self.config
        if self.encodes_images or self.normalizer is not None:
            image = self.image_shape or sorted(self.image_entries)
            what = f"an image {image}" if self.encodes_images else "normalize_observations=true"
            raise InputError(f"CrossQ's batch-renormalised critic reads the env's vectors as they are; env {cfg.env!r} "
                             f"with {what}: expected sac or td3 (or normalize_observations=false)")
        return make_batchrenorm_critic(self.observation_dim, int(self.action_spec.shape[-1]), cfg.critic_fc_layer_params,
                                       observation_key=self.observation_key, momentum=cfg.batch_renorm_momentum,
                                       warmup_steps=cfg.batch_renorm_warmup_steps, fast=cfg.fast)

    def make_loss(self, actor: nn.Module, qvalue: nn.Module) -> CrossQLoss:
        cfg, spec = self.config, self.action_spec
        target_entropy = cfg.target_entropy if cfg.target_entropy is not None else -float(spec.shape[-1])
        return (LeanCrossQLoss if cfg.fast else CrossQLoss)(actor, qvalue, num_qvalue_nets=2, loss_function="l2", alpha_init=cfg.initial_alpha,
                              target_entropy=target_entropy, action_spec=spec)

    def make_optimizers(self) -> dict[str, torch.optim.Optimizer]:
        cfg, loss = self.config, self.loss_module
        betas = (cfg.adam_beta1, 0.999)
        # parameters() only: the critics' BatchRenorm statistics are buffers, moved by the forward pass
        return {
            "actor": self.adam(loss.actor_network_params.parameters(), lr=cfg.actor_learning_rate, betas=betas),
            "qvalue": self.adam(loss.qvalue_network_params.parameters(), lr=cfg.critic_learning_rate,
                               betas=betas),
            "alpha": self.adam([loss.log_alpha], lr=cfg.alpha_learning_rate, betas=betas),
        }

    def make_target_updater(self):
        return None  # no target networks

    def update_periods(self) -> list[int]:
        return [self.config.policy_delay]

    def update(self, batch: TensorDictBase, update_index: int) -> dict[str, torch.Tensor]:
        """The critics on every update (no target networks: (s, a) and (s', a') in one pass), the actor and
        the temperature on every ``policy_delay``-th."""
        loss = self.loss_module
        batch = scale_rewards(batch, self.config.reward_scale_factor)
        losses = {"qvalue": loss.qvalue_loss(batch)[0]}
        actor_step = update_index % self.config.policy_delay == 0
        if actor_step:
            # The actor's loss reads the critics (eval mode, detached parameters) before they step.
            losses["actor"], meta = loss.actor_loss(batch)
            losses["alpha"] = loss.alpha_loss(meta["log_prob"], tensordict=batch)
            measured = {"alpha_value": loss.log_alpha.detach().exp(), "entropy": -meta["log_prob"].mean()}
        sum(losses.values()).backward()
        for name in losses:
            self.optimizers[name].step()
            self.optimizers[name].zero_grad(set_to_none=True)
        stepped = {name: value.detach() for name, value in losses.items()}
        if actor_step:
            self.average_policy()
            stepped.update(measured)
        return stepped


preset = CrossQ.preset
