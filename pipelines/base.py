"""What every pipeline is: the algorithm contract, the plug-in surface, and the parts they share.

A pipeline (``dqn.DQN``, ``td3.TD3``, ``sac.SAC``, ``crossq.CrossQ``) subclasses ``OffPolicyPipeline``
(CrossQ through ``sac.SAC``, whose actor and schedules it keeps) and declares:

* ``algo``, ``Config`` (its typed config), ``action_space`` (``"discrete"`` or ``"continuous"``) and
  ``loss_names`` (the losses ``update`` returns); its presets are files (``presets/``, whose ``algo`` names it);
* ``__init__``: ``super().__init__(...)`` (config, envs, device, observation key), then
  ``self.assemble(lambda: self.build(...))`` with the user's modules, if any (the base
  constructor never calls ``build``: a subclass has its whole state before it runs);
* ``build(actor=, qvalue=, loss_module=) -> Agent``: the policy, the exploring policy and the loss;
* ``make_optimizers()``, ``make_target_updater()``: made after the loss is on its device;
* ``update(batch, update_index) -> losses``: one update, its losses from the loss module's entry point and
  its optimisers stepped there, in the algorithm's own file (target updates included);
* ``export_module()``: the deterministic policy as a plain ``nn.Module`` on observation tensors.

Adding an algorithm is one new module with such a class and one line in ``pipelines.algos.ALGOS``.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.data import LazyMemmapStorage, LazyTensorStorage, ReplayBuffer
from torchrl.envs import EnvBase
from torchrl.objectives import LossModule
from torchrl.record.loggers import Logger

from rlpipe.envs import (
    EnvError,
    env_id_of,
    env_label,
    gym_env_under,
    image_scale,
    is_discrete,
    make_env,
    observation_images,
    observation_layout,
    observation_rescaling,
    resolve_env_id,
)
from rlpipe.envs.observations import GOAL_KEYS, discrete_entries, goal_env, image_frame, is_atari
from rlpipe.modules import fast as fast_parts
from rlpipe.modules.encoders import FEATURES_KEY, DictEncoder, make_image_encoder
from rlpipe.modules.fast.optim import LeanAdam, clip_gradient_norms
from rlpipe.modules.fast.sampling import sample
from rlpipe.modules.fast.target_updates import make_target_updater
from rlpipe.modules.frames import FrameReplayBuffer
from rlpipe.modules.hindsight import TRAJ_IDS, HindsightReplayBuffer
from rlpipe.modules.normalization import RunningObservationNorm
from rlpipe.modules.plain_policy import OnRescaledObservations
from rlpipe.pipelines import presets as preset_files
from rlpipe.pipelines.artifacts import checkpoint as ckpt
from rlpipe.pipelines.config import EVAL_SEED_OFFSET, PresetInfo, TrainConfig, env_options, layer_sizes, validate
from rlpipe.pipelines.errors import InputError
from rlpipe.pipelines.own_parts import (
    EnvArg,
    check_action_space,
    eval_env_of,
    factory_and_env,
    image_observation,
    observation_key_in,
    observation_key_of,
)
from rlpipe.pipelines.system.memory import check_memory
from rlpipe.pipelines.system.runtime import start_resource_tracker
from rlpipe.pipelines.training.loop import TrainResult
from rlpipe.pipelines.training.nstep import STEPS_KEY
from rlpipe.pipelines.training.run import Run, seed_everything
from rlpipe.pipelines.training.state import RunState
from rlpipe.pipelines.training.threads import choose_threads
from rlpipe.pipelines.training.triggers import Trigger
from rlpipe.pipelines.training.update_graph import GraphedUpdate
from rlpipe.pipelines.workers.backend import CollectorBackend
from rlpipe.pipelines.workers.factory import backend_class, make_backend
from rlpipe.pipelines.workers.local import push_weights as push_collector_weights

__all__ = ["Agent", "OffPolicyPipeline", "observation_key_of", "own_env_label", "seed_everything"]


def own_env_label(env: EnvBase, configured: str) -> str:
    """The env a run on a user's own ``env`` is labelled with: its gymnasium id where it was made from one;
    else the config's ``env`` when that names no gymnasium id (the user's own name for it); else (the
    config still names its preset's env, which this is not) the wrapped env's class name."""
    found = env_id_of(env)
    if found is not None:
        return found
    try:
        resolve_env_id(configured)
    except EnvError:
        return configured if configured else env_label(env)
    return env_label(env)


@dataclass
class Agent:
    """What an algorithm builds: the modules the loop trains, runs and saves."""

    policy: nn.Module
    """deterministic policy (evaluation, export): reads the observation, writes ``"action"``"""
    collect_policy: nn.Module
    """exploring policy (collection); may be ``policy`` itself when it explores by sampling"""
    loss_module: LossModule


class _PresetFiles:
    """``Pipeline.presets`` (name -> its file) or ``Pipeline.preset_info`` (name -> the task it is for, where its
    file says): the shipped preset files whose ``algo`` is the pipeline's, in ``presets.names()`` order."""

    def __init__(self, info: bool):
        self.info = info

    def __get__(self, obj, owner) -> dict:
        names = [name for name, algo in preset_files.names().items() if algo == owner.algo]
        if self.info:
            return {name: info for name in names if (info := preset_files.info(name)) is not None}
        return {name: preset_files.source(name) for name in names}


class OffPolicyPipeline:
    """Base of every pipeline: a TorchRL env, modules and loss, trained by the shared ``Loop``."""

    algo: ClassVar[str]
    Config: ClassVar[type[TrainConfig]]
    action_space: ClassVar[str]  # "discrete" or "continuous"
    presets: ClassVar[dict[str, str]] = _PresetFiles(info=False)
    """this algorithm's preset names -> their files (``presets/NAME.yaml``)"""
    preset_info: ClassVar[dict[str, PresetInfo]] = _PresetFiles(info=True)
    """this algorithm's preset names -> the task each is for (env, targets); a preset without one has none"""
    loss_names: ClassVar[tuple[str, ...]] = ("loss",)

    policy: nn.Module
    collect_policy: nn.Module
    loss_module: LossModule
    optimizers: dict[str, torch.optim.Optimizer]

    @classmethod
    def preset(cls, name: str | None = None) -> TrainConfig:
        """A fresh config of the named preset or preset file (default: the preset named for the algorithm, its
        tutorial's)."""
        algo, cfg = preset_files.load(name or cls.algo)
        if algo != cls.algo:
            raise InputError(f"preset {name!r} is a {algo} preset; expected one of {cls.algo}'s: {', '.join(cls.presets)}")
        return cfg

    def __init__(self, config: TrainConfig | None = None, *, env: EnvArg = None, eval_env: EnvArg = None,
                 observation_key: str | None = None):
        start_resource_tracker()  # before the replay buffer's locks start it, not deaf to SIGHUP
        cfg = config if config is not None else self.Config()
        if not isinstance(cfg, self.Config):
            raise InputError(f"config is a {type(cfg).__name__}; expected {self.Config.__name__} for {self.algo}")
        validate(cfg)
        changed = fast_parts.problems() if cfg.fast else []
        if changed:
            raise InputError(f"fast=true: rlpipe's fast parts (rlpipe.modules.fast) cannot vouch for this install: "
                             f"{'; '.join(changed)}; expected fast=false (TorchRL's own parts), or torch 2.13 and "
                             "torchrl 0.14")
        self.device = torch.device(cfg.device)
        self.env_fn, self.env = factory_and_env(env, cfg)
        # Evaluation plays one env copy of whole episodes: the collection env may be a vector of them, or an Atari
        # game whose training episodes end at each lost life.
        own_differs = env is None and (cfg.collector.envs_per_worker > 1
                                       or cfg.episodic_life and is_atari(resolve_env_id(cfg.env)))
        self.eval_env_fn = self.env_fn if not own_differs else functools.partial(
            make_env, cfg.env, device="cpu", **env_options(cfg), **cfg.env_kwargs)
        self.eval_env = eval_env_of(eval_env, self.eval_env_fn)
        self.env.set_seed(cfg.seed)
        self.eval_env.set_seed(cfg.seed + EVAL_SEED_OFFSET)
        # Runs are labelled (config.json, checkpoints, plots) with the env actually used.
        self.config = cfg if env is None else dataclasses.replace(cfg, env=own_env_label(self.env, cfg.env))
        self.action_spec = self.env.action_spec_unbatched
        check_action_space(self.algo, self.action_space, self.action_spec, self.config.env)
        self.observation_key = observation_key_in(self.env, observation_key, self.config.env)
        self.image_shape, self.image_scale = image_observation(self.env, self.observation_key, self.config.env)
        gym_env = gym_env_under(self.env)
        # the images among a Dict env's entries, joined into its observation vector (a DictEncoder reads them)
        self.image_entries = observation_images(gym_env) if gym_env is not None else {}
        spec = self.env.observation_spec[self.observation_key]
        # one observation as the policy takes it (exported policies too): a vector, or an image stack
        self.observation_shape = tuple(spec.shape[len(self.env.batch_size):])
        self.observation_dtype = spec.dtype
        # what the heads read: the observation vector, or the encoder's features of the images in it
        self.observation_dim = (int(self.env.observation_spec[self.observation_key].shape[-1]) if not self.encodes_images
                                else self.make_encoder().out_features)
        self.hindsight = self._hindsight()
        self.normalizer = None
        if cfg.normalize_observations:
            if self.encodes_images:
                image = self.image_shape or {key: entry.shape for key, entry in self.image_entries.items()}
                raise InputError(f"normalize_observations=true: env {self.config.env!r} observes an image "
                                 f"{image}, which its encoder scales itself; expected it for vector "
                                 "observations only")
            self.normalizer = RunningObservationNorm(self.observation_dim)
        action_dim = int(self.action_spec.space.n) if is_discrete(self.action_spec) else int(self.action_spec.shape[-1])
        check_memory(cfg, self.env, self.observation_key, action_dim, self.device,  # before a network is built
                     stored=self._replay_keys(), networks=layer_sizes(cfg), frame_bytes=self._frame_bytes())
        self.state = RunState.fresh(cfg)

    def _hindsight(self) -> dict[str, Any] | None:
        """What HER relabels with (``compute_reward`` and the goals' places in the observation), where it is on:
        ``config.her``, or by default for a goal env; ``InputError`` for HER asked of an env without goals."""
        cfg = self.config
        gym_env = gym_env_under(self.env)
        layout = observation_layout(gym_env) if gym_env is not None else None
        is_goal_env = gym_env is not None and goal_env(gym_env)
        if cfg.her and not is_goal_env:
            raise InputError(f"her=true: env {cfg.env!r} is not a goal env read here (a Dict observation with "
                             f"{' and '.join(GOAL_KEYS)} among the entries read, and a compute_reward method); expected "
                             "her=false, or a goal env made from config.env")
        if not (cfg.her if cfg.her is not None else is_goal_env):
            return None
        if cfg.n_step > 1:
            raise InputError(f"her with n_step={cfg.n_step}: a relabelled goal changes every reward of an n-step "
                             "return; expected n_step=1 (or her=false)")
        return {"compute_reward": gym_env.unwrapped.compute_reward, "achieved": layout["achieved_goal"],
                "desired": layout["desired_goal"], "observation_key": self.observation_key,
                "her_ratio": cfg.her_ratio}

    @property
    def encodes_images(self) -> bool:
        """Whether the networks read the observation through a convolutional encoder: an image, or a Dict with
        images among its entries."""
        return self.image_shape is not None or bool(self.image_entries)

    def make_encoder(self) -> nn.Module | None:
        """What each network that reads the observation puts in front of its head: a new encoder of an image
        or of a Dict with images in it (``modules.encoders``), the one running normaliser
        (``normalize_observations``), or None."""
        if self.image_entries:
            return DictEncoder(self.observation_entries(), {k: (e.shape, e.scale) for k, e in self.image_entries.items()})
        if self.image_shape is None:
            return self.normalizer
        return make_image_encoder(self.image_shape, self.image_scale)

    shared_encoder: nn.Module | None = None
    """the encoder the actor and critics share (SAC's and TD3's ``share_encoder``), set where the pipeline makes
    them; the update runs it (``encode``) and steps it with the critics"""

    def shares_encoder(self) -> bool:
        """Whether the actor and critics the pipeline makes share one encoder: ``share_encoder`` and an image
        among the observations."""
        return bool(getattr(self.config, "share_encoder", False)) and self.encodes_images

    def critic_input(self) -> tuple[str, nn.Module | None]:
        """(the key a critic made here reads, the encoder in front of its head): the shared encoder's features
        and none, or the observation and an encoder of its own (``make_encoder``)."""
        if self.shared_encoder is not None:
            return FEATURES_KEY, None
        return self.observation_key, self.make_encoder()

    def encode(self, batch: TensorDictBase) -> tuple[TensorDictBase, torch.Tensor]:
        """A shallow copy of ``batch`` with the shared encoder's features of its observations (with gradients:
        the critics' loss trains the encoder) and of its next observations (without: the critics' targets) under
        ``FEATURES_KEY``; and the features (an actor's loss reads them detached, DrQ's choice)."""
        key = self.observation_key
        features = self.shared_encoder(batch.get(key))
        with torch.no_grad():
            next_features = self.shared_encoder(batch.get(("next", key)))
        batch = batch.clone(False)
        batch.set(FEATURES_KEY, features)
        batch.set(("next", FEATURES_KEY), next_features)
        return batch, features

    def on_block(self, batch: TensorDictBase) -> None:
        """Called with each collected block before it is stored: the running normaliser learns its observations."""
        if self.normalizer is not None:
            self.normalizer.update(batch.get(self.observation_key))

    # --- what a pipeline supplies -----------------------------------------------------------------

    def build(self, *, actor: nn.Module | None = None, qvalue: nn.Module | None = None,
              loss_module: LossModule | None = None) -> Agent:
        """The policy, exploring policy and loss, from the user's modules where given."""
        raise NotImplementedError

    def make_optimizers(self) -> dict[str, torch.optim.Optimizer]:
        raise NotImplementedError

    def make_target_updater(self):
        """A TorchRL target updater for the loss, or None."""
        return None

    def adam(self, params, **kwargs) -> torch.optim.Adam:
        """An Adam optimiser over ``params``: ``LeanAdam`` (the same steps), or torch's own with ``fast=false``."""
        return (LeanAdam if self.config.fast else torch.optim.Adam)(list(params), **kwargs)

    def soft_update(self, tau: float, target_networks: bool = True):
        """The loss's target networks moved ``tau`` of the way to the online ones at each ``step()``:
        ``ForeachSoftUpdate``, or TorchRL's ``SoftUpdate`` with ``fast=false`` (``make_target_updater``)."""
        return make_target_updater(self.loss_module, tau, target_networks, fast=self.config.fast)

    def sample(self) -> TensorDictBase:
        """One replay batch: ``replay_buffer.sample()``, gathered directly where the buffer allows it unless
        ``fast=false`` (``modules.fast.sampling``)."""
        return sample(self.replay_buffer) if self.config.fast else self.replay_buffer.sample()

    def update(self, batch: TensorDictBase, update_index: int) -> dict[str, torch.Tensor]:
        """Update ``update_index`` (1, 2, ...) on ``batch``; returns detached losses named as in ``loss_names``."""
        raise NotImplementedError

    def clip_gradients(self, name: str, clip: float | None, stacked: bool = False) -> None:
        """Clip each gradient tensor of optimiser ``name``'s parameters to a norm of ``clip`` (None: nothing), as
        TF-Agents' ``gradient_clipping`` does (``stacked``: twin critics stacked [2, ...], one critic at a time)."""
        if clip is not None:
            params = [p for group in self.optimizers[name].param_groups for p in group["params"]]
            clip_gradient_norms(params, clip, stacked=stacked, fast=self.config.fast)

    def on_frames(self, frames: int) -> None:
        """Called after each collected block with its frame count (exploration schedules go here)."""

    def export_module(self) -> nn.Module:
        """The deterministic policy as a plain module: observations [B, D] -> actions (the observations the
        networks read: rescaled with ``rescale_observations``; ``exported_policy`` takes the env's own)."""
        raise NotImplementedError

    def exported_policy(self) -> nn.Module:
        """What a run exports to ``policy/``: the policy on the env's own observations, i.e. ``export_module()``
        preceded by the map to [-1, 1] that ``rescale_observations`` puts in the envs (``OnRescaledObservations``)."""
        module = self.export_module()
        bounds = observation_rescaling(self.env) if self.config.rescale_observations else None
        return module if bounds is None else OnRescaledObservations(module, *bounds)

    # --- assembled once, the same for every pipeline ------------------------------------------------

    def assemble(self, build: Callable[[], Agent]) -> None:
        """Call ``build`` (networks drawn from the config's seed, the caller's random state left as it
        was), put its modules on the pipeline's device, then make optimisers, target updater, buffer."""
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(self.config.seed)
            agent = build()
        self.policy = agent.policy.to(self.device)
        self.collect_policy = agent.collect_policy.to(self.device)
        self.loss_module = agent.loss_module.to(self.device)
        if self.normalizer is not None:  # the loss's own copies of the statistics (its critics' stacked buffers)
            self.normalizer.find_mirrors(self.loss_module)
        if self.config.n_step > 1 and _value_estimator(self.loss_module) is None:
            raise InputError(f"n_step={self.config.n_step} needs a loss that bootstraps through a TorchRL value "
                             f"estimator (its gamma, and steps_to_next_obs); {type(self.loss_module).__name__} has "
                             "none: expected n_step=1 or a TorchRL loss")
        self.optimizers = self.make_optimizers()
        self.target_updater = self.make_target_updater()
        self.replay_buffer = self.make_replay_buffer()
        self.replay_keys = self._replay_keys()
        self.update_step = self.make_update_step()

    def _replay_keys(self) -> list | None:
        """What the loop stores of each transition (None: everything the collector returns): the keys
        the loss reads, 6 of the collector's 16 (sampling them costs about a third less). Before the
        loss is built (the memory check), the transition's keys, which every built-in loss reads."""
        if self.config.replay_all_keys:
            return None
        steps = [STEPS_KEY] if self.config.n_step > 1 else []
        if self.hindsight is not None or self._stacks_frames():  # the buffer chains each episode's steps by id
            steps += [TRAJ_IDS]
        if hasattr(self, "loss_module"):
            # the features of a shared encoder are computed from the observations at each update (FEATURES_KEY)
            stored = {FEATURES_KEY: self.observation_key, ("next", FEATURES_KEY): ("next", self.observation_key)}
            return list(dict.fromkeys([stored.get(key, key) for key in self.loss_module.in_keys] + steps))
        obs = self.observation_key
        return [obs, "action", ("next", obs), ("next", "reward"), ("next", "done"), ("next", "terminated"), *steps]

    def update_periods(self) -> list[int]:
        """The index periods ``update`` branches on (``update_index % p == 0``), each dividing the
        next: CUDA graphs record one graph per branch pattern (``pipelines/training/update_graph.py``)."""
        return [self.config.target_update_period]

    def make_update_step(self) -> Callable[[TensorDictBase, int], dict[str, torch.Tensor]]:
        """``update``, compiled with ``compile=true``, replayed as CUDA graphs with ``cudagraph``."""
        cfg = self.config
        step = torch.compile(self.update) if cfg.compile else self.update
        if self.device.type == "cuda" and (cfg.compile if cfg.cudagraph is None else cfg.cudagraph):
            step = GraphedUpdate(step, self.update_periods())
        return step

    def observation_entries(self) -> dict[str, tuple[int, int]] | None:
        """A Dict env's entries and where each lies in the observation vector (the exported policy takes them by
        name), or None."""
        gym_env = gym_env_under(self.env)
        return observation_layout(gym_env) if gym_env is not None else None

    def observation_entry_images(self) -> dict[str, tuple[tuple[int, ...], bool]]:
        """The images among a Dict env's entries, each as the env gives it: (its shape, whether channels come
        last). The exported policy takes them so, as uint8."""
        return {key: (entry.env_shape, entry.channels_last) for key, entry in self.image_entries.items()}

    def export_inputs(self) -> dict[str, Any]:
        """``export_policy``'s keywords for the env's own observation, where rlpipe's wrappers changed it: a Dict
        env's entries by name (its images as uint8, its discrete entries as their integers), or an image's own
        frame where frames are not stacked."""
        gym_env = gym_env_under(self.env)
        if gym_env is None:
            return {}
        if self.image_shape is not None:
            frame = image_frame(gym_env)
            return {"frame": frame} if frame is not None else {}
        return {"entries": self.observation_entries(), "images": self.observation_entry_images(),
                "discrete": discrete_entries(gym_env)}

    def export_info(self) -> dict[str, Any]:
        spec = self.action_spec
        info = {"algo": self.algo, "env": self.config.env, "env_kwargs": dict(self.config.env_kwargs),
                "observation_key": str(self.observation_key)}
        layout = self.observation_entries()
        if layout is not None:  # a Dict env's entries, joined in this order into the observation vector
            info["observation_entries"] = {key: list(span) for key, span in layout.items()}
        if self.config.frame_stack > 1:
            info["frame_stack"] = self.config.frame_stack
        if is_discrete(spec):
            return {**info, "action": "discrete", "num_actions": int(spec.space.n)}
        return {**info, "action": "continuous", "low": spec.space.low.flatten().tolist(),
                "high": spec.space.high.flatten().tolist()}

    # --- the parts, as plain TorchRL objects -------------------------------------------------------

    def make_replay_buffer(self) -> ReplayBuffer:
        cfg = self.config
        on_disk = cfg.replay_buffer_storage == "memmap"
        storage = (LazyMemmapStorage(cfg.replay_buffer_capacity, device=self.device) if on_disk
                   else LazyTensorStorage(cfg.replay_buffer_capacity, device=self.device))
        if self.hindsight is not None:
            return HindsightReplayBuffer(storage=storage, batch_size=cfg.batch_size, **self.hindsight)
        if self._stacks_frames():
            return FrameReplayBuffer(storage=storage, batch_size=cfg.batch_size, capacity=cfg.replay_buffer_capacity,
                                     frame_stack=cfg.frame_stack, channels=self.image_shape[0] // cfg.frame_stack,
                                     observation_key=self.observation_key, memmap=on_disk)
        return ReplayBuffer(storage=storage, batch_size=cfg.batch_size)

    def _stacks_frames(self) -> bool:
        """Whether the replay buffer stores each frame once (``modules.frames``): an image stack the pipeline's
        own env made (``make_env``'s ``ImageObservation``: its channel layout known), stored on the CPU, with
        one-step transitions (an n-step transition's next observation is not the next step's, which the frame
        chain assumes: those store both stacks, uint8)."""
        return (self.image_shape is not None and image_scale(self.env) is not None and self.device.type == "cpu"
                and self.config.n_step == 1)

    def _frame_bytes(self) -> int | None:
        """A frame-stacking buffer's bytes per transition for its frames and their slots, else None."""
        if not self._stacks_frames():
            return None
        frame = math.prod(self.image_shape) // self.config.frame_stack
        return frame + frame // 16 + 16 * (self.config.frame_stack + 1)

    def make_backend(self) -> CollectorBackend:
        """The collector backend ``collector.backend`` names (local processes, Ray actors), not started:
        the exploring policy collects, on envs from the pipeline's env function."""
        return make_backend(self.config, policy=self.collect_policy, env_fn=self.env_fn, env=self.env,
                            device=self.device, learner_version=lambda: self.state.updates)

    def make_collector(self, total_frames: int, init_random_frames: int):
        """A started collector for a loop of one's own: a TorchRL collector (``Collector``,
        ``MultiSyncCollector`` or ``MultiAsyncCollector``; with ``collector.backend=ray``, the Ray
        backend, which iterates, ``set_seed``s and ``shutdown``s as one does) for ``total_frames``
        frames, the first ``init_random_frames`` random (none with ``initial_collect_policy=collect``).
        Push the learner's weights to it with ``push_weights``; ``shutdown()`` it when done."""
        return self.make_backend().start(total_frames, init_random_frames).collector

    def metrics_columns(self) -> list[str]:
        """metrics.csv's columns past the losses and speeds: what the collector backend reports, and a goal
        env's evaluated ``success_rate``."""
        gym_env = gym_env_under(self.env)
        success = ["success_rate"] if gym_env is not None and goal_env(gym_env) else []
        return [*backend_class(self.config).metric_columns, *success]

    def push_weights(self, collector) -> None:
        """Send the policy's weights to a collector's workers (``make_collector``'s, or a backend's;
        in-process collection shares them; Ray actors get them each time they are asked for a block).

        Raises ``supervision.WorkerFailure`` if a worker is dead or does not take them within
        ``collector.timeout`` seconds."""
        if isinstance(collector, CollectorBackend):
            collector.push_weights()
        else:
            push_collector_weights(collector)

    # --- checkpoint state -------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        return {
            "algo": self.algo,
            "env": self.config.env,
            "loss": self.loss_module.state_dict(),
            "collect_policy": self.collect_policy.state_dict(),
            "optimizers": {k: opt.state_dict() for k, opt in self.optimizers.items()},
            **self.state.state_dict(),
            "replay_buffer": ckpt.replay_buffer_state(self.replay_buffer),
            "rng": ckpt.rng_state(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore from ``state_dict`` output; ``InputError`` if it does not fit this pipeline."""
        try:
            self.loss_module.load_state_dict(state["loss"])
            self.collect_policy.load_state_dict(state["collect_policy"])
            for k, opt in self.optimizers.items():
                opt.load_state_dict(state["optimizers"][k])
            self.state.load_state_dict(state)
            self.replay_buffer.empty()
            ckpt.load_replay_buffer(self.replay_buffer, state["replay_buffer"], keys=self.replay_keys)
            ckpt.set_rng_state(state["rng"])
        except (KeyError, ValueError, RuntimeError, TypeError, IndexError) as exc:
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise InputError(f"checkpoint does not fit this {self.algo} pipeline and config: {first[:200]}") from exc

    # --- training ---------------------------------------------------------------------------------

    def train(self, out: str | Path | None = None, *, resume: bool = False, progress: bool = True,
              logger: Logger | None = None, callbacks: Sequence[Callable[[dict], None]] = (),
              triggers: Sequence[Trigger] = ()) -> TrainResult:
        """Train (or, with ``resume=True``, continue the run in ``out``); write everything into the run directory.

        ``logger``: any TorchRL ``Logger`` (default: TensorBoard events in ``out/tb``).
        ``callbacks``: functions called with each metrics row as it is written.
        ``triggers``: more ``Trigger``s, run after the built-in ones (log, eval, export, save).
        Ctrl-C (SIGINT) saves a checkpoint at the next safe point and raises ``KeyboardInterrupt``;
        ``train(out, resume=True)`` then continues from there. A loss or parameter that turns NaN or
        infinite raises ``TrainingDiverged`` at the end of that collected block, saving nothing more:
        the last checkpoint is the run's last finite state. (The run's lifecycle: ``training.run.Run``.)
        """
        run = Run(self)
        with run.session(out, resume=resume, progress=progress, logger=logger, callbacks=callbacks,
                         triggers=triggers) as loop:
            if loop is not None:  # None: a finished run, resumed with nothing owed
                loop.run()  # collect, update, triggers: training/loop.py
        return run.result

    def choose_threads(self) -> int:
        """The learner's torch threads for this machine and collector layout: ``training.threads.choose_threads``."""
        return choose_threads(self.config)


def _value_estimator(loss: nn.Module):
    """``loss``'s TorchRL value estimator (built on first use, as TorchRL's losses do), or None for a loss without one."""
    try:
        return loss.value_estimator
    except (AttributeError, NotImplementedError):
        return None
