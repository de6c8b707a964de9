"""SAC on TorchRL parts: TF-Agents' SAC-on-Minitaur tutorial (actor-learner API) as a pipeline.

    from rlpipe.pipelines import sac
    result = sac.SAC(sac.preset("sac")).train("runs/sac-minitaur")

TF-Agents' actor processes feeding a Reverb table become TorchRL collectors
(``collector.workers=N``, ``collector.sync=false`` for ``MultiAsyncCollector``) feeding a TorchRL
replay buffer; its ``SacAgent`` becomes TorchRL's ``SACLoss`` (TanhNormal actor, twin critics,
learned temperature; ``LeanSACLoss``, the same loss computed on tensors, unless you pass your own)
with a soft target update; its Learner and triggers are the shared loop. What SAC shares with
CrossQ (the actor, the schedules, the averaged greedy policy) is ``sac_family``.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.objectives import SACLoss

from rlpipe.modules.critics import INITIALIZERS, make_qvalue_critic
from rlpipe.modules.encoders import FEATURES_KEY
from rlpipe.modules.fast.sac_loss import LeanSACLoss
from rlpipe.pipelines.config import LAYER_SIZES, ClippedGradientKeys, checked, config_class, one_of
from rlpipe.pipelines.sac_family import SACFamilyConfig, SACFamilyPipeline, scale_rewards

__all__ = ["SACConfig", "SAC", "preset"]


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


class SAC(SACFamilyPipeline):
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
    config: SACConfig
    loss_module: SACLoss

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
