"""The config schema: every key, declared once with its type, default, rule and help.

Keys keep the TF-Agents tutorials' names where they mean the same thing (``num_iterations``,
``initial_collect_steps``, ``collect_steps_per_iteration``, ``replay_buffer_capacity``, ...), so a
reader of the tutorials finds them. Each field's docstring is its help text (``rlpipe train X --keys``).

Each key has one home. ``TrainConfig`` declares the keys every algorithm has, with neutral defaults; the keys
several algorithms (not all) have are declared in the small dataclasses below it (``ActorKeys``,
``CriticKeys``, ``OneRateKeys``, ``ClippedGradientKeys``), which an algorithm's config inherits; an
algorithm's own keys are declared in its config (``DQN.Config``, ``TD3.Config``, ``SAC.Config``,
``CrossQ.Config``; the last two on the keys they share, ``sac.SACFamilyConfig``). Where an algorithm's
default differs from the declared one (its tutorial's), its config says so in one place, ``@config_class(key=value)``
(or ``key=(value, "why")``, the why added to the key's help), without declaring the key again.

A rule on one key's value (positive, a choice, a range) is declared with its field (``checked(default,
POSITIVE)``); ``validation.validate`` applies them and the rules between keys.
"""

from __future__ import annotations

import ast
import copy
import dataclasses
import functools
import inspect
import json
import typing
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = [
    "ANNEAL_WINDOW",
    "BASELINE_SEED_OFFSET",
    "COLLECTOR_BACKENDS",
    "ENV_KWARGS_RESERVED",
    "EVAL_SEED_OFFSET",
    "GRADIENT_CLIPPING",
    "LAYER_SIZES",
    "LEARNING_RATE",
    "LOGGERS",
    "MAX_SEED",
    "NON_NEGATIVE",
    "POSITIVE",
    "PROBABILITY",
    "ActorKeys",
    "BackendNeeds",
    "Check",
    "ClippedGradientKeys",
    "CollectorConfig",
    "CriticKeys",
    "OneRateKeys",
    "PresetInfo",
    "RayConfig",
    "TrainConfig",
    "WORKERS_PER_CPU",
    "checked",
    "config_class",
    "duration_seconds",
    "env_options",
    "eval_seed",
    "field_docs",
    "flat_keys",
    "layer_sizes",
    "one_of",
    "steps_in_learner",
]

# Evaluations and the random baseline play env copies of their own, seeded apart from the collectors'
# stream (``seed + frames``), wherever they run (the learner's process, a process, a Ray actor).
EVAL_SEED_OFFSET = 10_000
"""the eval env's seed is the run's seed plus this"""
BASELINE_SEED_OFFSET = 20_000
"""the random baseline's env's seed is the run's seed plus this"""


# --- what a preset is for ------------------------------------------------------------------------


@dataclass(frozen=True)
class PresetInfo:
    """The task a preset is sized for, as data: ``rlpipe presets`` lists it, ``rlpipe train`` hints at
    it when a tutorial preset is pointed at its env, and the time-to-return bench stops a run at it."""

    env: str
    """the gymnasium env id the preset trains on"""
    targets: tuple[float, ...] = ()
    """returns that count as the task reached, in the order they are met (empty: a reproduction, no target)"""
    task: str = ""
    """a few words on what the preset is: 'the Minitaur tutorial', 'sized for time to -200', ..."""
    sized: bool = True
    """tuned for time to its target on a small CPU machine (false: a tutorial's or a paper's settings, kept as written)"""
    measured: tuple[tuple[str, Any], ...] = ()
    """its measured time to its target, as ``rlpipe presets`` shows it: ``seconds``, ``date``, ``commit`` and, for a preset
    with two targets, the ``target`` it is to (from a ``rlpipe bench time-to-return`` run; empty: not measured)"""

    @property
    def target(self) -> float | None:
        """the first of ``targets`` (None without one)"""
        return self.targets[0] if self.targets else None


