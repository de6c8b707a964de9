"""DQN on TorchRL parts: TF-Agents' DQN tutorial (CartPole) as a pipeline.

    from rlpipe.pipelines import dqn
    result = dqn.DQN(dqn.preset("dqn")).train("runs/dqn")
    result.policy            # greedy TensorDict policy
    result.summary["final_average_return"]

The pieces are TorchRL's: ``QValueActor`` over an MLP (TF-Agents' ``QNetwork``), ``EGreedyModule``
for the collect policy, ``DQNLoss`` with the element-wise squared TD error, ``SoftUpdate`` for the
target network (a copy with tau=1, every ``target_update_period`` updates), ``Adam``. Hand in your own env, Q-network or loss to use
them instead (``DQN(config, env=..., actor=..., loss_module=...)``).
"""

from __future__ import annotations

import copy

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.modules import QValueActor
from torchrl.objectives import DQNLoss

from rlpipe.modules import epsilon_greedy, make_qvalue_actor
from rlpipe.modules.fast.dqn_loss import LeanDQNLoss
from rlpipe.modules.fast.exploration import anneal_epsilon
from rlpipe.modules.plain_policy import TensorDictPolicy
from rlpipe.pipelines.base import Agent, OffPolicyPipeline, observation_key_of
from rlpipe.pipelines.config import (
    LAYER_SIZES,
    POSITIVE,
    PROBABILITY,
    ClippedGradientKeys,
    OneRateKeys,
    TrainConfig,
    checked,
    config_class,
    one_of,
)
from rlpipe.pipelines.errors import InputError

__all__ = ["DQNConfig", "DQN", "preset"]


@config_class(
    env="CartPole-v0",
    num_iterations=20_000,
    batch_size=64,
    gamma=(1.0, "DqnAgent's default, which the tutorial relies on"),
    target_update_tau=(1.0, "DqnAgent's default: a copy of the online network"),
    eval_interval=1000,
    log_interval=200,
    checkpoint_interval=5000,
    learning_rate=(1e-3, "of the Q-network"),
)
class DQNConfig(OneRateKeys, ClippedGradientKeys, TrainConfig):
    """DQN's keys; defaults are the tutorial's (``DqnAgent`` defaults included)."""

    # DQN's own keys
    fc_layer_params: list[int] = checked(check=LAYER_SIZES, factory=lambda: [100])
    """hidden layer sizes of the Q-network"""
    epsilon_greedy: float = checked(0.1, PROBABILITY)
    """probability of a random action in the collect policy"""
    epsilon_greedy_end: float | None = checked(None, PROBABILITY)
    """if set, epsilon decays linearly from `epsilon_greedy` to this value over `epsilon_decay_steps` env steps"""
    epsilon_decay_steps: int = checked(1, POSITIVE)
    """env steps over which epsilon decays (with `epsilon_greedy_end`)"""
    td_errors_loss: str = checked("l2", one_of("l2", "smooth_l1"))
    """TD error loss: 'l2' (element-wise squared, the tutorial's) or 'smooth_l1' (Huber)"""
    double_dqn: bool = False
    """use the online network to pick the next action (Double DQN)"""
    clip_rewards: bool = False
    """clip each reward to its sign (-1, 0, 1) in the loss, as the Nature DQN and CleanRL's dqn_atari.py do for Atari; the returns a run reports stay the env's (the game's score)"""


class _GreedyPolicy(nn.Module):
    """The exported policy: observations -> index of the highest Q-value."""

    def __init__(self, qnet: nn.Module):
        super().__init__()
        self.qnet = qnet

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return self.qnet(observation).argmax(-1)


