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

import dataclasses
import warnings
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
    CollectorConfig,
    PresetInfo,
    TrainConfig,
    check_learning_rate_schedule,
    checked,
    one_of,
)

__all__ = ["SACConfig", "SAC", "PRESETS", "PRESET_INFO", "preset"]


@dataclass
class SACConfig(TrainConfig):
    """SAC's keys; defaults are the actor-learner tutorial's (``SacAgent`` defaults included)."""

    # shared keys whose value here differs from TrainConfig's (their rules stay TrainConfig's)
    env: str = "MinitaurBulletEnv-v0"
    """gymnasium env id with a continuous (Box) action space"""
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


def _minitaur() -> SACConfig:
    # The actor-learner tutorial: MinitaurBulletEnv-v0, 100k iterations, 10k random steps,
    # replay 10k, batch 256, lr 3e-4 x3, tau 0.005, gamma 0.99, eval every 10k over 20 episodes,
    # policy saved every 5k. On CPU the update (~15 ms) is the bottleneck, so the env steps in a
    # collector process beside it (async), and evaluation runs in another process on a snapshot.
    return SACConfig(collector=CollectorConfig(workers=1, sync=False), eval_in_background=True)


def _halfcheetah() -> SACConfig:
    # SAC paper (Haarnoja et al. 2018, v2 table): 1M replay, batch 256, lr 3e-4, tau 0.005,
    # (256, 256) networks, target entropy -|A|, 10k random steps; 1M steps in the paper.
    return SACConfig(
        env="HalfCheetah-v5", num_iterations=1_000_000, initial_collect_steps=10_000,
        replay_buffer_capacity=1_000_000, target_entropy=-6.0, eval_interval=10_000,
        num_eval_episodes=10, checkpoint_interval=50_000, policy_save_interval=50_000,
    )


def _hopper() -> SACConfig:
    return SACConfig(
        env="Hopper-v5", num_iterations=1_000_000, initial_collect_steps=10_000,
        replay_buffer_capacity=1_000_000, target_entropy=-3.0, eval_interval=10_000,
        num_eval_episodes=10, checkpoint_interval=50_000, policy_save_interval=50_000,
    )


def _minitaur_002() -> SACConfig:
    # The older SAC-on-Minitaur tutorial (drivers, TFUniformReplayBuffer), whose printed log the
    # live log can be compared with: the same agent as the actor-learner one, but the initial 10k
    # steps come from the collect policy (a DynamicStepDriver with tf_agent.collect_policy), a
    # 1M-transition replay, a loss line every 5,000 steps, 30 evaluation episodes every 10,000,
    # gradient_clipping=None; its CriticNetwork keeps TF-Agents' default initialisers (not Glorot).
    # Collection in the learner's process, as its single driver did.
    return SACConfig(
        initial_collect_policy="collect", replay_buffer_capacity=1_000_000, log_interval=5000,
        num_eval_episodes=30, eval_interval=10_000, gradient_clipping=None,
    )


def _sized(env: str, **keys) -> SACConfig:
    """A preset sized for time to a target on a small CPU machine: what every such preset shares.

    No untrained evaluation, no random baseline, exports only at the end, the thread count named
    (no timing of the loss at start), learning rates 1e-3, the report page written at evaluations and
    at the end, not from log rows (its first write is 1-2 s of a 10-s Pendulum run; runs of many
    minutes keep ``live_report``); each preset adds what its task needs.
    Evaluations are sparse: 10 greedy Pendulum episodes in the learner's process are 2,000 env
    steps, the cost of ~1,000 iterations when the target comes at ~3,000-4,000.
    """
    defaults = dict(actor_learning_rate=1e-3, critic_learning_rate=1e-3, alpha_learning_rate=1e-3,
                    initial_eval=False, baseline_episodes=0, live_report=False, num_eval_episodes=10, num_threads=1,
                    collector=CollectorConfig(workers=1, sync=True))
    return SACConfig(env=env, **{**defaults, **keys})


def _pendulum() -> SACConfig:
    # Pendulum-v1 to -200: 64x64 networks, 1,000 random steps, the env in the learner's process (a
    # collector process takes seconds to start, and Pendulum's cheap step leaves nothing to overlap),
    # target networks 4x faster (tau 0.02) and learning rates 2e-3. Tries of 2026-11-27 (seeds 0-4,
    # `rlpipe train sac-pendulum target_return=-200 seed=S KEY=VALUE`, BENCHMARKS.md): env steps to the
    # target, median, tau 0.005 / lr 1e-3 (the preset before) 4,600 (13.5 s); tau 0.01 3,600 (10.9 s);
    # tau 0.02 + lr 2e-3 3,200 (9.3 s); tau 0.05 + lr 2e-3 3,200 (9.6 s); gamma 0.98, initial alpha 0.5,
    # batch 128, lr 2e-3 alone, 500 random steps, tau 0.05 alone: no fewer than tau 0.01.
    # Then the update made cheaper, as the env step is ~50x cheaper than it: the actor and temperature
    # step on every second update (policy_delay=2) and one update per 2 env steps. Tries of 2026-11-29
    # (seeds 10-17, one run at a time, BENCHMARKS.md): median seconds from launch to the target 10.15
    # (the settings above), 8.05 with the delay (every seed sooner), 7.6 with a delay of 3, 8.15 with 2
    # env steps per update alone, 7.15 with both (4,200 env steps and 1,600 updates against 3,400 and 2,400).
    return _sized("Pendulum-v1", num_iterations=7_500, initial_collect_steps=1000, replay_buffer_capacity=100_000,
                  collect_steps_per_iteration=2, policy_delay=2,
                  actor_fc_layer_params=[64, 64], critic_joint_fc_layer_params=[64, 64], target_update_tau=0.02,
                  actor_learning_rate=2e-3, critic_learning_rate=2e-3, alpha_learning_rate=2e-3,
                  eval_interval=2500, log_interval=250, policy_save_interval=7_500, checkpoint_interval=7_500)