def eval_seed(seed: int, step: int) -> int:
    """The eval env's seed for the evaluation at iteration ``step``: from the run's seed and that step
    alone, so an evaluation plays the same episodes whatever came before it (a resume, an evaluator
    restarted, evaluations skipped). A hash, not ``seed + EVAL_SEED_OFFSET + step``, which would meet the
    collectors' ``seed + frames``."""
    return int(np.random.SeedSequence([seed, EVAL_SEED_OFFSET, step]).generate_state(1)[0])


# --- rules on one key's value, declared with its field --------------------------------------------


@dataclass(frozen=True)
class Check:
    """What one key's value must be: ``validate`` raises ``InputError("key=value: expected ...")``
    when ``ok(value)`` is false. Declared as the field's metadata by ``checked``; null values pass."""

    ok: Callable[[Any], bool]
    expected: str | Callable[[Any], str]

    def describe(self, value) -> str:
        return self.expected(value) if callable(self.expected) else self.expected


def _number(value) -> str:
    return "number" if isinstance(value, float) else "integer"


POSITIVE = Check(lambda v: v > 0, lambda v: f"a positive {_number(v)}")
NON_NEGATIVE = Check(lambda v: v >= 0, lambda v: f"zero or a positive {_number(v)}")
PROBABILITY = Check(lambda v: 0.0 <= v <= 1.0, "a probability in [0, 1]")
LEARNING_RATE = Check(lambda v: v > 0, "a positive learning rate")
GRADIENT_CLIPPING = Check(lambda v: v > 0, "a positive norm, or null for none")
ANNEAL_WINDOW = Check(lambda v: len(v) == 2 and 0 <= v[0] < v[1], "[start, end] env steps with 0 <= start < end")
"""a schedule's window in env steps (frames collected, random ones included)"""

LAYER_SIZES = Check(lambda v: bool(v) and all(n > 0 for n in v),
                    "a non-empty list of positive layer sizes, e.g. [256,256]")
"""hidden layer sizes of a network (the memory check counts the parameters of every such key)"""


ENV_KWARGS_RESERVED = ("seed", "device", "num_envs", "rescale_observations", "render_mode", "observation_keys",
                       "frame_stack", "episodic_life")
"""what ``rlpipe.envs.make_env`` takes itself: an env keyword of the same name could not reach the env"""
ENV_KWARGS = Check(lambda v: not set(v) & set(ENV_KWARGS_RESERVED),
                   lambda v: f"keywords other than {', '.join(ENV_KWARGS_RESERVED)} (rlpipe sets those itself: the "
                             f"`seed` key seeds the env, videos choose the render mode)")


LOGGERS = {"tensorboard": None, "csv": None, "wandb": "wandb", "mlflow": "mlflow"}
"""the ``logger`` choices and the package each needs beyond rlpipe's own"""


def duration_seconds(text: str | float | int) -> float | None:
    """Seconds of a duration written ``90``, ``90s``, ``10m`` or ``2h`` (a positive number); None if it is not one."""
    import re

    found = re.fullmatch(r"\s*(\d+(?:\.\d+)?)\s*([smh]?)\s*", str(text))
    if found is None or float(found.group(1)) <= 0:
        return None
    return float(found.group(1)) * {"": 1, "s": 1, "m": 60, "h": 3600}[found.group(2)]


def env_options(cfg, *, rescaled: bool = True, training: bool = False) -> dict[str, Any]:
    """The keywords of ``rlpipe.envs.make_env`` that the config sets besides the env's own (``env_kwargs``);
    ``rescaled=False`` leaves out the rescaling, which the exported policy does itself; ``training=True`` adds
    what only the training envs do (an Atari episode ended at each lost life)."""
    options = {"observation_keys": cfg.observation_keys, "frame_stack": cfg.frame_stack}
    if training:
        options["episodic_life"] = cfg.episodic_life
    return {"rescale_observations": cfg.rescale_observations, **options} if rescaled else options


def one_of(*choices: str, expected: str | None = None) -> Check:
    return Check(lambda v: v in choices, expected or f"one of {', '.join(repr(c) for c in choices)}")


