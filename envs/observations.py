"""What an env's observation becomes before TorchRL sees it: one entry, ``observation``, that the networks read.

* **Vectors, and a Dict of them** (gymnasium-robotics' goal envs, any Dict env): every entry the user reads
  (``observation_keys``, default all) is flattened in the Dict's own key order and concatenated into one
  float32 vector (``DictObservation``). Where each entry lies in that vector is its ``layout``: hindsight
  relabelling writes a goal into its slice, and the exported policy takes the entries by name and joins
  them the same way. Concatenating at the env keeps one tensor per transition, so the collectors, the
  replay buffer and the lean losses serve Dict envs unchanged. An image among the entries (a camera beside
  a robot's joint angles, MiniGrid's view beside its direction) is joined too, channels first, in its own
  units; its ``images`` entry (shape and scale) tells the networks' ``DictEncoder`` to read that span through
  a convolutional encoder. Joined so, it is stored as float32 (4 bytes a pixel) and not frame-stacked.
* **Images** (a bool Box, or an integer one bounded in [0, 255], of HxW, HxWxC or CxHxW): kept as uint8,
  channels first, the last ``frame_stack`` frames stacked on the channel axis (``ImageObservation``):
  ``uint8 [frame_stack * C, H, W]``. A convolutional encoder (``rlpipe.modules.encoders``) reads it.
* **Atari** (``ALE/...`` ids): gymnasium's ``AtariPreprocessing`` as CleanRL's and SB3's Atari wrappers set
  it up (no-op reset up to 30, frame skip 4 with max-pooling, 84x84 grey), before the frames are stacked;
  every life starts with FIRE pressed where the game has it (``FireOnLifeStart``), and in training a lost
  life ends the episode while the game plays on at the next reset (``EpisodicLife``; evaluations play whole
  games). Rewards stay the game's score; clipping them is the loss's business (``clip_rewards``).

An entry that cannot be read (a Text space, a nested Dict) is one ``EnvError`` naming the entry and what is
expected.
"""

from __future__ import annotations

import contextlib
import io
from collections import deque
from collections.abc import Sequence
from typing import NamedTuple, TypeVar

import gymnasium
import numpy as np
from gymnasium import spaces

__all__ = [
    "DictObservation", "EpisodicLife", "FireOnLifeStart", "ImageObservation", "GOAL_KEYS", "atari_preprocessed",
    "ImageEntry", "discrete_entries", "goal_env", "image_frame", "image_space", "is_atari", "is_image",
    "observation_images", "observation_layout", "register_optional_families", "wrapper_of",
]

GOAL_KEYS = ("achieved_goal", "desired_goal")
"""the entries of gymnasium-robotics' goal envs that hindsight relabelling reads and writes"""

ROBOTICS_PREFIXES = ("Fetch", "Hand", "PointMaze", "AntMaze", "Adroit", "FrankaKitchen")
"""the env names gymnasium-robotics registers (rlpipe[robotics]): imported only for an id that may be one"""

W = TypeVar("W", bound=gymnasium.Wrapper)

_VECTOR_SPACES = (spaces.Box, spaces.Discrete, spaces.MultiDiscrete, spaces.MultiBinary)


def is_image(space: spaces.Space) -> bool:
    """A Box of 2 or 3 dimensions whose values fit in a byte (bool, or integers bounded in [0, 255]): a picture,
    stored and exported as uint8. Any other Box of that shape (floats, a uint16 depth camera, signed integers) is a
    matrix, flattened into the vector the networks read, as SB3 reads every Box but a uint8 one."""
    if not isinstance(space, spaces.Box) or len(space.shape) not in (2, 3):
        return False
    if space.dtype == np.bool_:
        return True
    return bool(np.issubdtype(space.dtype, np.integer) and np.all(space.low >= 0) and np.all(space.high <= 255))


def image_space(space: spaces.Box) -> tuple[int, int, int]:
    """(C, H, W) of an image space: HxW is one channel; a last axis of 1, 3 or 4 (and a first that is not)
    holds the channels (gymnasium's and Atari's HxWxC), else the first does (CxHxW, as TorchRL's pixels)."""
    shape = space.shape
    if len(shape) == 2:
        return 1, shape[0], shape[1]
    if shape[-1] in (1, 3, 4) and shape[0] not in (1, 3, 4):
        return shape[2], shape[0], shape[1]
    if shape[-1] in (1, 3, 4) and shape[0] in (1, 3, 4) and shape[-1] < shape[0]:
        return shape[2], shape[0], shape[1]
    return shape[0], shape[1], shape[2]


