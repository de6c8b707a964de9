"""Environments: gymnasium ids -> TorchRL envs with the standard transforms.

``make_env`` is the one door: it resolves the tutorials' ids (``MinitaurBulletEnv-v0`` names our
gymnasium-native Minitaur) and a user's own env named ``module:Target`` or ``module:Id-v0``
(``user.py``), rejects unknown ids with the closest valid ones, and returns a plain TorchRL
``TransformedEnv`` that a user can hand to any TorchRL collector.

Importing this package registers ``rlpipe/MinitaurBullet-v0`` with gymnasium.
"""

from __future__ import annotations

import difflib
import re

import gymnasium
import numpy as np
import torch
from gymnasium import spaces
from gymnasium.error import DependencyNotInstalled
from gymnasium.wrappers import DtypeObservation, FlattenObservation, RescaleObservation
from torchrl.data import Categorical, OneHot, TensorSpec
from torchrl.envs import (
    Compose,
    DoubleToFloat,
    EnvBase,
    GymEnv,
    GymWrapper,
    InitTracker,
    RewardSum,
    StepCounter,
    TransformedEnv,
)
from torchrl.envs.batched_envs import BatchedEnvBase

from rlpipe.envs import user
from rlpipe.envs.observations import (
    DictObservation,
    ImageObservation,
    atari_preprocessed,
    dict_keys,
    goal_env,
    is_atari,
    is_image,
    observation_images,
    observation_layout,
    register_optional_families,
    wrapper_of,
)

__all__ = [
    "EnvError", "MINITAUR_ID", "describe_action_space", "env_id_of", "env_label", "is_discrete", "make_env", "resolve_env_id",
    "observation_rescaling", "rescaling_bounds", "with_episode_return", "gym_env_under", "goal_env", "observed", "observation_images", "observation_layout",
    "image_scale",
]

MINITAUR_ID = "rlpipe/MinitaurBullet-v0"

if MINITAUR_ID not in gymnasium.registry:
    gymnasium.register(
        id=MINITAUR_ID,
        entry_point="rlpipe.envs.minitaur:MinitaurBulletEnv",
        max_episode_steps=1000,
        reward_threshold=15.0,
    )

# The tutorials' ids that name something else here.
_ALIASES = {"MinitaurBulletEnv-v0": MINITAUR_ID}

# gymnasium's env families and the pip extra that installs what each needs (gymnasium's own setup).
_EXTRAS = {
    "gymnasium.envs.box2d": "gymnasium[box2d]",
    "gymnasium.envs.mujoco": "gymnasium[mujoco]",
    "gymnasium.envs.toy_text": "gymnasium[toy-text]",
    "gymnasium.envs.classic_control": "gymnasium[classic-control]",
    "ale_py": "rlpipe[atari]",
}
# Namespaces registered only once their package is imported: an id in one is not a typo.
_NAMESPACE_EXTRAS = {"ALE": "rlpipe[atari]", "MinAtar": "rlpipe[minatar]"}

# Observation spaces gymnasium's FlattenObservation turns into one flat vector (one-hot for discrete parts).
_FLATTENED = (spaces.Box, spaces.Discrete, spaces.MultiDiscrete, spaces.MultiBinary, spaces.Tuple)


class EnvError(ValueError):
    """An env id or env that cannot serve the request; the message says what is expected."""


def resolve_env_id(env_id: str) -> str:
    """Return the gymnasium id that ``env_id`` names, or raise ``EnvError`` with close matches.

    ``module:Target`` and ``module:Id-v0`` import the module (``user.resolve``)."""
    if user.is_user_env(env_id):
        return user.resolve(env_id, EnvError)
    env_id = _ALIASES.get(env_id, env_id)
    register_optional_families(env_id)
    if env_id in gymnasium.registry:
        return env_id
    namespace = env_id.split("/", 1)[0] if "/" in env_id else None
    if namespace in _NAMESPACE_EXTRAS:
        extra = _NAMESPACE_EXTRAS[namespace]
        raise EnvError(f"env id {env_id!r} needs the {extra} extra, which is not installed; expected it installed "
                       f"(pip install \"{extra}\") or another env id")
    known = list(gymnasium.registry) + list(_ALIASES)
    close = difflib.get_close_matches(env_id, known, n=3, cutoff=0.5)
    hint = f"; did you mean {', '.join(repr(c) for c in close)}?" if close else "; expected a gymnasium id such as 'CartPole-v1'"
    raise EnvError(f"unknown env id {env_id!r}{hint}")