def checked(default: Any = dataclasses.MISSING, check: Check | None = None, *, factory: Callable[[], Any] | None = None):
    """A dataclass field whose value ``validate`` checks with ``check`` (``factory``: a mutable default)."""
    kwargs = {"default_factory": factory} if factory is not None else {"default": default}
    return field(metadata={"check": check}, **kwargs)


def _checks(cls: type, prefix: str = "") -> dict[str, Check]:
    """Every key's declared rule (an algorithm's default for it, ``config_class``, keeps the declaration's)."""
    rules: dict[str, Check] = {}
    for klass in reversed(cls.__mro__):
        for name, f in getattr(klass, "__dataclass_fields__", {}).items():
            if f.metadata.get("check") is not None:
                rules[prefix + name] = f.metadata["check"]
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        if dataclasses.is_dataclass(hints[f.name]):
            rules.update(_checks(hints[f.name], prefix + f.name + "."))
    return rules


def layer_sizes(cfg) -> dict[str, list[int]]:
    """The keys of ``cfg`` that give a network's hidden layer sizes (declared ``LAYER_SIZES``), with their values."""
    return {key: _get(cfg, key) for key, check in _checks(type(cfg)).items() if check is LAYER_SIZES}


MAX_SEED = 2**31 - 1
"""seeds go to torch, NumPy (below 2**32) and gymnasium, offset per worker and eval env: this keeps them all in range"""
WORKERS_PER_CPU = 8
"""collector processes per CPU beyond which a run only thrashes (each is a whole Python process with torch)"""


@dataclass(frozen=True)
class BackendNeeds:
    """What a collector backend (``workers.backend``) asks of a config, checked by ``validate``: the
    config cannot import the backends (they sit above it), so each says here what it needs."""

    what: str
    """a few words for error messages"""
    package: str | None = None
    """a module it imports, installed by the extra of the same name (``pip install 'rlpipe[ray]'``)"""
    even_sync_blocks: bool = False
    """with collector.sync=true, each block splits evenly over the workers"""


COLLECTOR_BACKENDS = {
    "local": BackendNeeds("collector processes"),
    "ray": BackendNeeds("Ray actors", package="ray", even_sync_blocks=True),
}
"""``collector.backend`` -> what that backend needs (``workers.factory.make_backend`` picks the backend itself)"""


@dataclass
class CollectorConfig:
    """How env steps are gathered: TorchRL collectors in place of TF-Agents' actor processes."""

    workers: int = checked(1, POSITIVE)
    """collector processes; 1 with sync=true steps the env in the learner's process (TorchRL `Collector`)"""
    sync: bool = True
    """true: `MultiSyncCollector` (workers step in lock-step); false: `MultiAsyncCollector` (collection overlaps learning)"""
    envs_per_worker: int = checked(1, POSITIVE)
    """env copies each worker steps as one batch (gymnasium's SyncVectorEnv): the policy and TorchRL's per-step work run once per batch; made from `env` (evaluation keeps one copy)"""
    direct: bool = True
    """with one env copy per worker made from `env`: each collector (in the learner's process or a worker's) steps the gymnasium env directly (`GymCollector`, a TorchRL `Collector` giving TorchRL's keys at a fraction of its per-step cost over `GymEnv`); false: TorchRL's `Collector` over `GymEnv`"""
    frames_per_batch: int = checked(50, POSITIVE)
    """env steps gathered per block (all workers together); the block's updates follow at the same update-to-data ratio (1 = the tutorials' exact interleave). Triggers land on round iterations when it divides `initial_collect_steps` and the intervals"""
    policy_device: str = checked("", one_of("", "cpu"))
    """where the collect policy acts: '' on the learner's `device`; 'cpu' from a CPU copy of the policy (TorchRL's `policy_device`), its weights copied from the learner's after each block's updates: with device=cuda, each env step then pays no host-device round trip, only each block does. Worker processes (workers>1 or sync=false) act from their own CPU copies, store their blocks on the CPU and never start CUDA; the learner copies each block to its device"""
    weight_sync_interval: int = checked(1, POSITIVE)
    """updates between pushes of fresh policy weights to collector processes (the tutorial's variable container); with backend=ray a worker gets the learner's weights each time it is asked for a block"""
    backend: str = checked("local", one_of(*COLLECTOR_BACKENDS, expected=" or ".join(
        f"{name!r} ({needs.what})" for name, needs in COLLECTOR_BACKENDS.items())))
    """'local': collector processes on this machine; 'ray': collectors as Ray actors placed by Ray (TorchRL's `RayCollector`; see the `ray` keys)"""
    max_restarts: int = checked(3, NON_NEGATIVE)
    """restarts allowed (each of the collector and of the background evaluator, per session) when a worker process dies or stops answering; one more failure saves a checkpoint and stops the run (exit status 75)"""
    timeout: float = checked(120.0, POSITIVE)
    """seconds any wait on collector processes may take (a block of env steps, a weight push; their start-up: at least 300) before the wait counts as a failed worker"""


