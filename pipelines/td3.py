"""TD3 on TorchRL parts, with its six ingredients as switches: the TD3-on-Pendulum tutorial.

    from rlpipe.pipelines import td3
    cfg = td3.preset("td3")                 # the tutorial: Pendulum-v1, 100k steps, collector process
    cfg.clipped_double_q = False            # leave one ingredient out
    result = td3.TD3(cfg).train("runs/td3-no-cdq")

The tutorial's names map onto the keys like this (``startup_time`` -> ``initial_collect_steps``):

    tutorial        key here
    discount        gamma
    expl_noise      exploration_noise
    lr              learning_rate
    startup_time    initial_collect_steps   (random actions; updates start at learning_starts)
    tau             target_update_tau
    policy_noise    policy_noise
    noise_clip      noise_clip
    policy_freq     policy_delay
    buffer_size     replay_buffer_capacity
    batch_size      batch_size
    MAX_STEPS       initial_collect_steps + num_iterations
    hidden1_dim     actor_fc_layer_params / critic_fc_layer_params
    LOG_INTERVAL    policy_save_interval
    NEVALS          num_eval_episodes
"""

from __future__ import annotations

import copy

import torch
from tensordict import TensorDictBase
from tensordict.nn import ProbabilisticTensorDictSequential, TensorDictModule
from torch import nn
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.objectives import TD3Loss

from rlpipe.modules.actors import (
    TanhBoundedMLP,
    TanhNormalMode,
    make_deterministic_actor,
    make_exploration_policy,
    make_gaussian_actor,
    tanh_normal_head,
)
from rlpipe.modules.critics import make_qvalue_critic
from rlpipe.modules.encoders import FEATURES_KEY
from rlpipe.modules.plain_policy import TensorDictPolicy
from rlpipe.modules.td3_loss import TD3AblationLoss
from rlpipe.pipelines.base import Agent, OffPolicyPipeline, observation_key_of
from rlpipe.pipelines.config import (
    NON_NEGATIVE,
    ActorKeys,
    CriticKeys,
    OneRateKeys,
    TrainConfig,
    checked,
    config_class,
)
from rlpipe.pipelines.errors import InputError

__all__ = ["TD3Config", "TD3", "INGREDIENTS", "preset"]

INGREDIENTS = (
    "deterministic_policy",
    "experience_replay",
    "target_networks",
    "target_policy_smoothing",
    "delayed_policy_updates",
    "clipped_double_q",
)


@config_class(
    env=("Pendulum-v1", "an env with a continuous (Box) action space"),
    num_iterations=(90_000, "tutorial: MAX_STEPS=100,000 env steps in all, start-up included"),
    initial_collect_steps=(10_000, "tutorial: startup_time"),
    learning_starts=(256, "tutorial: as soon as the buffer holds one batch"),
    target_update_period=(1, "counted in actor updates: the tutorial's targets move with every actor update"),
    eval_interval=5000,
    checkpoint_interval=5000,
    learning_rate=(3e-4, "the actor's and the critics': the tutorial's lr"),
    actor_fc_layer_params=([256], "tutorial: hidden1_dim=256, hidden2_dim=0"),
    critic_fc_layer_params=[256],
    policy_delay=(2, "critic updates per actor and target update: the tutorial's policy_freq"),
)
class TD3Config(ActorKeys, CriticKeys, OneRateKeys, TrainConfig):
    """TD3's keys; defaults are the tutorial's (Pendulum-v1)."""

    # TD3's own keys
    exploration_noise: float = checked(0.1, NON_NEGATIVE)
    """std of the Gaussian exploration noise as a fraction of the half action range (tutorial: expl_noise)"""
    policy_noise: float = checked(0.2, NON_NEGATIVE)
    """std of the target policy smoothing noise, in half action ranges (tutorial: policy_noise)"""
    noise_clip: float = checked(0.5, NON_NEGATIVE)
    """the smoothing noise is clipped to +-noise_clip half action ranges (tutorial: noise_clip)"""
    deterministic_policy: bool = True
    """ingredient 1; off: a stochastic Gaussian (TanhNormal) policy that explores by sampling instead of added noise"""
    experience_replay: bool = True
    """ingredient 2; off: a buffer of 1 and a batch of 1 (only the latest transition), as the tutorial says"""
    target_networks: bool = True
    """ingredient 3; off: tau = 1, the targets are copies of the online networks"""
    target_policy_smoothing: bool = True
    """ingredient 4; off: no noise on the target action"""
    delayed_policy_updates: bool = True
    """ingredient 5; off: update the actor and targets on every critic update"""
    clipped_double_q: bool = True
    """ingredient 6; off: the target uses the first critic alone (both critics still trained)"""