def _channels_last(space: spaces.Box) -> bool:
    """Whether an image space holds its channels on the last axis (``image_space``'s reading)."""
    channels = image_space(space)[0]
    return len(space.shape) == 3 and space.shape[-1] == channels and space.shape[0] != channels


def _image_unit(space: spaces.Box) -> float:
    """One unit of an image space as a fraction of full brightness: 1/255 for uint8 pictures, 1 for 0/1 channels."""
    high = float(np.max(space.high)) if space.dtype != np.bool_ else 1.0
    return 1.0 / max(high, 1.0)


def _channels_first(image, channels_last: bool) -> np.ndarray:
    """One image as ``[C, H, W]``: HxW gets one channel, HxWxC has its channels moved first."""
    frame = np.asarray(image)
    if frame.ndim == 2:
        return frame[None]
    return np.moveaxis(frame, -1, 0) if channels_last else frame


class ImageObservation(gymnasium.ObservationWrapper):
    """An image observation as the encoders read it: ``uint8 [frames * C, H, W]``, the newest frame last.

    Channels go first (the convolutions' layout); bool images (MinAtar's) become 0/1. At a reset the stack
    is filled with the first frame, as gymnasium's ``FrameStackObservation(padding_type="reset")`` does.
    ``scale`` is what one unit of the image is as a fraction of full brightness (1/255 for uint8 pictures,
    1 for 0/1 channels): the encoder multiplies by it.
    """

    def __init__(self, env: gymnasium.Env, frames: int = 1):
        super().__init__(env)
        space = env.observation_space
        channels, height, width = image_space(space)
        self.channels_last = _channels_last(space)
        self.frames = frames
        self.scale = _image_unit(space)
        self.observation_space = spaces.Box(0, 255 if space.dtype != np.bool_ else 1,
                                            (frames * channels, height, width), np.uint8)
        self._stack: deque[np.ndarray] = deque(maxlen=frames)

    def _frame(self, observation) -> np.ndarray:
        return _channels_first(observation, self.channels_last).astype(np.uint8, copy=False)

    def reset(self, **kwargs):
        observation, info = self.env.reset(**kwargs)
        frame = self._frame(observation)
        self._stack.clear()
        self._stack.extend([frame] * self.frames)
        return self._stacked(), info

    def observation(self, observation):
        self._stack.append(self._frame(observation))
        return self._stacked()

    def _stacked(self) -> np.ndarray:
        return np.ascontiguousarray(np.concatenate(self._stack, axis=0))


class ImageEntry(NamedTuple):
    """An image among a Dict observation's entries, as joined into the observation vector."""

    shape: tuple[int, int, int]
    """(C, H, W): what its span of the vector is reshaped to"""
    scale: float
    """one unit as a fraction of full brightness (``ImageObservation.scale``)"""
    env_shape: tuple[int, ...]
    """the shape the env gives it (HxW, HxWxC or CxHxW)"""
    channels_last: bool
    """whether the env gives its channels last (they are moved first in the vector)"""


class DictObservation(gymnasium.ObservationWrapper):
    """A Dict observation's entries ``keys``, each flattened, concatenated into one float32 vector.

    ``layout`` maps each entry to its ``(start, stop)`` in the vector; ``entry_spaces`` keeps each entry's
    own space (the exported policy's named inputs). An image entry (``is_image``) is put channels first and
    flattened, in its own units; ``images`` maps each to its ``ImageEntry``: the shape the networks'
    ``DictEncoder`` reshapes its span to, and the scale it reads it at.
    """

    def __init__(self, env: gymnasium.Env, keys: Sequence[str]):
        super().__init__(env)
        space: spaces.Dict = env.observation_space
        self.keys = list(keys)
        self.entry_spaces = {key: space[key] for key in self.keys}
        self.images = {key: ImageEntry(image_space(sub), _image_unit(sub), tuple(sub.shape), _channels_last(sub))
                       for key, sub in self.entry_spaces.items() if is_image(sub)}
        self.layout: dict[str, tuple[int, int]] = {}
        start = 0
        for key in self.keys:
            size = int(spaces.flatdim(space[key]))
            self.layout[key] = (start, start + size)
            start += size
        low = np.concatenate([_flat_bound(space[k], "low") for k in self.keys])
        high = np.concatenate([_flat_bound(space[k], "high") for k in self.keys])
        self.observation_space = spaces.Box(low, high, (start,), np.float32)

    def observation(self, observation) -> np.ndarray:
        return np.concatenate([self._flat(k, observation[k]) for k in self.keys])

    def _flat(self, key: str, value) -> np.ndarray:
        if key in self.images:
            return _channels_first(value, self.images[key].channels_last).astype(np.float32).reshape(-1)
        return spaces.flatten(self.entry_spaces[key], value).astype(np.float32, copy=False)