def steps_in_learner(c: CollectorConfig) -> bool:
    """Whether the env steps in the learner's own process: one local worker, synchronous (TorchRL's
    ``Collector``, no process to start or watch); collection and updates then take turns."""
    return c.backend == "local" and c.workers == 1 and c.sync


@dataclass
class RayConfig:
    """Where Ray places the collectors when collector.backend=ray."""

    address: str = ""
    """the Ray cluster to use: empty starts a local Ray instance for this run (shut down at its end); HOST:PORT, or 'auto' (RAY_ADDRESS if set, else the cluster `ray start` began on this machine), joins a running cluster, which the run leaves up"""
    num_cpus_per_worker: float = checked(1.0, Check(lambda v: v > 0, "a positive number of CPUs"))
    """CPUs Ray reserves for each collector actor (a fraction packs several actors on one core)"""


@dataclass
class TrainConfig:
    """The keys every off-policy pipeline shares, with neutral defaults: each algorithm's config
    (``DQN.Config``, ``TD3.Config``, ``SAC.Config``) sets its tutorial's. Intervals count iterations (train steps)."""

    env: str = ""
    """gymnasium env id (the tutorials' ids work too, e.g. MinitaurBulletEnv-v0), or your own: `my_package.envs:MyArm` (a gymnasium.Env subclass, or a function annotated `-> gymnasium.Env`) or `my_package:MyArm-v0` (an id the module registers), the module installed or on PYTHONPATH"""
    env_kwargs: dict[str, Any] = checked(check=ENV_KWARGS, factory=dict)
    """keywords for the env's constructor (`gymnasium.make`'s), one a key on the command line: env_kwargs.size=3"""
    rescale_observations: bool = False
    """map each observation linearly from the observation space's bounds to [-1, 1] (gymnasium's RescaleObservation) in the envs made from `env`, so that no input dwarfs the others (Minitaur's motor velocities are bounded by 168, its motor angles by 3.15); the exported policy takes the env's own observations and rescales them itself. Needs finite bounds"""
    normalize_observations: bool = False
    """keep each observation entry's running mean and variance (updated by the learner from every collected block, frozen in evaluations) and feed the networks (observation - mean) / std clipped to [-10, 10], as SB3's VecNormalize; the statistics are in every checkpoint and in the exported policy, which takes the env's own observations. Vector observations"""
    observation_keys: list[str] | None = None
    """the entries of a Dict observation the networks read, concatenated in the env's order (null: every entry); each a vector (a Box, or a discrete space read one-hot)"""
    frame_stack: int = checked(1, POSITIVE)
    """stack the last N frames of an image observation on its channel axis (4 for Atari, as the Nature DQN); 1 for vector observations"""
    episodic_life: bool = True
    """Atari (ALE/ ids): a lost life ends the training episode and the game goes on at the next reset, as SB3's AtariWrapper and CleanRL's dqn_atari.py train (the learner bootstraps no value past a lost life); training returns are then one life's score, while evaluations play whole games. Other envs: no effect"""
    her: bool | None = None
    """Hindsight Experience Replay: relabel a share (her_ratio) of each sampled batch with a goal the same episode achieved later (the "future" strategy) and the env's compute_reward; needs a goal env (achieved_goal, desired_goal, compute_reward); null: on for a goal env"""
    her_ratio: float = checked(0.8, PROBABILITY)
    """share of each sampled batch HER relabels (0.8: four relabelled goals per original, the HER paper's k=4)"""
    seed: int = checked(0, Check(lambda v: 0 <= v <= MAX_SEED, f"an integer from 0 to {MAX_SEED}"))
    """seed for networks, replay sampling, exploration and envs; worker seeds derive from it"""
    num_iterations: int = checked(100_000, POSITIVE)
    """training iterations after the initial collect; each collects `collect_steps_per_iteration` env steps and makes one update"""
    initial_collect_steps: int = checked(1000, NON_NEGATIVE)
    """env steps taken with a uniformly random policy before the collect policy takes over"""
    collect_steps_per_iteration: int = checked(1, POSITIVE)
    """env steps per iteration (per update): the inverse of the update-to-data ratio"""
    learning_starts: int | None = checked(None, NON_NEGATIVE)
    """env steps collected before updates begin; each later step pays for 1/`collect_steps_per_iteration` updates (null: `initial_collect_steps`, as TF-Agents does)"""
    replay_buffer_capacity: int = checked(100_000, POSITIVE)
    """transitions kept; the oldest are evicted first"""
    replay_buffer_storage: str = checked("memory", one_of("memory", "memmap"))
    """where the replay buffer keeps its transitions: 'memory', or 'memmap' (files in the system's temporary folder, memory-mapped: TorchRL's LazyMemmapStorage, and the image frame ring in a file), for a buffer larger than the memory"""
    batch_size: int = checked(256, POSITIVE)
    """transitions per update, sampled uniformly"""
    replay_all_keys: bool = False
    """store every key the collector returns (true: e.g. to inspect ("collector", "traj_ids") or step counts in the buffer; each trajectory id is one episode across the run's collectors, restarted or resumed ones included); false stores only the keys the loss reads (`loss_module.in_keys`): less memory, faster sampling"""
    gamma: float = checked(0.99, Check(lambda v: 0.0 < v <= 1.0, "a discount in (0, 1]"))
    """discount factor"""
    n_step: int = checked(1, POSITIVE)
    """n-step returns: each stored transition's reward is the discounted sum of the next n rewards of its episode and its next observation the one n env steps on (fewer at an episode's end or a collected block's), its bootstrap discounted by gamma**k for a window of k steps (`steps_to_next_obs`, as TorchRL's TD0 reads it); 1: one-step TD"""
    target_update_tau: float = checked(0.005, Check(lambda v: 0.0 < v <= 1.0, "a value in (0, 1]"))
    """target network soft-update factor (1.0 copies the online network)"""
    target_update_period: int = checked(1, POSITIVE)
    """updates between target network updates"""
    eval_interval: int = checked(10_000, NON_NEGATIVE)
    """iterations between evaluations of the deterministic policy (0: only before and after training)"""
    num_eval_episodes: int = checked(10, POSITIVE)
    """episodes per evaluation; their mean return is AverageReturn"""
    initial_eval: bool = True
    """evaluate the untrained policy before the first update (the tutorials' step-0 row); false: the first evaluation is at `eval_interval` (a preset sized for time to a target skips the untrained one: ~1-2 s on Pendulum before the first env step)"""
    baseline_episodes: int = checked(-1, Check(lambda v: v >= -1, "-1 (num_eval_episodes), 0 (no baseline) or a positive count"))
    """episodes of the random agent played once before training for its baseline return (RUN/baseline.json, the DQN tutorial's); -1: num_eval_episodes; 0: no baseline"""
    eval_in_background: bool = False
    """evaluate in a separate process on a snapshot of the policy while training goes on; results land at the iteration they were taken"""
    logger: str = checked("tensorboard", one_of(*LOGGERS))
    """where the metrics go besides RUN/metrics.csv (TorchRL's loggers): 'tensorboard' (RUN/tb), 'csv' (RUN/csv), 'wandb' (Weights & Biases, project 'rlpipe', files in RUN/wandb; WANDB_MODE=offline runs without a network; pip install 'rlpipe[wandb]') or 'mlflow' (an MLflow file store in RUN/mlruns; pip install 'rlpipe[mlflow]'); the run's config is logged once as its hyperparameters"""
    live_report: bool = True
    """refresh RUN/report.html and RUN/returns.png while the run goes on, at evaluations and log rows (the first of each at once, later ones within ~2% of the run's time); false: at the end only, and when the run stops early (a preset sized for time to a target: the first page costs about a second, a tenth of a Pendulum run)"""
    eval_timeout: float = checked(600.0, POSITIVE)
    """seconds a background evaluation may take before its process counts as failed (it is restarted and asked again, as for `collector.max_restarts`)"""
    log_interval: int = checked(1000, POSITIVE)
    """iterations between rows of losses and speed in metrics.csv and TensorBoard"""
    policy_save_interval: int = checked(5000, POSITIVE)
    """iterations between exports of the deterministic policy (the tutorials' saved policy)"""
    policy_keep: int = checked(0, NON_NEGATIVE)
    """exports kept in policy/ as step_NNNNNNN.onnx/.pt2 (the newest; 0: all, as the tutorials keep every saved policy); policy.onnx/.pt2 is always the latest"""
    checkpoint_interval: int = checked(10_000, POSITIVE)
    """iterations between checkpoints that `--resume` continues from"""
    video: bool = False
    """at the end of training, film the trained policy to RUN/trained-agent.mp4 (as `rlpipe video RUN`) and show it on RUN/report.html"""
    checkpoint_keep: int = checked(2, NON_NEGATIVE)
    """checkpoints kept, newest first (the oldest goes once a new one is whole; `--resume` falls back on an older one if the newest is damaged); 0 keeps every one"""
    fast: bool = True
    """use rlpipe's fast parts, each the equal of the TorchRL or torch part it replaces (the lean losses, LeanAdam, ForeachSoftUpdate, the replay sample, collection and evaluation on the gymnasium env, the exploration policies on tensors: the table in rlpipe.modules.fast); false puts every stock TorchRL part back at once (the same learning, slower); a run with true refuses to start, in one line, on a TorchRL or torch whose private names these parts read have changed"""
    compile: bool = False
    """compile the update with torch.compile (faster per update for small networks, ~30 s to compile on CPU); on device=cuda also replays it as CUDA graphs (see `cudagraph`)"""
    cudagraph: bool | None = None
    """on device=cuda, replay the update as CUDA graphs (tensordict's CudaGraphModule: one launch instead of hundreds of small kernels); null: when `compile` is true"""
    num_threads: int = checked(-1, Check(lambda v: v >= -1, "-1 (chosen at start), 0 (torch's default) or a positive count"))
    """torch threads of the learner; -1: chosen at the start of training by a rule over this machine's cores (half of those the collector processes leave free, at most 4, at most OMP_NUM_THREADS where that is set; never a timing), recorded in config.json and reused by --resume; 0: torch's default"""
    device: str = "cpu"
    """device of the learner ('cpu', 'cuda', 'cuda:1', ...)"""
    initial_collect_policy: str = checked("random", one_of("random", "collect"))
    """policy of the `initial_collect_steps`: 'random' (uniform actions, the DQN and actor-learner SAC tutorials) or 'collect' (the exploring policy of the untrained networks, the older SAC tutorial's driver)"""
    time_budget: str | None = checked(None, Check(lambda v: duration_seconds(v) is not None,
                                                  "a duration such as 90s, 10m or 2h (a number alone: seconds), or null"))
    """end the run once its wall-clock time (every session of a resumed run, evaluations and saving included) reaches this, at the end of the collected block that crosses it; null: no budget"""
    plateau: float = checked(0.0, Check(lambda v: 0.0 <= v < 1.0, "a fraction of the run in [0, 1) (0: off)"))
    """end the run at a plateau: once no greedy evaluation has beaten the best one for this fraction of the run's iterations so far, and for at least `plateau_evaluations` evaluations (0.5: the best came in the first half of the run); 0: off"""
    plateau_evaluations: int = checked(5, POSITIVE)
    """evaluations after the best one that a plateau needs at least (with `plateau`)"""
    plateau_min_iterations: int = checked(0, NON_NEGATIVE)
    """iterations before which a plateau does not end the run (a sparse-reward env may evaluate flat for a while before it learns)"""
    keep_best: bool = False
    """keep the weights of the best greedy evaluation so far (in every checkpoint) and export them as policy/policy.onnx at the end, the last policy beside it as policy/step_NNNNNNN.onnx; false: policy/ is the last policy"""
    target_return: float | None = None
    """stop training once the mean return of the last `target_window` finished training episodes is at least this and a greedy evaluation of `target_eval_episodes` episodes confirms it (summary.json's "target" records when); null: train for `num_iterations`"""
    target_window: int = checked(5, POSITIVE)
    """finished training episodes whose mean return is compared with `target_return`"""
    target_eval_episodes: int = checked(10, POSITIVE)
    """episodes of the deterministic policy that must reach `target_return` on average to confirm it (the eval env)"""
    target_recheck_episodes: int = checked(5, POSITIVE)
    """after an evaluation that did not confirm `target_return`, finished training episodes before the next one (so evaluations cannot dominate the run)"""
    collector: CollectorConfig = field(default_factory=CollectorConfig)
    ray: RayConfig = field(default_factory=RayConfig)

    def validate_extra(self) -> None:
        """Rules between an algorithm's own keys, if it has any (``validate`` calls this after the shared ones)."""

    @property
    def total_frames(self) -> int:
        return self.initial_collect_steps + self.num_iterations * self.collect_steps_per_iteration

    @property
    def first_update_frame(self) -> int:
        return self.initial_collect_steps if self.learning_starts is None else self.learning_starts


