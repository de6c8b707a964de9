"""A run sized from the env and the machine, for an env no preset is sized for.

    rlpipe train env=Reacher-v5              # SAC (a Box action space), sized for Reacher-v5
    rlpipe train sac env=Reacher-v5          # the same, the algorithm named

    from rlpipe.pipelines import sizing
    facts = sizing.measure(cfg)              # what the rule reads, from the env cfg.env names
    config, why = sizing.sized_config("sac", facts)

``measure`` records the facts: observation and action sizes, action bounds, the time limit, the random
agent's return and episode length (5 episodes, seeded apart from any run, so the same on every call), and
the CPUs. ``sized_config`` is a plain function of them, with no timing: the same facts give the same config,
which the run writes to config.json as any other; ``why`` is the line ``rlpipe train`` prints first.

The rule is what the sized presets learned on a 2-core CPU (their tries: BENCHMARKS.md, "Presets sized for
a task"), written once for every env:

- networks 64x64 (every sized preset: each halving of the width made the update ~4x cheaper for no more
  env steps, on HalfCheetah and Minitaur), wider only for an observation wider than 64;
- random steps enough for five random episodes, at least 1,000 and at most 5,000 (Pendulum and
  InvertedPendulum 1,000; HalfCheetah 5,000, where 2,000 was no sooner);
- one learner thread; no untrained evaluation or random baseline; exports at the end;
- one actuator (the pendulums) learns with the pendulum presets' faster target networks and larger
  learning rates (SAC: tau 0.02, 2e-3, the actor on every second update; TD3: tau 0.05, 2e-3), which
  carried over from Pendulum to InvertedPendulum and InvertedDoublePendulum; two or more learn with the
  HalfCheetah preset's learning rates 1e-3, tau 0.005 and (SAC) target entropy -|A| (on Reacher's two the
  pendulum settings missed -5 within 30,000 env steps on seeds 0 and 1, these reached it at 10,500 and
  14,800: BENCHMARKS.md, "The sized default and the development suite");
- SAC and TD3 discount by 0.999 where the random agent plays every episode to a time limit of 1,000 steps or more
  (nothing it does ends one early, so a return is earned over the whole episode), else by 0.99: on Swimmer-v5,
  seeds 0-2 reached 40 at 37,000-48,000 env steps with 0.999, seed 0 not by 60,000 with 0.99 (RL-Zoo's Swimmer
  setting is 0.999 too; BENCHMARKS.md, "The sized default: the tries");
- SAC makes one update per two env steps where the random agent does not play every episode to such a limit
  (it ends them early, or the limit is shorter), one per env step where it does: the 30-minute studies on
  InvertedDoublePendulum-v5 and Reacher-v5 both chose two, which reached their targets sooner on every development
  seed (by 14-51%) and, on the judging seeds 100-104, 16% and 10% sooner in the median (on 4 and 3 seeds of 5),
  while on Swimmer-v5 and HalfCheetah-v5, whose random agents run every episode to 1,000 steps, it reached them later
  or not at all (BENCHMARKS.md, "The sized default: the tries"); TD3 updates on every env step;
- SAC learns from 3-step returns where the time limit is 1,000 steps or more and the random agent's episodes last
  a tenth of it or longer (a reward earned over a long episode reaches the critic's targets three times sooner):
  on Swimmer-v5, whose random agent plays every episode to the limit, development seeds 0-4 reached 40 at
  17,000-29,000 env steps with them, at 37,000-48,000 (and not by 80,000 on seed 4) without; on
  LunarLanderContinuous-v3, whose random agent crashes after ~110 steps, seeds 0 and 1 reached 200 at 77,700 and
  80,500 with them, not by 120,000 without, and the judging seeds 100-104 at 79,450-127,050. One-step returns where a random episode ends within a tenth of the
  limit (InvertedDoublePendulum's 7 steps, Hopper's 22, Ant's 34), as the judged InvertedDoublePendulum default
  has, and where the limit is shorter (BENCHMARKS.md, "The sized default: the tries");
- a body of one or two actuators steps in the learner's process; one of three or more (HalfCheetah's 6,
  Minitaur's 8) in a collector process beside the learner when there are two CPUs or more;
- DQN as the sized CartPole presets: learning rate 2.3e-3, gamma 0.99, epsilon 1.0 -> 0.04, the target
  network copied every 20 updates, the env in the learner's process; one update per 4 env steps (Nature DQN's
  and SB3's train_freq): a classic-control step costs ~0.1 ms in the learner's process and an update ~0.7, so the
  updates are the run's time (Acrobot-v1, seeds 0-4: ~4,000 updates to -100 against ~8,000 at one a step, for
  ~1.7x the env steps; BENCHMARKS.md, "The sized default and the development suite");
- schedules (DQN's epsilon) sized to 100 episodes of the time limit (of the random agent's episodes where the env
  has none), at least 50,000 and at most 1,000,000 env steps; the run goes on past them while its greedy evaluations
  improve: it ends at a plateau (``plateau``: no better evaluation over the last half of the run, from those 100
  episodes on) or at a ceiling of 1,000 episodes, at most 1,000,000 env steps (the peers' length for the 1,000-step
  MuJoCo envs), with a replay buffer that keeps them all; evaluations at most 10,000 env steps apart, and the best
  one's policy is what ``policy/`` exports (``keep_best``). With ``time_budget=`` the budget ends the run instead of a
  plateau (the user's time is the run's length; the best policy is still the one exported).

``resolve_for_env`` is what ``rlpipe train`` asks first: for ``env=ID`` with no preset, or a tutorial preset
(``sac``, ``td3``, ``dqn``) pointed at another env, the settings of the preset sized for that env and algorithm
where one exists, run for the sized default's length (``run_length``: its own is a benchmark's, to its target),
else the sized default; for anything else, nothing (the preset as named).
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass
from typing import Any

from rlpipe.modules.encoders import NATURE_MIN_SIZE
from rlpipe.pipelines.config import CollectorConfig, TrainConfig, apply_overrides, duration_seconds, flat_keys
from rlpipe.pipelines.errors import InputError

__all__ = ["EnvFacts", "Resolved", "measure", "resolve_for_env", "sized_config", "SIZED_ALGOS"]

SIZED_ALGOS = ("sac", "td3", "dqn")
"""the algorithms the rule sizes (CrossQ keeps its presets: it was sized on the pendulums and Minitaur only)"""
RANDOM_EPISODES = 5
"""episodes the random agent plays for the facts (the SAC presets' baseline_episodes)"""
RANDOM_SEED = 20_000
"""the random agent's seed for the facts: the baseline's offset (config.BASELINE_SEED_OFFSET) from seed 0"""
LONG_EPISODE = 1000
"""a time limit from which SAC and TD3 discount by 0.999 when the random agent's episodes all run to it"""
LONG_EPISODE_N_STEP = 3
"""SAC's n-step returns where the limit is LONG_EPISODE steps or more and random episodes last a tenth of it"""
LONG_RANDOM_EPISODE = 0.1
"""the fraction of the time limit from which a random agent's episodes count as long (for n-step returns)"""
CEILING_EPISODES = 1000
"""the env-step ceiling: 1,000 episodes of the time limit, at most 1,000,000 env steps (the peers' length for the
1,000-step MuJoCo envs), at least the 100 episodes the schedules are sized to"""
PLATEAU = 0.5
"""the sized run ends once its best greedy evaluation lies in the first half of the run (``plateau``)"""
EVAL_EVERY = 10_000
"""env steps between the sized run's evaluations at most"""
IMAGE_EVAL_EVERY = 50_000
"""the same for an image env's DQN (an Atari evaluation's ten games cost what ~10,000 training env steps do)"""
NO_TIME_LIMIT_STEPS = 1000
"""an episode of an env with no time limit is cut here when the random agent plays it"""


@dataclass(frozen=True)
class EnvFacts:
    """What the rule reads about an env and the machine."""

    env: str
    """the env as config.env names it"""
    discrete: bool
    """a Discrete action space (else a Box)"""
    observation_size: int
    """entries of the observation the networks read"""
    action_size: int
    """a Box's dimensions, or a Discrete space's number of actions"""
    action_low: tuple[float, ...] = ()
    """a Box's lower bounds (empty for a Discrete space)"""
    action_high: tuple[float, ...] = ()
    """a Box's upper bounds"""
    time_limit: int | None = None
    """the env's max_episode_steps (None: none registered)"""
    random_return: float = 0.0
    """the random agent's mean return over RANDOM_EPISODES episodes"""
    random_episode_length: float = 0.0
    """the random agent's mean episode length (short where the env ends a failed episode early)"""
    cpus: int = 1
    """this machine's CPUs"""
    observation_shape: tuple[int, ...] = ()
    """one observation's shape: (D,) for a vector, (C, H, W) for an image (an encoder reads it)"""
    goal_env: bool = False
    """a goal env (achieved and desired goals, compute_reward): HER relabels its goals"""
    entry_images: tuple[tuple[str, tuple[int, int, int]], ...] = ()
    """the images among a Dict env's entries, joined into its vector: (name, (C, H, W)) each (a CNN reads them)"""

    @property
    def image(self) -> bool:
        return len(self.observation_shape) == 3

    def describe(self) -> str:
        if self.discrete:
            actions = f"{self.action_size} actions"
        else:
            low, high = set(self.action_low), set(self.action_high)
            bounds = (f"in [{_g(min(low))}, {_g(max(high))}]" if len(low) == 1 and len(high) == 1
                      else f"in [{_g(min(low))}..{_g(max(low))}, {_g(min(high))}..{_g(max(high))}]")
            actions = f"act {self.action_size} {bounds}"
        limit = f"{self.time_limit:,}-step episodes" if self.time_limit else "no time limit"
        observed = (f"image {'x'.join(map(str, self.observation_shape))}" if self.image
                    else f"goal env, obs {self.observation_size}" if self.goal_env else f"obs {self.observation_size}")
        if self.entry_images:
            observed += " ({} through a CNN)".format(", ".join(f"image {name!r} {'x'.join(map(str, shape))}"
                                                              for name, shape in self.entry_images))
        return (f"{observed}, {actions}, {limit}, random agent {self.random_return:,.1f} in "
                f"{self.random_episode_length:,.0f} steps, {self.cpus} CPU{'s' if self.cpus != 1 else ''}")


def _g(x: float) -> str:
    return f"{x:g}"


def measure(cfg: TrainConfig, *, play: bool = True) -> EnvFacts:
    """The facts of the env ``cfg`` makes (``cfg.env``, as the pipeline makes it) and of this machine; with
    ``play=False`` its spaces and time limit only (no random agent: what the algorithm is chosen by)."""
    from rlpipe.envs import goal_env, gym_env_under, is_discrete, observation_images
    from rlpipe.pipelines.own_parts import factory_and_env, observation_key_in

    _, env = factory_and_env(None, cfg)
    try:
        spec = env.action_spec_unbatched
        discrete = is_discrete(spec)
        key = observation_key_in(env, None, cfg.env)
        shape = tuple(env.observation_spec[key].shape)
        obs = int(math.prod(shape)) or 1
        if discrete:
            size, low, high = int(spec.space.n), (), ()
        else:
            size = int(spec.shape[-1])
            low = tuple(float(v) for v in spec.space.low.flatten().tolist())
            high = tuple(float(v) for v in spec.space.high.flatten().tolist())
        gym_env = gym_env_under(env)
        goals = gym_env is not None and goal_env(gym_env)
        images = tuple((k, e.shape) for k, e in observation_images(gym_env).items()) if gym_env is not None else ()
        limit, (ret, length) = _random_agent(env) if play else (_time_limit(env), (0.0, 0.0))
    finally:
        env.close()
    return EnvFacts(cfg.env, discrete, obs, size, low, high, limit, ret, length, os.cpu_count() or 1, shape, goals,
                    images)


def _time_limit(env) -> int | None:
    """The max_episode_steps of the gymnasium env under ``make_env``'s env (None: none, or no gymnasium env)."""
    from rlpipe.pipelines.workers.gym_collector import gym_env_of

    gym_env = gym_env_of(env)
    return getattr(getattr(gym_env, "spec", None), "max_episode_steps", None) if gym_env is not None else None


def _random_agent(env) -> tuple[int | None, tuple[float, float]]:
    """(time limit, (mean return, mean episode length)) of uniformly random actions over RANDOM_EPISODES
    episodes: played on the gymnasium env under ``make_env``'s env where there is one (as evaluations are), else
    through TorchRL's rollout; seeded with RANDOM_SEED, so every call plays the same episodes."""
    import torch

    from rlpipe.pipelines.workers.gym_collector import gym_env_of

    gym_env = gym_env_of(env)
    limit = _time_limit(env)
    cap = limit or NO_TIME_LIMIT_STEPS
    returns, lengths = [], []
    if gym_env is not None:
        gym_env.action_space.seed(RANDOM_SEED)
        for episode in range(RANDOM_EPISODES):
            gym_env.reset(seed=RANDOM_SEED if episode == 0 else None)
            total, steps, done = 0.0, 0, False
            while not done and steps < cap:
                _, reward, terminated, truncated, _ = gym_env.step(gym_env.action_space.sample())
                total, steps, done = total + float(reward), steps + 1, terminated or truncated
            returns.append(total)
            lengths.append(steps)
    else:
        from torchrl.envs.utils import RandomPolicy

        from rlpipe.pipelines.workers.evaluation import evaluate

        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(RANDOM_SEED)
            env.set_seed(RANDOM_SEED)
            result = evaluate(env, RandomPolicy(env.full_action_spec), RANDOM_EPISODES, max_steps=cap)
        returns = result["returns"]
        lengths = [result["average_episode_length"]]
    return limit, (sum(returns) / len(returns), sum(lengths) / len(lengths))


def _eval_interval(iterations: int, per_update: int, every: int = EVAL_EVERY) -> int:
    """Iterations between evaluations: a tenth of the run, at least 1,000 iterations, at most ``every`` env steps
    (the plateau rule and the best policy need evaluations throughout a long run)."""
    return max(1000, min(_round_up(iterations / 10, 1000), every // per_update))


def _round_up(x: float, unit: int) -> int:
    return int(math.ceil(x / unit) * unit)


def _ceiling(facts: EnvFacts) -> tuple[int, int]:
    """(horizon, ceiling) in env steps: the 100 episodes the schedules are sized to and the 1,000 a run may go
    on to, of the time limit (of the random agent's episodes where the env has none), each at least 50,000 and at
    most 1,000,000 env steps."""
    episode = facts.time_limit or max(1, round(facts.random_episode_length))  # no limit: as long as it lasts
    horizon = min(1_000_000, max(50_000, 100 * episode))
    return horizon, max(horizon, min(1_000_000, CEILING_EPISODES * episode))


def run_length(facts: EnvFacts, random_steps: int, per_update: int,
               time_budget: str | None = None) -> tuple[dict[str, Any], str]:
    """The keys that decide when a run on ``facts``'s env ends, for a run of ``random_steps`` random env steps and
    ``per_update`` env steps an update, and the words that say so: the ceiling (``_ceiling``) with a replay buffer
    that keeps it all, ended sooner by a plateau of the greedy evaluations (none with ``time_budget``: the budget
    ends it), evaluations throughout, the best one's policy exported. What the sized default runs for, and what
    ``rlpipe train env=ID`` gives the settings of a preset sized for that env (whose own length is a benchmark's,
    to its target)."""
    horizon, ceiling = _ceiling(facts)
    iterations = (ceiling - random_steps) // per_update
    keys = dict(num_iterations=iterations, replay_buffer_capacity=ceiling,
                eval_interval=_eval_interval(iterations, per_update), log_interval=500 if ceiling <= 100_000 else 1000,
                checkpoint_interval=min(25_000, iterations), policy_save_interval=iterations,
                plateau=0.0 if time_budget else PLATEAU, keep_best=True,
                plateau_min_iterations=min(iterations, (horizon - random_steps) // per_update))
    return keys, _until(ceiling, time_budget)


def _until(ceiling: int, time_budget: str | None) -> str:
    if time_budget:
        return (f"until the time budget {time_budget} or {ceiling:,} env steps (no plateau stop: the time is yours), "
                "the best evaluation's policy exported")
    return (f"until a plateau (no better greedy evaluation over the last {PLATEAU:.0%} of the run) or "
            f"{ceiling:,} env steps, the best evaluation's policy exported")


def sized_config(algo: str, facts: EnvFacts, time_budget: str | None = None,
                 share_encoder: bool = True) -> tuple[TrainConfig, str]:
    """The config the rule gives ``algo`` on the env of ``facts``, and one line saying what and why.

    ``time_budget`` (the command's ``time_budget=``, e.g. ``10m``): the user's time is the run's length, so no
    plateau ends it sooner (the best evaluation's policy is still the one exported). ``share_encoder`` (the
    command's; true by default): what the line says of an image's encoder."""
    from rlpipe.pipelines import pipeline_class

    if algo not in SIZED_ALGOS:
        raise InputError(f"the sized default is for {', '.join(SIZED_ALGOS)}; expected one of them, not {algo!r}")
    Config = pipeline_class(algo).Config
    width = 64 if facts.observation_size <= 64 else min(256, 2 ** math.ceil(math.log2(facts.observation_size)))
    random_steps = min(5000, max(1000, _round_up(5 * facts.random_episode_length, 50)))
    # the schedules (epsilon's decay) are sized to 100 episodes; the run may go on to the ceiling, ended
    # before it by a plateau of its greedy evaluations (run_length)
    horizon, budget = _ceiling(facts)
    big_body = not facts.discrete and facts.action_size >= 3
    one_actuator = not facts.discrete and facts.action_size == 1
    in_process = not big_body or facts.cpus < 2
    long_random_episodes = (not facts.discrete and facts.time_limit is not None and facts.time_limit >= LONG_EPISODE
                            and facts.random_episode_length >= LONG_RANDOM_EPISODE * facts.time_limit)
    whole_episodes = long_random_episodes and facts.random_episode_length >= facts.time_limit
    # env steps per update (collect_steps_per_iteration)
    per_update = 4 if facts.discrete else 2 if algo == "sac" and not whole_episodes and not facts.goal_env else 1
    # goal envs: RL-Zoo's HER settings for Fetch (and the HER paper's short horizon): gamma 0.95, observations
    # normalised (their positions and velocities are of different scales), an update every env step
    gamma = 0.999 if whole_episodes else 0.95 if facts.goal_env else 0.99
    length, until = run_length(facts, random_steps, per_update, time_budget)
    keys = dict(
        env=facts.env, initial_collect_steps=random_steps, initial_eval=False, baseline_episodes=0,
        live_report=not in_process, num_threads=1, num_eval_episodes=10,
        collector=CollectorConfig(workers=1, sync=in_process), **length,
    )
    net = [width, width]
    chosen = [f"{width}x{width}"]
    if facts.goal_env:
        # RL-Zoo's VecNormalize for Fetch; not over an image among the entries, which its encoder scales itself
        keys.update(normalize_observations=not facts.entry_images)
        chosen += ["gamma 0.95", *(["observations normalised"] if not facts.entry_images else []), "HER"]
    if facts.image and algo == "dqn":  # after the encoder's convolutions: the Nature DQN's 512, the MinAtar paper's 128
        net = [512] if min(facts.observation_shape[1:]) >= NATURE_MIN_SIZE else [128]
        chosen = [f"a CNN then {net[0]}"]
    if algo in ("sac", "td3") and (facts.image or facts.entry_images):
        chosen[0] = (f"one CNN for the actor and critics, trained by the critics, then {chosen[0]}" if share_encoder
                     else f"a CNN for the actor and each critic, then {chosen[0]}")
    if algo == "sac":
        keys.update(actor_fc_layer_params=net, critic_joint_fc_layer_params=list(net))
        if not one_actuator:
            rate, tau = 1e-3, 0.005
            keys.update(target_entropy=-float(facts.action_size))
            chosen += [f"lr {rate:g}", f"tau {tau:g}", f"target entropy -{facts.action_size}"]
        else:
            rate, tau = 2e-3, 0.02
            keys.update(policy_delay=2)
            chosen += [f"lr {rate:g}", f"tau {tau:g}", "the actor on every 2nd update"]
        keys.update(actor_learning_rate=rate, critic_learning_rate=rate, alpha_learning_rate=rate, target_update_tau=tau,
                    gamma=gamma, collect_steps_per_iteration=per_update)
        chosen += [f"an update every {per_update} env steps" if per_update > 1 else "an update every env step"]
        if long_random_episodes:
            keys.update(n_step=LONG_EPISODE_N_STEP)
            chosen += [f"{LONG_EPISODE_N_STEP}-step returns"]
    elif algo == "td3":
        rate, tau = (2e-3, 0.05) if one_actuator else (1e-3, 0.005)
        keys.update(actor_fc_layer_params=net, critic_fc_layer_params=list(net), learning_rate=rate,
                    target_update_tau=tau, learning_starts=random_steps, gamma=gamma)
        chosen += [f"lr {rate:g}", f"tau {tau:g}"]
    elif facts.image:
        # 1,000,000 env steps, as the peers train image envs (the MinAtar paper's buffer of 100,000 on small grids);
        # the MinAtar paper's DQN (Young & Tian 2019) for small grids, the Nature DQN's for pictures: Adam at their
        # rates, batch 32, a target copy every 1,000 env steps, epsilon to 0.01 (0.1 for MinAtar) over a tenth
        small = net == [128]
        rate, end = (2.5e-4, 0.1) if small else (1e-4, 0.01)
        per_update = 1 if small else 4
        budget = 1_000_000
        decay = budget // 10
        keys.update(fc_layer_params=net, learning_rate=rate, gamma=0.99, epsilon_greedy=1.0, epsilon_greedy_end=end,
                    epsilon_decay_steps=decay, target_update_period=1000 // per_update, batch_size=32,
                    collect_steps_per_iteration=per_update, clip_rewards=not small)
        iterations = (budget - random_steps) // per_update
        keys.update(num_iterations=iterations, replay_buffer_capacity=100_000 if small else budget,
                    log_interval=1000, eval_interval=_eval_interval(iterations, per_update, IMAGE_EVAL_EVERY),
                    checkpoint_interval=min(25_000, iterations), policy_save_interval=iterations,
                    plateau_min_iterations=min(iterations, 2 * decay // per_update))
        chosen += [f"lr {rate:g}", f"epsilon 1 -> {end:g} over {decay:,} steps",
                   f"an update every {per_update} env steps" if per_update > 1 else "an update every env step",
                   "the " + ("MinAtar paper's" if small else "Nature DQN's") + " settings"]
    else:
        decay = max(5000, _round_up(horizon / 10, 1000))
        keys.update(fc_layer_params=net, learning_rate=2.3e-3, gamma=0.99, epsilon_greedy=1.0, epsilon_greedy_end=0.04,
                    epsilon_decay_steps=decay, target_update_period=20, collect_steps_per_iteration=per_update)
        chosen += ["lr 0.0023", f"epsilon 1 -> 0.04 over {decay:,} steps", f"an update every {per_update} env steps"]
    if whole_episodes:
        chosen += [f"gamma {gamma:g} (random episodes run to the {facts.time_limit:,}-step limit)"]
    chosen += [f"{random_steps:,} random steps"]
    if facts.image and algo == "dqn":  # the image rule's own length (above)
        until = _until(budget, time_budget)
    chosen += [until]
    where = ("env in the learner's process" if in_process else
             f"env in a collector process ({facts.action_size} actuators; {facts.cpus} CPUs)")
    cfg = Config(**keys)
    line = f"sized for {facts.env}: {facts.describe()} -> {', '.join(chosen)}, {where} (pipelines/sizing.py)"
    return cfg, line


# --- what `rlpipe train` trains when it names an env -------------------------------------------------


@dataclass
class Resolved:
    """What ``rlpipe train`` trains: the algorithm, the config before the command's overrides, the overrides
    (``env=ID`` included), and the lines to print first (what was chosen, and why)."""

    algo: str
    config: TrainConfig
    overrides: list[str]
    lines: list[str]
    source: str = "the sizing rule (pipelines/sizing.py)"
    """where the config's values come from, as ``rlpipe train ... --keys`` names it"""


def _key(item: str) -> str:
    return item.partition("=")[0].strip()


def _env_overrides(overrides: list[str]) -> list[str]:
    """The overrides that say which env to make (``env=``, and the keys of its making, ``env_*``)."""
    return [o for o in overrides if _key(o) == "env" or _key(o).startswith("env_")]


def resolve_for_env(name: str, overrides: list[str], *, resume: bool = False) -> Resolved | None:
    """What ``rlpipe train NAME [overrides]`` trains when NAME is a ``key=value`` (no preset: ``env=ID``), or a
    tutorial preset (``sac``, ``td3``, ``dqn``) with ``env=`` naming another env than its own; None otherwise.

    - no algorithm: SAC for a Box action space, DQN for a Discrete one;
    - then the preset sized for that env and algorithm if there is one (``sac env=Pendulum-v1`` trains
      ``sac-pendulum``'s settings, for the sized default's length: ``run_length``), else the sized default
      (``sized_config``).

    With ``resume``, nothing is sized: the run's saved config is what it goes on with.
    """
    from rlpipe.pipelines import ALGOS, pipeline_class, preset_info, presets, resolve_preset

    no_algo = "=" in name and _key(name) in flat_keys(TrainConfig)
    if no_algo:
        overrides = [name, *overrides]
        if not any(_key(o) == "env" for o in overrides):
            raise InputError(f"rlpipe train {name}: no preset and no env; expected `rlpipe train PRESET [key=value ...]` "
                             "or `rlpipe train env=ID [key=value ...]`")
        algo = None
    elif name in ALGOS and preset_info(name) is not None and not preset_info(name).sized:
        algo = name
    else:
        return None
    base = resolve_preset(algo or "sac")[1]
    wanted = apply_overrides(base, _env_overrides(overrides))
    if algo is not None and _same_env(wanted.env, base.env):
        return None  # the tutorial on its own env: as the tutorial specifies
    kind = None
    if algo is None:
        kind = measure(wanted, play=False)
        algo = "dqn" if kind.discrete else "sac"
        space = f"a Discrete({kind.action_size})" if kind.discrete else f"a Box({kind.action_size})"
        other = "" if kind.discrete else f"; `rlpipe train td3 env={wanted.env}` for TD3"
        first = [f"rlpipe: training {algo.upper()}: {wanted.env} has {space} action space "
                 f"(SAC for a Box action space, DQN for a Discrete one{other})"]
    else:
        first = []
    if resume:
        return Resolved(algo, resolve_preset(algo)[1], overrides, [], f"preset {algo}")
    budget = _last_value(overrides, "time_budget", None)
    budget = budget if budget is not None and duration_seconds(budget) else None  # null; a bad one: its own line
    fits = [p for p in presets.names() if _same_env(getattr(presets.info(p), "env", None) or "", wanted.env)
            and preset_info(p).sized and resolve_preset(p)[0] == algo]
    if fits:
        # the preset's learning settings; its length is a benchmark's, to its target: the run's own is the sized
        # default's, ended by the user's target, time budget, a plateau or the ceiling
        info, cfg = preset_info(fits[0]), resolve_preset(fits[0])[1]
        facts = kind or measure(wanted, play=False)  # the spaces and time limit, measured once
        if facts.time_limit is None:  # the ceiling counts the random agent's episodes instead
            facts = measure(wanted)
        length, until = run_length(facts, cfg.initial_collect_steps, cfg.collect_steps_per_iteration, budget)
        cfg = dataclasses.replace(cfg, **length)
        line = (f"rlpipe: {algo} on {wanted.env}: the settings of preset {fits[0]!r} ({info.task}), the preset "
                f"sized for this env, {until} (`rlpipe train {fits[0]}` runs the preset as it is)")
        return Resolved(algo, cfg, overrides, [*first, line], f"preset {fits[0]}, sized for {wanted.env}")
    if algo not in SIZED_ALGOS:
        return None  # CrossQ: its tutorial preset and the hint of what sizes a run
    kind = kind or measure(wanted, play=False)
    if kind.discrete != (pipeline_class(algo).action_space == "discrete"):
        return None  # the pipeline says, in its own line, which action space the algorithm needs
    cfg, line = sized_config(algo, measure(wanted), time_budget=budget,
                             share_encoder=_last_bool(overrides, "share_encoder", True))
    return Resolved(algo, cfg, overrides, [*first, f"rlpipe: {line}"], f"sized for {wanted.env} (pipelines/sizing.py)")


def _last_value(overrides: list[str], key: str, default: str | None) -> str | None:
    """The value the last ``key=value`` of ``overrides`` gives ``key``, as written (``default`` if none)."""
    return next((o.partition("=")[2].strip() for o in reversed(overrides) if _key(o) == key), default)


@dataclass
class _Flag:
    value: bool = True


def _last_bool(overrides: list[str], key: str, default: bool) -> bool:
    """The bool the last ``key=value`` of ``overrides`` gives ``key``, read as the config reads a bool (OmegaConf:
    true/false, yes/no, on/off, 1/0); ``default`` if none or not a bool (``apply_overrides`` then says so in its own
    line)."""
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    value = _last_value(overrides, key, None)
    if value is None:
        return default
    try:
        return OmegaConf.merge(OmegaConf.structured(_Flag), OmegaConf.from_dotlist([f"value={value}"])).value
    except OmegaConfBaseException:
        return default


def _same_env(a: str, b: str) -> bool:
    """``a`` and ``b`` name the same env (``MinitaurBulletEnv-v0`` and ``rlpipe/MinitaurBullet-v0`` do)."""
    if a == b:
        return True
    from rlpipe.envs import EnvError, resolve_env_id

    try:
        return resolve_env_id(a) == resolve_env_id(b)
    except EnvError:  # an env of the user's own (module:Class), or one that is not there: by its name
        return False
