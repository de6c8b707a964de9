"""The plug-in surface: what a user's own env, eval env and modules must be, checked before a pipeline
builds anything, each refusal one line naming what is wrong and what is expected.

``OffPolicyPipeline.__init__`` calls these; an algorithm's constructor calls ``observation_key_of``
to read the observation key off the user's actor or loss.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import torch
from torch import nn
from torchrl.envs import EnvBase

from rlpipe.envs import EnvError, describe_action_space, image_scale, is_discrete, make_env, with_episode_return
from rlpipe.pipelines.algos import ALGOS, pipeline_class
from rlpipe.pipelines.config import TrainConfig, env_options
from rlpipe.pipelines.errors import InputError

__all__ = ["EnvArg", "check_action_space", "eval_env_of", "factory_and_env", "image_observation", "observation_key_in",
           "observation_key_of"]

EnvArg = EnvBase | Callable[[], EnvBase] | None

# entries the standard transforms add to an env's observations: never what a network reads
_BOOKKEEPING = ("episode_reward", "step_count", "is_init")


def factory_and_env(env: EnvArg, cfg: TrainConfig) -> tuple[Callable[[], EnvBase] | None, EnvBase]:
    """(a picklable factory, or None for an instance; the learner's env), with what the loop needs added."""
    if env is not None and cfg.collector.envs_per_worker > 1:
        raise InputError(f"collector.envs_per_worker={cfg.collector.envs_per_worker} makes vector envs from config.env; "
                         "with env= given, expected collector.envs_per_worker=1 (batch your own env, e.g. a SerialEnv)")
    if env is not None and cfg.rescale_observations:
        raise InputError("rescale_observations=true rescales the envs made from config.env; with env= given, expected "
                         "rescale_observations=false (rescale in your own env, e.g. gymnasium's RescaleObservation)")
    if env is not None and (cfg.observation_keys or cfg.frame_stack > 1):
        raise InputError("observation_keys and frame_stack shape the envs made from config.env; with env= given, "
                         "expected them unset (select and stack in your own env, e.g. TorchRL's CatTensors, CatFrames)")
    if env is None:
        factory = functools.partial(make_env, cfg.env, device="cpu", num_envs=cfg.collector.envs_per_worker,
                                    **env_options(cfg, training=True), **cfg.env_kwargs)
    elif isinstance(env, EnvBase):
        if cfg.collector.workers > 1 or not cfg.collector.sync:
            raise InputError("collector.workers>1 or collector.sync=false: pass env as a function that makes the env")
        if cfg.eval_in_background:
            raise InputError("eval_in_background=true: pass env as a function that makes the env")
        return None, with_episode_return(env)
    elif callable(env):
        factory = functools.partial(_made_with_episode_return, env)
    else:
        raise InputError(f"env is a {type(env).__name__}; expected a TorchRL EnvBase or a function returning one")
    try:
        made = factory()
    except EnvError as exc:
        raise InputError(str(exc)) from exc
    if not isinstance(made, EnvBase):
        raise InputError(f"env() returned a {type(made).__name__}; expected a TorchRL EnvBase")
    return factory, made


def _made_with_episode_return(env_fn: Callable[[], EnvBase]) -> EnvBase:
    return with_episode_return(env_fn())


def eval_env_of(eval_env: EnvArg, eval_env_fn: Callable[[], EnvBase] | None) -> EnvBase:
    """The env evaluations run on: the user's (an env or a function making one), else another ``eval_env_fn()``."""
    if eval_env is None:
        if eval_env_fn is None:
            raise InputError("env is an instance: pass eval_env as well (an env or a function making one), "
                             "or pass env as a function that makes the env")
        return eval_env_fn()
    env = eval_env() if callable(eval_env) and not isinstance(eval_env, EnvBase) else eval_env
    if not isinstance(env, EnvBase):
        raise InputError(f"eval_env is a {type(env).__name__}; expected a TorchRL EnvBase or a function returning one")
    return env


def check_action_space(algo: str, action_space: str, spec, env_label: str) -> None:
    """``InputError`` unless the env's actions are of the kind ``algo`` learns (``"discrete"`` or ``"continuous"``)."""
    if is_discrete(spec) == (action_space == "discrete"):
        return
    needs = "discrete action space" if action_space == "discrete" else "continuous (Box) action space"
    other = "continuous" if action_space == "discrete" else "discrete"
    learners = [name for name in ALGOS if pipeline_class(name).action_space == other]
    names = f"{', '.join(learners[:-1])} or {learners[-1]}" if len(learners) > 1 else learners[0]
    raise InputError(f"{algo.upper()} needs a {needs}; env {env_label!r} has a {describe_action_space(spec)} "
                     f"(use {names} for {other} actions)")


def observation_key_in(env: EnvBase, given: str | None, env_label: str) -> str:
    """The observation entry the networks read: ``given``, else ``"observation"``, else the env's only one."""
    keys = [k for k in env.observation_spec.keys() if k not in _BOOKKEEPING]
    key = given or ("observation" if "observation" in keys else keys[0] if len(keys) == 1 else None)
    if key not in keys:
        raise InputError(f"env {env_label!r} has no observation {key or 'observation'!r} (it has "
                         f"{', '.join(map(str, keys))}); pass observation_key=... or an actor that reads one of them")
    return key


def image_observation(env: EnvBase, key: str, env_label: str) -> tuple[tuple[int, int, int] | None, float]:
    """``((C, H, W), scale)`` where the observation ``key`` is an image (3 dimensions: an encoder reads it), else
    ``(None, 1.0)``. ``scale``: one unit as a fraction of full brightness (1/255 for uint8 pictures). A float
    image must already be in [0, 1]; one the networks cannot read is an ``InputError``."""
    spec = env.observation_spec[key]
    dims = tuple(spec.shape[len(env.batch_size):])
    if len(dims) == 1:
        return None, 1.0
    if len(dims) != 3:
        raise InputError(f"env {env_label!r} observes {key!r} of shape {dims}; expected a vector or an image of "
                         "[C, H, W]")
    shape = dims
    if spec.dtype == torch.uint8:
        scale = image_scale(env)
        return shape, 1 / 255 if scale is None else scale
    if spec.dtype.is_floating_point:
        return shape, 1.0
    raise InputError(f"env {env_label!r} observes an image {key!r} of dtype {spec.dtype}; expected uint8 (or float "
                     "in [0, 1])")


def observation_key_of(*modules: nn.Module | None) -> str | None:
    """The observation key the first given module reads (an actor's first in_key, or a loss's actor's)."""
    for module in modules:
        if module is None:
            continue
        for name in ("actor_network", "value_network"):  # a loss: the network that reads observations
            if getattr(module, name, None) is not None:
                module = getattr(module, name)
                break
        in_keys = getattr(module, "in_keys", None)
        if in_keys:
            key = in_keys[0]
            return key if isinstance(key, str) else None
    return None