# --- keys several algorithms (not all) have, each declared once ------------------------------------


@dataclass
class ActorKeys:
    """The keys of the algorithms with an actor network: the SAC family and TD3."""

    actor_fc_layer_params: list[int] = checked(check=LAYER_SIZES, factory=lambda: [256, 256])
    """hidden layer sizes of the actor"""
    policy_delay: int = checked(1, POSITIVE)
    """update the actor (and with it the temperature, the averaged greedy policy or the target networks, as the algorithm has them) on every policy_delay-th update only, the critics on every one (TD3's delayed policy updates, CrossQ's policy_delay); 1: every update"""
    share_encoder: bool = True
    """an image observation (or a Dict with images among its entries), SAC and TD3: one encoder for the actor and the critics, trained by the critics' loss alone; the actor's loss reads its features detached, the critics' targets read them at the next observation without gradients (DrQ's choice for learning from pixels; SAC: two forward passes and one backward through the encoder an update, where an encoder per network makes eight and three). false: the actor and each critic an encoder of its own, each trained by its own loss (SB3's default for SAC and TD3). Nothing for a vector observation"""


@dataclass
class CriticKeys:
    """The critic widths of the algorithms whose critics are not TF-Agents' joint critic: TD3 and CrossQ."""

    critic_fc_layer_params: list[int] = checked(check=LAYER_SIZES, factory=lambda: [256, 256])
    """hidden layer sizes of each critic"""