def _flat_bound(space: spaces.Space, which: str) -> np.ndarray:
    if is_image(space):
        return _channels_first(getattr(space, which), _channels_last(space)).astype(np.float32).reshape(-1)
    if isinstance(space, spaces.Box):
        return getattr(space, which).astype(np.float32).reshape(-1)
    return np.full(spaces.flatdim(space), 0.0 if which == "low" else 1.0, np.float32)  # one-hot parts


def dict_keys(space: spaces.Dict, wanted: Sequence[str] | None, label: str, error: type[Exception]) -> list[str]:
    """The entries of a Dict space the networks read: ``wanted`` (each must exist), else all; each must be a
    vector (a Box, or a discrete space read one-hot) or an image. One ``error`` naming the first entry that is not."""
    names = list(space.spaces)
    if wanted:
        missing = [k for k in wanted if k not in space.spaces]
        if missing:
            raise error(f"observation_keys names {', '.join(map(repr, missing))}, which env {label!r} does not "
                        f"observe; expected some of {', '.join(map(repr, names))}")
        names = list(wanted)
    for key in names:
        sub = space[key]
        if not isinstance(sub, _VECTOR_SPACES):
            raise error(f"env {label!r} observes {key!r} as {sub}, which the networks cannot read; expected a Box or "
                        "a Discrete, MultiDiscrete or MultiBinary space, or observation_keys leaving it out")
    return names


def wrapper_of(gym_env: gymnasium.Env, kind: type[W]) -> W | None:
    """The outermost wrapper of ``kind`` around ``gym_env``'s env, or None."""
    env = gym_env
    while isinstance(env, gymnasium.Wrapper):
        if isinstance(env, kind):
            return env
        env = env.env
    return None


def observation_layout(gym_env: gymnasium.Env) -> dict[str, tuple[int, int]] | None:
    """Where each Dict entry lies in the observation vector (``DictObservation.layout``), or None."""
    joined = wrapper_of(gym_env, DictObservation)
    return dict(joined.layout) if joined is not None else None


def observation_images(gym_env: gymnasium.Env) -> dict[str, ImageEntry]:
    """The images among a Dict env's entries (``DictObservation.images``); empty where there are none."""
    joined = wrapper_of(gym_env, DictObservation)
    return dict(joined.images) if joined is not None else {}


def discrete_entries(gym_env: gymnasium.Env) -> dict[str, tuple[tuple[int, ...], list[int], list[int]]]:
    """The discrete entries (Discrete, MultiDiscrete) among a Dict env's, read one-hot: each one's shape as the env
    gives it (() for a Discrete), and the sizes and starts of its values, flattened; empty where there are none."""
    joined = wrapper_of(gym_env, DictObservation)
    found = {}
    for key, space in (joined.entry_spaces if joined is not None else {}).items():
        if isinstance(space, spaces.Discrete):
            found[key] = ((), [int(space.n)], [int(space.start)])
        elif isinstance(space, spaces.MultiDiscrete):
            found[key] = (tuple(space.shape), np.asarray(space.nvec).reshape(-1).tolist(),
                          np.asarray(space.start).reshape(-1).tolist())
    return found


def image_frame(gym_env: gymnasium.Env) -> tuple[tuple[int, ...], bool] | None:
    """An image observation of one frame (``ImageObservation`` with ``frames=1``): the shape the env gives it
    (HxW, HxWxC or CxHxW) and whether its channels come last; else None (no image, or frames stacked)."""
    image = wrapper_of(gym_env, ImageObservation)
    if image is None or image.frames != 1:
        return None
    return tuple(image.env.observation_space.shape), image.channels_last


def goal_env(gym_env: gymnasium.Env) -> bool:
    """Whether an env follows gymnasium-robotics' goal-env convention as read here: both goal entries
    observed and a ``compute_reward(achieved_goal, desired_goal, info)``."""
    layout = observation_layout(gym_env)
    return (layout is not None and all(k in layout for k in GOAL_KEYS)
            and callable(getattr(gym_env.unwrapped, "compute_reward", None)))


