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
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import List

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.data import LazyTensorStorage, ReplayBuffer

from rlpipe.envs import describe_action_space, is_discrete
from rlpipe.modules.actors import (
    TanhNormalMode,
    make_deterministic_actor,
    make_exploration_policy,
    make_gaussian_actor,
)
from rlpipe.modules.critics import make_qvalue_critic
from rlpipe.pipelines.config import CollectorConfig, TrainConfig
from rlpipe.pipelines.errors import InputError
from rlpipe.pipelines.loop import OffPolicyPipeline
from rlpipe.pipelines.optim import LeanAdam
from rlpipe.pipelines.td3_loss import TD3AblationLoss, make_target_updater, td3_update

__all__ = ["TD3Config", "TD3", "INGREDIENTS", "PRESETS", "preset"]

INGREDIENTS = (
    "deterministic_policy",
    "experience_replay",
    "target_networks",
    "target_policy_smoothing",
    "delayed_policy_updates",
    "clipped_double_q",
)


@dataclass
class TD3Config(TrainConfig):
    """TD3's keys; defaults are the tutorial's (Pendulum-v1)."""

    env: str = "Pendulum-v1"
    """gymnasium env id with a continuous (Box) action space"""
    num_iterations: int = 90_000
    """iterations after the start-up steps (tutorial: MAX_STEPS=100,000 env steps in all, start-up included)"""
    initial_collect_steps: int = 10_000
    """uniformly random actions for the first env steps (tutorial: startup_time)"""
    learning_starts: int = 256
    """env steps collected before updates begin (tutorial: as soon as the buffer holds one batch)"""
    replay_buffer_capacity: int = 100_000
    """transitions kept, oldest evicted first (tutorial: buffer_size)"""
    batch_size: int = 256
    """transitions per update (tutorial: batch_size)"""
    gamma: float = 0.99
    """discount factor (tutorial: discount)"""
    learning_rate: float = 3e-4
    """Adam learning rate of actor and critics (tutorial: lr)"""
    actor_fc_layer_params: List[int] = field(default_factory=lambda: [256])
    """hidden layer sizes of the actor (tutorial: hidden1_dim=256, hidden2_dim=0)"""
    critic_fc_layer_params: List[int] = field(default_factory=lambda: [256])
    """hidden layer sizes of each critic"""
    exploration_noise: float = 0.1
    """std of the Gaussian exploration noise as a fraction of the half action range (tutorial: expl_noise)"""
    target_update_tau: float = 0.005
    """target networks' soft-update factor (tutorial: tau)"""
    policy_noise: float = 0.2
    """std of the target policy smoothing noise, in half action ranges (tutorial: policy_noise)"""
    noise_clip: float = 0.5
    """the smoothing noise is clipped to +-noise_clip half action ranges (tutorial: noise_clip)"""
    policy_delay: int = 2
    """critic updates per actor and target update (tutorial: policy_freq)"""
    eval_interval: int = 5000
    """iterations between evaluations of the deterministic policy"""
    num_eval_episodes: int = 10
    """episodes per evaluation (tutorial: NEVALS)"""
    log_interval: int = 1000
    """iterations between rows of losses and speed in metrics.csv and TensorBoard"""
    policy_save_interval: int = 5000
    """iterations between exports of the policy (tutorial: LOG_INTERVAL, models saved every 5,000 steps)"""
    checkpoint_interval: int = 5000
    """iterations between checkpoints that `--resume` continues from"""
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

    def validate_extra(self) -> None:
        for key in ("exploration_noise", "policy_noise", "noise_clip"):
            if getattr(self, key) < 0:
                raise InputError(f"{key}={getattr(self, key)}: expected zero or a positive number")
        if self.policy_delay <= 0:
            raise InputError(f"policy_delay={self.policy_delay}: expected a positive integer")


def _collect_beside_learning() -> CollectorConfig:
    # One collector process stepping the env while the learner updates (MultiAsyncCollector): on
    # Pendulum ~1.5x the updates per second of in-process collection, same returns (BENCHMARKS.md).
    return CollectorConfig(sync=False)


def _pendulum() -> TD3Config:
    # The tutorial: Pendulum-v1, 1x256 actor/critics, discount 0.99, expl_noise 0.1, lr 3e-4,
    # 10,000 start-up steps, tau 0.005, policy noise 0.2 clipped at 0.5, policy_freq 2,
    # buffer 100,000, batch 256, 100,000 steps, models saved every 5,000.
    return TD3Config(collector=_collect_beside_learning())