def make_env(
    env_id: str,
    *,
    seed: int | None = None,
    device: str = "cpu",
    render_mode: str | None = None,
    num_envs: int = 1,
    rescale_observations: bool = False,
    observation_keys: list[str] | None = None,
    frame_stack: int = 1,
    episodic_life: bool = False,
    **gym_kwargs,
) -> TransformedEnv:
    """A TorchRL env for ``env_id`` with ``StepCounter``, ``RewardSum``, ``InitTracker``, and
    ``DoubleToFloat`` where the env has float64 entries (MuJoCo's observations).

    Discrete actions are integer indices (``categorical_action_encoding``), as in gymnasium, so an
    exported policy's action goes straight into ``gymnasium.Env.step``. Extra keywords go to
    ``gymnasium.make``, i.e. the env's constructor (for example Minitaur's ``env_randomizer=None``),
    checked against its signature first.

    ``rescale_observations`` maps a Box observation from its bounds to [-1, 1] with gymnasium's
    ``RescaleObservation`` (``rescaling_bounds`` says from what), before TorchRL sees it.

    A Dict observation becomes one float vector of the entries ``observation_keys`` names (default: all),
    an image stays uint8, channels first, with the last ``frame_stack`` frames stacked, and Atari ids get
    the standard preprocessing (``rlpipe.envs.observations``); ``episodic_life`` (the training envs') ends an
    Atari episode at each lost life.

    ``num_envs > 1`` makes one env of batch size ``[num_envs]``: gymnasium's ``SyncVectorEnv``
    stepping the copies in this process as one call, wrapped by TorchRL's ``GymWrapper`` (which
    resets finished copies itself, so the vector env's own autoreset is off). A collector then
    runs the policy once per ``num_envs`` steps: TorchRL's per-step cost (~1.5 ms here, for a
    CartPole step of ~25 us) is paid once for all copies. ``TorchRL``'s own ``GymEnv(num_envs=N)``
    steps the copies in N processes instead (``AsyncVectorEnv``), which on a 2-core machine
    costs more than it saves.
    """
    gym_id = resolve_env_id(env_id)
    own = user.is_user_env(env_id)
    label = env_id if own else gym_id  # what error messages call it
    if render_mode is not None:
        gym_kwargs["render_mode"] = render_mode
    if gym_kwargs:
        user.check_kwargs(gym_id, gym_kwargs, label, EnvError)
    if is_atari(gym_id):
        gym_kwargs.setdefault("frameskip", 1)  # AtariPreprocessing skips frames itself

    def readable(gym_env: gymnasium.Env) -> gymnasium.Env:
        return observed(gym_env, label, observation_keys=observation_keys, frame_stack=frame_stack,
                        rescale_observations=rescale_observations, episodic_life=episodic_life)

    with _extra_named(gym_id, env_id):
        if num_envs > 1:
            vector = gymnasium.vector.SyncVectorEnv(
                [lambda: readable(gymnasium.make(gym_id, **gym_kwargs))] * num_envs,
                autoreset_mode=gymnasium.vector.AutoresetMode.DISABLED,
            )
            base = GymWrapper(vector, device=device, categorical_action_encoding=True)
        else:
            if own:  # TorchRL's GymEnv would hand its own keywords (frameskip) to the user's constructor;
                # wrapped before TorchRL reads its spaces, which it cannot for some (a uint16 Box)
                base = GymWrapper(readable(gymnasium.make(gym_id, **gym_kwargs)), device=device,
                                  categorical_action_encoding=True)
            else:
                base = GymEnv(gym_id, device=device, categorical_action_encoding=True, **gym_kwargs)
                flat = readable(base._env)
                if flat is not base._env:
                    base = GymWrapper(flat, device=device, categorical_action_encoding=True)
    transforms = [StepCounter(), RewardSum(), InitTracker()]
    if _has_float64(base):
        # Only where there is something to convert: with nothing to convert (CartPole, Pendulum,
        # Minitaur) DoubleToFloat still costs ~0.1 ms per step here, ~5% of a DQN tutorial iteration.
        transforms.append(DoubleToFloat())
    env = TransformedEnv(base, Compose(*transforms))
    if seed is not None:
        env.set_seed(seed)
    return env