def is_atari(gym_id: str) -> bool:
    return gym_id.startswith("ALE/")


def atari_preprocessed(env: gymnasium.Env, *, episodic_life: bool = False) -> gymnasium.Env:
    """Atari as the Nature DQN paper, CleanRL's ``dqn_atari.py`` and SB3's ``AtariWrapper`` play it: no-op
    resets (up to 30), 4 frames a step with the last two max-pooled, 84x84 grey, FIRE at the start of each
    life where the game has it; with ``episodic_life`` (training), a lost life ends the episode. The env
    must be made with ``frameskip=1`` (the preprocessing skips frames itself)."""
    env = gymnasium.wrappers.AtariPreprocessing(env, noop_max=30, frame_skip=4, screen_size=84,
                                                terminal_on_life_loss=False, grayscale_obs=True)
    if episodic_life:
        env = EpisodicLife(env)
    if "FIRE" in env.unwrapped.get_action_meanings():
        env = FireOnLifeStart(env)
    return env


def _lives(env: gymnasium.Env) -> int:
    return int(env.unwrapped.ale.lives())


class EpisodicLife(gymnasium.Wrapper):
    """A lost life ends the episode (``terminated``) for the learner, which then bootstraps no value past it; the
    next ``reset`` carries on with the same game (one no-op step) unless the game itself was over. SB3's
    ``EpisodicLifeEnv`` and CleanRL's ``dqn_atari.py`` train so; the Nature DQN paper too. An episode's return is
    then one life's score: evaluations play without this wrapper and report whole games."""

    def __init__(self, env: gymnasium.Env):
        super().__init__(env)
        self.lives = 0
        self.game_over = True

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.game_over = terminated or truncated
        lives = _lives(self.env)
        if 0 < lives < self.lives:
            terminated = True
        self.lives = lives
        return obs, reward, terminated, truncated, info

    def reset(self, **kwargs):
        if self.game_over:
            obs, info = self.env.reset(**kwargs)
        else:
            obs, _, terminated, truncated, info = self.env.step(0)  # NOOP: the game goes on with its next life
            if terminated or truncated:
                obs, info = self.env.reset(**kwargs)
        self.lives = _lives(self.env)
        self.game_over = False
        return obs, info


class FireOnLifeStart(gymnasium.Wrapper):
    """FIRE after each reset and each lost life, for games that wait for it to serve (Breakout, ...). SB3's and
    CleanRL's ``FireResetEnv`` press it at reset, which with ``EpisodicLife`` is the start of every life; here an
    evaluation's whole game gets the same, so a policy never learns to wait on a ball that is not served (a greedy
    Breakout agent would otherwise stand still until the game's frame limit)."""

    def __init__(self, env: gymnasium.Env):
        super().__init__(env)
        self.fire = env.unwrapped.get_action_meanings().index("FIRE")
        self.lives = 0

    def reset(self, **kwargs):
        self.env.reset(**kwargs)
        obs, _, terminated, truncated, info = self.env.step(self.fire)
        if terminated or truncated:
            obs, info = self.env.reset(**kwargs)
        self.lives = _lives(self.env)
        return obs, info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        lives = _lives(self.env)
        if 0 < lives < self.lives and not (terminated or truncated):
            obs, more, terminated, truncated, info = self.env.step(self.fire)
            reward += more
            lives = _lives(self.env)
        self.lives = lives
        return obs, reward, terminated, truncated, info


def register_optional_families(env_id: str) -> None:
    """Register the env families that need their package imported first (ALE's Atari, MinAtar,
    gymnasium-robotics' Fetch and mazes) when ``env_id`` may be one of them and the package is installed."""
    if env_id in gymnasium.registry:
        return
    if env_id.startswith("ALE/"):
        try:
            import ale_py
        except ImportError:
            return
        gymnasium.register_envs(ale_py)
    elif env_id.startswith("MinAtar/"):
        try:
            import minatar.gym
        except ImportError:
            return
        minatar.gym.register_envs()
    elif env_id.startswith(ROBOTICS_PREFIXES):
        try:
            # its import prints a notice about Adroit's rewards
            with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
                import gymnasium_robotics
        except ImportError:
            return
        from rlpipe.envs import robotics_compat

        robotics_compat.apply()
        gymnasium.register_envs(gymnasium_robotics)