def _mujoco(env: str) -> TD3Config:
    # The TD3 paper (Fujimoto et al. 2018): (400, 300) actor/critics, lr 1e-3, batch 100,
    # 1M replay, expl noise 0.1, 10k (HalfCheetah) / 1k (others) start-up steps, 1M steps,
    # evaluation every 5k steps over 10 episodes.
    return TD3Config(
        env=env,
        num_iterations=1_000_000 - (10_000 if env.startswith("HalfCheetah") else 1000),
        initial_collect_steps=10_000 if env.startswith("HalfCheetah") else 1000,
        learning_starts=10_000 if env.startswith("HalfCheetah") else 1000,
        replay_buffer_capacity=1_000_000,
        batch_size=100,
        learning_rate=1e-3,
        actor_fc_layer_params=[400, 300],
        critic_fc_layer_params=[400, 300],
        checkpoint_interval=50_000,
        policy_save_interval=50_000,
        collector=_collect_beside_learning(),
    )


PRESETS = {
    "td3": _pendulum,
    "td3-halfcheetah": lambda: _mujoco("HalfCheetah-v5"),
    "td3-hopper": lambda: _mujoco("Hopper-v5"),
}


def preset(name: str = "td3") -> TD3Config:
    """A fresh config of the named preset."""
    if name not in PRESETS:
        raise InputError(f"unknown TD3 preset {name!r}; expected one of {', '.join(PRESETS)}")
    return PRESETS[name]()


def _adam(params, lr: float) -> torch.optim.Adam:
    # Fused Adam does the parameter update in one kernel (~10% of a TD3 update on this CPU), and
    # LeanAdam calls it without Optimizer.step's per-call Python (another ~6%): see pipelines/optim.py.
    return LeanAdam(list(params), lr=lr)


class TD3(OffPolicyPipeline):
    """Twin delayed DDPG: TorchRL's ``TD3Loss`` (as ``TD3AblationLoss``) + ``SoftUpdate``."""

    algo = "td3"
    Config = TD3Config
    loss_names = ("qvalue", "actor")

    def check_env(self, env) -> None:
        if is_discrete(env):
            raise InputError(
                f"TD3 needs a continuous (Box) action space; env {self.config.env!r} is {describe_action_space(env)} "
                "(use dqn for discrete actions)"
            )

    def build(self) -> None:
        cfg = self.config
        spec = self.env.action_spec
        action_dim = int(spec.shape[-1])
        if cfg.deterministic_policy:
            self.policy = make_deterministic_actor(self.observation_dim, spec, cfg.actor_fc_layer_params)
            self.collect_policy = make_exploration_policy(self.policy, spec, sigma=cfg.exploration_noise)
        else:
            # Samples in collection (exploration), its deterministic sample in evaluation.
            self.policy = make_gaussian_actor(self.observation_dim, spec, cfg.actor_fc_layer_params)
            self.collect_policy = self.policy
        critic = make_qvalue_critic(self.observation_dim, action_dim, cfg.critic_fc_layer_params)
        self.loss_module = TD3AblationLoss(
            self.policy,
            critic,
            action_spec=spec,
            deterministic_policy=cfg.deterministic_policy,
            target_policy_smoothing=cfg.target_policy_smoothing,
            clipped_double_q=cfg.clipped_double_q,
            policy_noise=cfg.policy_noise,
            noise_clip=cfg.noise_clip,
        )
        self.loss_module.make_value_estimator(gamma=cfg.gamma)
        self.target_updater = make_target_updater(self.loss_module, cfg.target_update_tau, cfg.target_networks)
        self.optimizers = {
            "actor": _adam(self.loss_module.actor_network_params.parameters(), cfg.learning_rate),
            "qvalue": _adam(self.loss_module.qvalue_network_params.parameters(), cfg.learning_rate),
        }

    def make_replay_buffer(self) -> ReplayBuffer:
        if self.config.experience_replay:
            return super().make_replay_buffer()
        # Ingredient 2 off: learn from the latest transition only.
        return ReplayBuffer(storage=LazyTensorStorage(1, device=self.device), batch_size=1)

    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        cfg = self.config
        out = td3_update(
            self.loss_module, batch, self.optimizers["qvalue"], self.optimizers["actor"], self.target_updater,
            update_index=self.counters["updates"] + 1, policy_delay=cfg.policy_delay,
            delayed_policy_updates=cfg.delayed_policy_updates,
        )
        return {name.removeprefix("loss_"): value for name, value in out.items()}

    def export_module(self) -> nn.Module:
        if self.config.deterministic_policy:
            return copy.deepcopy(self.policy.module).cpu()
        return TanhNormalMode.from_actor(self.policy, self.env.action_spec)


PIPELINE = TD3