def _inverted_pendulum() -> SACConfig:
    # InvertedPendulum-v5 to 950 (1,000 is the most an episode gives): sac-pendulum's settings (64x64,
    # tau 0.02, learning rates 2e-3) as they were before its delayed actor and 2 env steps per update
    # (not tried here: 4.0x SBX on seeds 100-104 as it is, BENCHMARKS.md). 2026-11-27, `rlpipe train sac-invpendulum target_return=950 seed=S`,
    # seeds 0 and 1: env steps to the target 9,450 and 9,000 (30 and 29 s), against 15,350 and 21,450
    # (53 and 69 s) with tau 0.005 and learning rates 1e-3 (the preset before).
    return _sized("InvertedPendulum-v5", num_iterations=50_000, initial_collect_steps=1000,
                  replay_buffer_capacity=100_000, actor_fc_layer_params=[64, 64],
                  critic_joint_fc_layer_params=[64, 64], target_update_tau=0.02, actor_learning_rate=2e-3,
                  critic_learning_rate=2e-3, alpha_learning_rate=2e-3, eval_interval=5000, log_interval=1000,
                  policy_save_interval=50_000, checkpoint_interval=25_000)


def _halfcheetah_100k() -> SACConfig:
    # HalfCheetah-v5 to 3,000 within 100k env steps: 5,000 random steps instead of 10,000, lr 1e-3, target
    # entropy -|A|, 64x64 networks; the update is the bound, so MuJoCo steps in a collector process beside
    # it and the learner keeps one core. 2026-11-27, `rlpipe train sac-halfcheetah-100k target_return=3000
    # seed=S` (the time-to-return rule): 256x256 (the paper's) 313.8 s, 33,000 env steps (in `rlpipe bench
    # time-to-return`, b90efc6); 128x128 175.7 s (36,000); 64x64 82.3 and 85.1 s (27,000 and 29,000, seeds
    # 0 and 1), each update ~4x cheaper per halving and no more env steps; 2,000 random steps: 81.1 s.
    # Not checked past 3,000 (the paper's 256x256 may plateau higher over 1M steps: `sac-halfcheetah`).
    return _sized("HalfCheetah-v5", num_iterations=95_000, initial_collect_steps=5000,
                  actor_fc_layer_params=[64, 64], critic_joint_fc_layer_params=[64, 64],
                  replay_buffer_capacity=100_000, target_entropy=-6.0, eval_interval=10_000,
                  log_interval=1000, policy_save_interval=95_000, checkpoint_interval=25_000, live_report=True,
                  collector=CollectorConfig(workers=1, sync=False))