def observed(gym_env: gymnasium.Env, label: str, *, observation_keys: list[str] | None = None, frame_stack: int = 1,
             rescale_observations: bool = False, episodic_life: bool = False) -> gymnasium.Env:
    """A gymnasium env (made with ``frameskip=1`` for Atari) with the wrappers ``make_env`` puts under TorchRL:
    its observation as the networks read it. ``label`` names the env in errors."""
    spec = getattr(gym_env, "spec", None)
    if spec is not None and is_atari(spec.id):
        gym_env = atari_preprocessed(gym_env, episodic_life=episodic_life)
    gym_env = _flat_observations(gym_env, label, observation_keys, frame_stack)
    return _rescaled(gym_env, label, rescale_observations)


def _has_float64(env: EnvBase) -> bool:
    """Whether any observation, reward, state, action or done entry of ``env`` is float64."""
    specs = (env.full_observation_spec, env.full_reward_spec, env.full_state_spec, env.full_action_spec,
             env.full_done_spec)
    return any(leaf.dtype == torch.float64 for spec in specs for _, leaf in spec.items(True, True))


class _extra_named:
    """gymnasium's "X is not installed" (with its own install advice) as one line naming the pip extra."""

    def __init__(self, gym_id: str, env_id: str):
        self.gym_id, self.env_id = gym_id, env_id

    def __enter__(self):
        return self

    def __exit__(self, kind, exc, tb):
        if kind is None or not issubclass(kind, (DependencyNotInstalled, ImportError)):
            return False
        entry = self.env_id if user.is_user_env(self.env_id) else gymnasium.spec(self.gym_id).entry_point
        entry = entry if isinstance(entry, str) else getattr(entry, "__module__", "")
        extra = next((e for prefix, e in _EXTRAS.items() if entry.startswith(prefix)), None)
        what = f"the {extra} extra" if extra else f"a package that {entry.split(':')[0]} imports"
        missing = str(exc).split(" is not installed")[0].split(".")[0] if " is not installed" in str(exc) else (
            getattr(exc, "name", None) or "a dependency")
        install = f' (pip install "{extra}")' if extra else ""
        raise EnvError(f"env {self.env_id!r} needs {what}, which is not installed ({missing} is missing); "
                       f"expected it installed{install} or another env id") from exc