@dataclass
class OneRateKeys:
    """One learning rate for every network: TD3 and DQN."""

    learning_rate: float = checked(3e-4, LEARNING_RATE)
    """Adam learning rate of every network"""


@dataclass
class ClippedGradientKeys:
    """TF-Agents' gradient clipping: SAC and DQN (their agents have it)."""

    gradient_clipping: float | None = checked(None, GRADIENT_CLIPPING)
    """clip each gradient tensor's norm to this value before the optimisers step, as TF-Agents' SacAgent's and DqnAgent's gradient_clipping does (clip_gradient_norms: per variable, not one norm over all gradients); null: no clipping"""


# --- an algorithm's defaults for keys declared elsewhere --------------------------------------------


@typing.dataclass_transform(field_specifiers=(dataclasses.field,))
def config_class(cls: type | None = None, /, **defaults: Any):
    """``@dataclass`` for an algorithm's config, with its defaults for keys a base class declares:
    ``@config_class(num_iterations=20_000, gamma=(1.0, "DqnAgent's default, which the tutorial relies on"))``.

    A key keeps its one declaration (type, rule, help) where it is written; here it only gets this class's default
    value, and the why, when given, is added to its help (``field_docs``). A key the class declares itself, or one
    no base declares, is a ``TypeError`` at import.
    """

    def wrap(klass: type) -> type:
        own = dict(klass.__dict__.get("__annotations__", {}))
        inherited: dict[str, tuple[dataclasses.Field, type]] = {}
        for base in reversed(klass.__mro__[1:]):
            if dataclasses.is_dataclass(base):
                hints = typing.get_type_hints(base)
                inherited.update({f.name: (f, hints[f.name]) for f in dataclasses.fields(base)})
        annotations: dict[str, Any] = {}
        for name, given in defaults.items():
            if name in own:
                raise TypeError(f"{klass.__name__}.{name} is declared in the class: give its default there")
            if name not in inherited:
                raise TypeError(f"{klass.__name__}: a default for {name!r}, which no base class declares")
            base_field, hint = inherited[name]
            value, why = given if isinstance(given, tuple) else (given, None)
            metadata = {**base_field.metadata, "why": why} if why else dict(base_field.metadata)
            annotations[name] = hint
            if isinstance(value, (list, dict)):
                setattr(klass, name, field(default_factory=functools.partial(copy.deepcopy, value), metadata=metadata))
            else:
                setattr(klass, name, field(default=value, metadata=metadata))
        klass.__annotations__ = {**annotations, **own}
        return dataclass(klass)

    return wrap if cls is None else wrap(cls)