def _minitaur_fast() -> SACConfig:
    # MinitaurBulletEnv-v0 to 1.0, then 5, beside the tutorial's `sac`: the tutorial's 10k replay
    # evicts what the walk is learned from after 10 s of collection, so 200k here; 2,000 random
    # steps (two episodes) instead of 10,000; lr 1e-3; evaluation in its own process as in `sac`.
    # Rewards x100 in the update and target entropy 0: Minitaur pays the metres moved in each 10 ms
    # (~1e-3 a step), so the temperature term (-alpha * log_prob, ~-4 alpha a step at the default target
    # of -|A|/2) outweighs the reward until alpha has fallen ~100x, and staying up costs. 2026-11-27,
    # `rlpipe train sac-minitaur target_return=1.0 seed=0` (the time-to-return rule, 900 s cap): without
    # them not reached by 90,000 env steps (two runs); x100 alone 48,700 env steps (481 s, but by a
    # ~100-step lunge); x100 + target entropy 0 51,150 (488 s; greedy episodes 366 steps, 1.66).
    # 64x64 networks: the update is the bound, and it is ~3x cheaper than at 256x256 (~315 env steps/s
    # against ~110) for no more env steps to 1.0 (2026-11-27, seeds 0 and 1: 30,950 and 32,350 env steps,
    # 112 and 110 s, greedy episodes 826 and 678 steps long; 128x128: 34,450 and 42,950, 182 and 220 s;
    # 256x256: 449 and 446 s). In `rlpipe bench time-to-return --tasks minitaur-sac-1 --seeds 5 --peers sbx`
    # (a13faf7, 2026-11-29): 81.8 s median, 5/5 (SBX 2/5 within 90,000 env steps): BENCHMARKS.md.
    # The entropy target then falls from 0 to -|A| (-8) between 40,000 and 100,000 env steps: at 0 the sampled
    # policy walks at 5 while its mean action (the greedy policy the target is judged by) gives 1-2.5
    # (seed 1: training mean 5.4, greedy 2.7 and 1.9, not reached within 600 s, also with a fall to -4 over
    # 30,000-90,000); falling to -8 over 30,000-90,000, seed 1 reached 5 at 101,800 env steps, 321 s (greedy
    # 8.6 over whole episodes at 80,000). It starts at 40,000, past most runs to 1.0 (28,000 env steps median at
    # 5e02349; a run whose greedy policy lags goes past it, 68,600 at most there); starting it at 10,000 (to -8 by
    # 70,000) was no sooner to 1.0 on seeds 0-4 (2026-11-29, BENCHMARKS.md's TF-Agents section).
    return _sized("MinitaurBulletEnv-v0", num_iterations=200_000, initial_collect_steps=2000,
                  reward_scale_factor=100.0, target_entropy=0.0, target_entropy_final=-8.0,
                  target_entropy_anneal=[40_000, 100_000],
                  actor_fc_layer_params=[64, 64], critic_joint_fc_layer_params=[64, 64],
                  replay_buffer_capacity=200_000, eval_interval=10_000, num_eval_episodes=5,
                  eval_in_background=True, log_interval=1000, policy_save_interval=50_000, live_report=True,
                  checkpoint_interval=25_000, collector=CollectorConfig(workers=1, sync=False))


def _minitaur_walk() -> SACConfig:
    # MinitaurBulletEnv-v0 to 5 (a gait, the main job's second target): `sac-minitaur` with 3-step returns
    # (`n_step=3`: the metres of three 10 ms steps reach the critics in one update instead of three) and the
    # greedy policy (evaluations, export, a target's confirmation) a Polyak average of the actor
    # (`policy_average_tau=0.0005`, a window of ~2,000 updates: the actor's greedy action swings between a walk
    # and a fall from one evaluation to the next). `rlpipe bench time-to-return --tasks minitaur-sac-5 --seeds 5
    # --peers none --cap-scale 0.15 n_step=3 policy_average_tau=0.0005` (2026-11-29 at 94bd6eb): 333.4 s median
    # (201.7-614.8), 5 of 5, 4 within 10 minutes, 81,200 env steps median; `sac-minitaur` itself reached 5 on 2
    # seeds of 5 within 190,000 env steps (db76cc4), the averaged greedy policy alone on 2 of 3 (2ff1f9c).
    return dataclasses.replace(_minitaur_fast(), n_step=3, policy_average_tau=0.0005)


PRESETS = {
    "sac": _minitaur, "sac-002": _minitaur_002, "sac-halfcheetah": _halfcheetah, "sac-hopper": _hopper,
    "sac-pendulum": _pendulum, "sac-invpendulum": _inverted_pendulum, "sac-halfcheetah-100k": _halfcheetah_100k,
    "sac-minitaur": _minitaur_fast, "sac-minitaur-5": _minitaur_walk,
}

PRESET_INFO = {
    "sac": PresetInfo("MinitaurBulletEnv-v0", (1.0, 5.0), "TF-Agents' SAC actor-learner tutorial", sized=False),
    "sac-002": PresetInfo("MinitaurBulletEnv-v0", (), "TF-Agents' older SAC Minitaur tutorial (drivers)", sized=False),
    "sac-halfcheetah": PresetInfo("HalfCheetah-v5", (), "the SAC paper's settings, 1M steps", sized=False),
    "sac-hopper": PresetInfo("Hopper-v5", (), "the SAC paper's settings, 1M steps", sized=False),
    "sac-pendulum": PresetInfo("Pendulum-v1", (-200.0,), "sized for time to -200"),
    "sac-invpendulum": PresetInfo("InvertedPendulum-v5", (950.0,), "sized for time to 950"),
    "sac-halfcheetah-100k": PresetInfo("HalfCheetah-v5", (3000.0,), "sized for a return of 3,000 within 100k steps"),
    "sac-minitaur": PresetInfo("MinitaurBulletEnv-v0", (1.0,), "sized for time to 1.0"),
    "sac-minitaur-5": PresetInfo("MinitaurBulletEnv-v0", (5.0,), "sized for time to 5 (a gait)"),
}
"""each preset's task (env, targets); ``rlpipe presets`` and the time-to-return bench read it"""


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
    presets = PRESETS
    preset_info = PRESET_INFO
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


def __getattr__(name: str):
    # clip_gradient_norms moved to rlpipe.modules.optim (DQN clips with it too); the old name goes
    # in the release after 0.2.
    if name == "clip_gradient_norms":
        warnings.warn("rlpipe.pipelines.sac.clip_gradient_norms moved to rlpipe.modules.optim.clip_gradient_norms; "
                      "the old name goes in the next release", DeprecationWarning, stacklevel=2)
        return optim.clip_gradient_norms
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