class DQN(OffPolicyPipeline):
    """Deep Q-learning: epsilon-greedy collection, greedy evaluation, TorchRL's ``DQNLoss``.

    Args:
        config: a ``DQNConfig`` (default: the tutorial's, ``preset("dqn")``).
        env: a TorchRL env, or a function making one (needed for collector processes and background
            evaluation); batched envs (``SerialEnv``, ``ParallelEnv``) too. Default: ``config.env``.
        eval_env: the env to evaluate on (an env or a function); default: another ``env()``.
        actor: your Q-value policy (e.g. a TorchRL ``QValueActor``) writing ``"action"`` and
            ``"action_value"``; or
        qvalue: your Q-network, a plain ``nn.Module`` mapping observations to one value per action
            (TF-Agents' ``QNetwork``), wrapped here in a ``QValueActor``.
        loss_module: your TorchRL ``DQNLoss``; it keeps its own value estimator and target network
            settings. Its ``value_network`` is the policy unless ``actor`` names it.
        observation_key: the observation entry the networks read (default: the actor's in_key, or
            ``"observation"``).
    """

    algo = "dqn"
    Config = DQNConfig
    action_space = "discrete"
    loss_names = ("loss",)

    def __init__(self, config: DQNConfig | None = None, *, env=None, eval_env=None, actor: nn.Module | None = None,
                 qvalue: nn.Module | None = None, loss_module: DQNLoss | None = None, observation_key: str | None = None):
        super().__init__(config, env=env, eval_env=eval_env,
                         observation_key=observation_key or observation_key_of(actor, loss_module))
        self.assemble(lambda: self.build(actor=actor, qvalue=qvalue, loss_module=loss_module))

    def build(self, *, actor=None, qvalue=None, loss_module=None) -> Agent:
        cfg, spec = self.config, self.action_spec
        if qvalue is not None and (actor is not None or loss_module is not None):
            raise InputError("qvalue is a bare Q-network for DQN to wrap; pass it alone, not with actor or loss_module")
        if qvalue is not None:
            actor = QValueActor(qvalue, in_keys=[self.observation_key], spec=spec)
        if actor is None:
            actor = (loss_module.value_network if loss_module is not None  # the network the given loss trains
                     else make_qvalue_actor(self.observation_dim, spec, cfg.fc_layer_params,
                                            observation_key=self.observation_key, encoder=self.make_encoder()))
        if loss_module is None:
            # A target network updated with tau=1 after every update equals the online network, so the
            # loss can read the online one directly: same result, two fewer copies per update.
            has_target = not (cfg.target_update_tau == 1.0 and cfg.target_update_period == 1)
            # DQNLoss computed on tensors (modules/fast/dqn_loss.py): the same numbers, ~1 ms less per update.
            loss_module = (LeanDQNLoss if cfg.fast else DQNLoss)(actor, loss_function=cfg.td_errors_loss, delay_value=has_target,
                                      double_dqn=cfg.double_dqn, action_space=spec)
            loss_module.make_value_estimator(gamma=cfg.gamma)
        collect_policy = epsilon_greedy(actor, spec, cfg.epsilon_greedy, cfg.epsilon_greedy_end, cfg.epsilon_decay_steps,
                                        fast=cfg.fast)
        return Agent(policy=actor, collect_policy=collect_policy, loss_module=loss_module)

    def make_optimizers(self) -> dict[str, torch.optim.Optimizer]:
        return {"q": self.adam(self.loss_module.parameters(), lr=self.config.learning_rate)}

    def make_target_updater(self):
        if not self.loss_module.delay_value:
            return None
        # TorchRL's HardUpdate is not used for tau=1: its step() copies on every second call only (a
        # Python counter), so targets moved every 2 * target_update_period updates; and that counter
        # is Python state a CUDA graph cannot replay. A lerp with weight 1 copies exactly.
        return self.soft_update(self.config.target_update_tau)

    def update(self, batch: TensorDictBase, update_index: int) -> dict[str, torch.Tensor]:
        """The Q-network's TD step, then the target network every ``target_update_period`` updates."""
        loss_module = self.loss_module
        if self.config.clip_rewards:  # the batch's entry replaced, the buffer's tensor untouched
            batch.set(("next", "reward"), batch.get(("next", "reward")).sign())
        # LeanDQNLoss's forward without the module call and the TensorDict around its loss (~15 us an update)
        lean = type(loss_module) is LeanDQNLoss and loss_module.lean_call
        loss = loss_module.lean_loss(batch) if lean else loss_module(batch)["loss"]
        loss.backward()
        self.clip_gradients("q", self.config.gradient_clipping)
        self.optimizers["q"].step()
        self.optimizers["q"].zero_grad(set_to_none=True)
        if self.target_updater is not None and update_index % self.config.target_update_period == 0:
            self.target_updater.step()
        return {"loss": loss.detach()}

    def on_frames(self, frames: int) -> None:
        if self.config.epsilon_greedy_end is not None:
            anneal_epsilon(self.collect_policy[-1], frames, fast=self.config.fast)  # EGreedyModule.step's values

    def export_module(self) -> nn.Module:
        if isinstance(self.policy, QValueActor):
            return _GreedyPolicy(copy.deepcopy(self.policy.module[0]).cpu())
        return TensorDictPolicy(copy.deepcopy(self.policy).cpu(), self.observation_key,
                                observation_ndim=len(self.observation_shape))


preset = DQN.preset