def _flat_observations(env: gymnasium.Env, gym_id: str, observation_keys: list[str] | None = None,
                       frame_stack: int = 1) -> gymnasium.Env:
    """``env`` as the networks read it: one ``observation`` (a float vector, or a uint8 image stack), and Box
    or Discrete actions.

    A flat float Box comes back as it is. A Dict becomes one float vector of its entries (``DictObservation``:
    images among them joined channels first, read by an encoder; a Dict holding only an image is that image).
    An image (``is_image``: a Box of 2 or 3 dimensions whose values fit in a byte) stays uint8, channels first,
    ``frame_stack`` frames deep (``ImageObservation``). Discrete,
    MultiDiscrete, MultiBinary and Tuples of them (FrozenLake's Discrete(16), Blackjack's Tuple) and other
    Boxes become one flat float32 vector through gymnasium's ``FlattenObservation`` (one-hot for the
    discrete parts).
    """
    action, obs = env.action_space, env.observation_space
    if not isinstance(action, (spaces.Box, spaces.Discrete)) or isinstance(action, spaces.Box) and len(action.shape) != 1:
        raise EnvError(f"env {gym_id!r} has a {action} action space; expected a Discrete one or a one-dimensional Box")
    if observation_keys and not isinstance(obs, spaces.Dict):
        raise EnvError(f"observation_keys={list(observation_keys)}: env {gym_id!r} has a {obs} observation space, "
                       "not a Dict; expected observation_keys unset")
    if isinstance(obs, spaces.Dict):
        if len(obs.spaces) == 1 and is_image(next(iter(obs.spaces.values()))) and not observation_keys:
            (key, image), = obs.spaces.items()
            return ImageObservation(gymnasium.wrappers.TransformObservation(env, lambda o: o[key], image), frame_stack)
        if frame_stack > 1:
            raise EnvError(f"frame_stack={frame_stack}: env {gym_id!r} observes a Dict of {len(obs.spaces)} entries, whose "
                           "frames rlpipe does not stack; expected frame_stack=1 (stacking is for an image observation "
                           "alone)")
        return DictObservation(env, dict_keys(obs, observation_keys, gym_id, EnvError))
    if is_image(obs):
        return ImageObservation(env, frame_stack)
    if frame_stack > 1:
        raise EnvError(f"frame_stack={frame_stack}: env {gym_id!r} observes {obs}, not an image; expected "
                       "frame_stack=1 (stacking is for image observations)")
    if isinstance(obs, spaces.Box) and len(obs.shape) == 1 and np.issubdtype(obs.dtype, np.floating):
        return env
    if not _flattenable(obs):
        raise EnvError(f"env {gym_id!r} has a {obs} observation space; expected a Box, Dict, or Discrete, "
                       "MultiDiscrete, MultiBinary or Tuple spaces of them (flattened into one vector)")
    return DtypeObservation(FlattenObservation(env), np.float32)


RESCALE_MAX_WIDTH = 1e6
"""observation bounds wider than this are unbounded for ``rescale_observations``"""


def rescaling_bounds(space: spaces.Space, gym_id: str) -> tuple[np.ndarray, np.ndarray]:
    """The (low, high) an observation space is rescaled from, as float32 arrays: a flat Box's own
    bounds, which must be finite (``EnvError`` otherwise, naming the env and what is expected)."""
    if not isinstance(space, spaces.Box) or len(space.shape) != 1:
        raise EnvError(f"rescale_observations=true: env {gym_id!r} has a {space} observation space; expected a flat "
                       "Box with finite bounds, or rescale_observations=false")
    low, high = space.low.astype(np.float32), space.high.astype(np.float32)
    # CartPole bounds its velocities by float32's largest value: finite, but a map from that width to [-1, 1]
    # would squash them to ~1e-39, so a width past RESCALE_MAX_WIDTH counts as unbounded
    unbounded = ~np.isfinite(low) | ~np.isfinite(high) | (high.astype(np.float64) - low > RESCALE_MAX_WIDTH)
    if unbounded.any():
        raise EnvError(f"rescale_observations=true: env {gym_id!r} has observation bounds that are not finite "
                       f"({int(unbounded.sum())} of {low.size} entries infinite or wider than {RESCALE_MAX_WIDTH:g}); "
                       "expected finite low and high, or rescale_observations=false")
    return low, high


def observation_rescaling(env: EnvBase) -> tuple[np.ndarray, np.ndarray] | None:
    """The (low, high) ``make_env(..., rescale_observations=True)`` maps ``env``'s observations from, or None
    where it does not rescale them."""
    gym_env = gym_env_under(env)  # None for a user's own env (a SerialEnv's __getattr__ would ask each copy)
    if isinstance(gym_env, RescaleObservation):
        return rescaling_bounds(gym_env.env.observation_space, "")
    return None