class TD3(OffPolicyPipeline):
    """Twin delayed DDPG: TorchRL's ``TD3Loss`` (as ``TD3AblationLoss``) + ``SoftUpdate``.

    Args:
        config: a ``TD3Config`` (default: the tutorial's, ``preset("td3")``).
        env: a TorchRL env, or a function making one (needed for collector processes and background
            evaluation); batched envs (``SerialEnv``, ``ParallelEnv``) too. Default: ``config.env``.
        eval_env: the env to evaluate on (an env or a function); default: another ``env()``.
        actor: your deterministic policy writing ``"action"`` inside the action bounds (or, with
            ``deterministic_policy=False``, a stochastic ``ProbabilisticActor``); exploration
            noise is added for collection.
        qvalue: your critic, ``(observation, action) -> "state_action_value"``; TD3 makes the twin.
        loss_module: your TorchRL ``TD3Loss`` (it holds actor and critics; ``actor`` may name its actor).
        observation_key: the observation entry the networks read (default: the actor's in_key, or
            ``"observation"``).
    """

    algo = "td3"
    Config = TD3Config
    action_space = "continuous"
    loss_names = ("qvalue", "actor")

    def __init__(self, config: TD3Config | None = None, *, env=None, eval_env=None, actor: nn.Module | None = None,
                 qvalue: nn.Module | None = None, loss_module: TD3Loss | None = None, observation_key: str | None = None):
        super().__init__(config, env=env, eval_env=eval_env,
                         observation_key=observation_key or observation_key_of(actor, loss_module))
        self.assemble(lambda: self.build(actor=actor, qvalue=qvalue, loss_module=loss_module))

    def build(self, *, actor=None, qvalue=None, loss_module=None) -> Agent:
        cfg, spec, key = self.config, self.action_spec, self.observation_key
        if loss_module is not None:
            if qvalue is not None:
                raise InputError("qvalue is unused when loss_module is given (the loss holds its critics); pass one of them")
            actor = actor if actor is not None else loss_module.actor_network
        loss_actor = actor
        if loss_module is None and actor is None:
            make = make_deterministic_actor if cfg.deterministic_policy else make_gaussian_actor
            encoder = self.make_encoder()
            actor = loss_actor = make(self.observation_dim, spec, cfg.actor_fc_layer_params, observation_key=key,
                                      encoder=encoder)
            self._gaussian_actor_made = not cfg.deterministic_policy  # exported as TanhNormalMode of its MLP
            if qvalue is None and self.shares_encoder():
                # the loss holds the actor's head on the features the update computes (update)
                self.shared_encoder = encoder
                loss_actor = (TensorDictModule(actor.module[1], in_keys=[FEATURES_KEY], out_keys=list(actor.out_keys))
                              if cfg.deterministic_policy else tanh_normal_head(actor, FEATURES_KEY, spec))
        stochastic = isinstance(actor, ProbabilisticTensorDictSequential)
        if cfg.deterministic_policy and stochastic:
            raise InputError("actor is stochastic (a ProbabilisticActor); expected a deterministic one, "
                             "or deterministic_policy=false")
        # A stochastic actor explores by sampling; a deterministic one with Gaussian noise added.
        collect_policy = actor if stochastic else make_exploration_policy(actor, spec, sigma=cfg.exploration_noise)
        if loss_module is None:
            if qvalue is None:
                critic_key, critic_encoder = self.critic_input()
                qvalue = make_qvalue_critic(self.observation_dim, int(spec.shape[-1]), cfg.critic_fc_layer_params,
                                            observation_key=critic_key, encoder=critic_encoder)
            loss_module = TD3AblationLoss(
                loss_actor, qvalue, action_spec=spec,
                deterministic_policy=cfg.deterministic_policy,
                target_policy_smoothing=cfg.target_policy_smoothing,
                clipped_double_q=cfg.clipped_double_q,
                policy_noise=cfg.policy_noise,
                noise_clip=cfg.noise_clip,
                on_tensors=cfg.fast,
            )
            loss_module.make_value_estimator(gamma=cfg.gamma)
        return Agent(policy=actor, collect_policy=collect_policy, loss_module=loss_module)

    def make_optimizers(self) -> dict[str, torch.optim.Optimizer]:
        lr, loss = self.config.learning_rate, self.loss_module
        return {"actor": self.adam(loss.actor_network_params.parameters(), lr=lr),
                "qvalue": self.adam(loss.qvalue_network_params.parameters(), lr=lr),
                # the shared encoder learns with the critics
                **({"encoder": self.adam(self.shared_encoder.parameters(), lr=lr)}
                   if self.shared_encoder is not None else {})}

    def make_target_updater(self):
        return self.soft_update(self.config.target_update_tau, self.config.target_networks)

    def make_replay_buffer(self) -> ReplayBuffer:
        if self.config.experience_replay:
            return super().make_replay_buffer()
        # Ingredient 2 off: learn from the latest transition only.
        return ReplayBuffer(storage=LazyTensorStorage(1, device=self.device), batch_size=1)

    def update_periods(self) -> list[int]:
        actor_every = self.config.policy_delay if self.config.delayed_policy_updates else 1
        return [actor_every, actor_every * self.config.target_update_period]

    def update(self, batch: TensorDictBase, update_index: int) -> dict[str, torch.Tensor]:
        """The tutorial's ``TD3.train`` step: the critics on every update; the actor on every
        ``policy_delay``-th (every one with ``delayed_policy_updates`` off), its loss read from the critics
        just stepped; the targets on every ``target_update_period``-th actor step."""
        cfg, loss, optimizers = self.config, self.loss_module, self.optimizers
        features = None
        if self.shared_encoder is not None:  # its features; the actor's loss reads them detached (DrQ)
            batch, features = self.encode(batch)
        critic_loss = loss.value_loss(batch)[0]
        critic_loss.backward()
        for name in ("qvalue", "encoder") if self.shared_encoder is not None else ("qvalue",):
            optimizers[name].step()
            optimizers[name].zero_grad(set_to_none=True)
        stepped = {"qvalue": critic_loss.detach()}
        actor_every = cfg.policy_delay if cfg.delayed_policy_updates else 1
        if update_index % actor_every == 0:  # a Python int: a compiled update picks one of two graphs
            actor_batch = batch if features is None else batch.clone(False).set(FEATURES_KEY, features.detach())
            actor_loss = loss.actor_loss(actor_batch)[0]
            actor_loss.backward()
            optimizers["actor"].step()
            optimizers["actor"].zero_grad(set_to_none=True)
            stepped["actor"] = actor_loss.detach()
            if update_index % (actor_every * cfg.target_update_period) == 0:
                self.target_updater.step()
        return stepped

    _gaussian_actor_made = False

    def export_module(self) -> nn.Module:
        network = getattr(self.policy, "module", None)
        if type(network) is TanhBoundedMLP:  # make_deterministic_actor's: its network alone, on tensors
            return copy.deepcopy(network).cpu()
        if self._gaussian_actor_made:
            return TanhNormalMode.from_actor(self.policy, self.action_spec)
        return TensorDictPolicy(copy.deepcopy(self.policy).cpu(), self.observation_key,
                                observation_ndim=len(self.observation_shape))


preset = TD3.preset