# --- the schema's keys and their help ---------------------------------------------------------------


def _get(cfg, dotted: str):
    for part in dotted.split("."):
        cfg = getattr(cfg, part)
    return cfg


def flat_keys(cls: type, prefix: str = "") -> list[str]:
    """Every settable key of a config class, nested ones dotted (``collector.workers``)."""
    keys = []
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        ftype = hints[f.name]
        if dataclasses.is_dataclass(ftype):
            keys += flat_keys(ftype, prefix + f.name + ".")
        else:
            keys.append(prefix + f.name)
    return keys


def field_docs(cls: type, prefix: str = "") -> dict[str, str]:
    """The docstring under each dataclass field, keyed by dotted name (CleanRL/tyro style help)."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass):
            continue
        try:
            tree = ast.parse(inspect.getsource(klass))
        except (OSError, TypeError):
            continue
        body = tree.body[0].body
        for node, nxt in zip(body, body[1:]):
            if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
                if isinstance(nxt, ast.Expr) and isinstance(getattr(nxt, "value", None), ast.Constant):
                    docs[prefix + node.target.id] = str(nxt.value.value).strip()
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        ftype = hints[f.name]
        if dataclasses.is_dataclass(ftype):
            docs.update(field_docs(ftype, prefix + f.name + "."))
        elif f.metadata.get("why"):  # an algorithm's own default of a key declared elsewhere (config_class)
            value = f.default if f.default is not dataclasses.MISSING else f.default_factory()
            docs[prefix + f.name] = (f"{docs.get(prefix + f.name, '')} (default {json.dumps(value)} here: "
                                     f"{f.metadata['why']})").strip()
    return docs