def _rescaled(env: gymnasium.Env, gym_id: str, rescale: bool) -> gymnasium.Env:
    if not rescale:
        return env
    rescaling_bounds(env.observation_space, gym_id)
    return RescaleObservation(env, np.float32(-1.0), np.float32(1.0))


def _flattenable(space: spaces.Space) -> bool:
    if isinstance(space, spaces.Tuple):
        return all(_flattenable(s) for s in space.spaces)
    return isinstance(space, _FLATTENED)


def gym_env_under(env: EnvBase) -> gymnasium.Env | None:
    """The gymnasium env a TorchRL env made by ``make_env`` steps (the first copy of a vector), else None."""
    base = env.base_env if isinstance(env, TransformedEnv) else env
    if not isinstance(base, GymWrapper):
        return None
    gym_env = base._env
    if isinstance(gym_env, gymnasium.vector.SyncVectorEnv):
        gym_env = gym_env.envs[0]
    return gym_env if isinstance(gym_env, gymnasium.Env) else None


def image_scale(env: EnvBase) -> float | None:
    """What one unit of ``env``'s image observation is as a fraction of full brightness (1/255 for uint8
    pictures, 1 for 0/1 channels), or None where ``env`` does not observe an image (``ImageObservation``)."""
    image = wrapper_of(gym_env_under(env), ImageObservation)
    return image.scale if image is not None else None


def _action_spec(env_or_spec: EnvBase | TensorSpec) -> TensorSpec:
    return env_or_spec.action_spec_unbatched if isinstance(env_or_spec, EnvBase) else env_or_spec


def is_discrete(env_or_spec: EnvBase | TensorSpec) -> bool:
    """Whether an env's action space (or an action spec) is a finite set of choices (what DQN needs)."""
    return isinstance(_action_spec(env_or_spec), (Categorical, OneHot))


def describe_action_space(env_or_spec: EnvBase | TensorSpec) -> str:
    """A short phrase for error messages, e.g. 'continuous Box of shape (1,)'."""
    spec = _action_spec(env_or_spec)
    if is_discrete(spec):
        return f"discrete action space of {spec.space.n} actions"
    return f"continuous Box of shape {tuple(spec.shape)}"


def env_id_of(env: EnvBase) -> str | None:
    """The gymnasium id of the world an env steps, where it wraps one made from an id; else None."""
    while isinstance(env, TransformedEnv):
        env = env.base_env
    if isinstance(env, BatchedEnvBase):
        # SerialEnv/ParallelEnv describe their sub-env only as its repr, "GymEnv(env=ID, ...)"
        found = re.search(r"GymEnv\(env=([^,)\s]+)", env.meta_data.env_str)
        return found.group(1) if found else None
    name = getattr(env, "env_name", None) if isinstance(env, GymEnv) else None
    if name is None and isinstance(env, GymWrapper):  # a gymnasium env wrapped here, or made without an id
        name = getattr(getattr(env._env, "spec", None), "id", None)
    return name if isinstance(name, str) else None


def env_label(env: EnvBase) -> str:
    """The name of the world an env steps: its gymnasium id if it wraps one, else the class name of the
    gymnasium env it wraps (a user's own, made without an id), else its own class name."""
    found = env_id_of(env)
    if found is not None:
        return found
    while isinstance(env, TransformedEnv):
        env = env.base_env
    inner = getattr(env, "_env", None) if isinstance(env, GymWrapper) else None
    unwrapped = getattr(inner, "unwrapped", inner)
    return type(unwrapped).__name__ if unwrapped is not None else type(env).__name__


def with_episode_return(env: EnvBase) -> EnvBase:
    """``env`` with TorchRL's ``RewardSum`` appended if it has none: the loop reads each finished
    training episode's return from ``("next", "episode_reward")``."""
    if "episode_reward" in env.observation_spec.keys():
        return env
    return TransformedEnv(env, RewardSum())
