"""A gymnasium env's state in the middle of an episode, as data: ``capture`` it, ``restore`` it into
another instance of the same env (in another process too), ``capturable`` says where that is exact.

The state is a flat ``dict[str, torch.Tensor]`` (no pickles: checkpoints load with ``weights_only``).
What it holds, by family:

* every layer of the wrapper chain and the base env (unless it replays): its plain data attributes (numbers, booleans,
  ``None``, numeric NumPy arrays: CartPole's ``state``, Pendulum's ``last_u``, ``TimeLimit``'s
  ``_elapsed_steps``, ...) and the base env's ``np_random`` (PCG64, gymnasium's generator);
* MuJoCo envs: ``mj_getState(mjSTATE_INTEGRATION)`` (time, qpos, qvel, act, warm start, controls,
  applied forces, mocap, ...); derived quantities are recomputed with ``mj_forward`` on restore;
* envs that replay their episode (``replay_state``/``replay``: our pybullet Minitaur): pybullet's
  ``saveState`` lives in one process's memory only, so the env keeps the generator's state at its
  last reset and the actions since, and ``restore`` plays the episode again (pybullet is
  deterministic given the same world and actions).

Box2D envs (LunarLander, BipedalWalker) hold a Box2D world that cannot be read as data: not capturable.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

__all__ = ["NotCapturable", "capture", "capturable", "restore", "why_not_capturable"]

_FAMILIES = ("gymnasium.envs.classic_control.", "gymnasium.envs.mujoco.")
_NONE, _BOOL, _INT, _FLOAT, _ARRAY, _SCALAR = "none", "bool", "int", "float", "array", "scalar"


class NotCapturable(ValueError):
    """The env's state cannot be captured (a user's own env, Box2D, a soft-reset Minitaur)."""


def _layers(gym_env) -> list:
    """The wrapper chain, outermost first, ending with the base env."""
    layers, env = [], gym_env
    while True:
        layers.append(env)
        inner = getattr(env, "env", None)
        if inner is None or inner is env or not hasattr(env, "unwrapped"):
            return layers
        env = inner


def why_not_capturable(gym_env) -> str | None:
    """Why ``gym_env``'s state cannot be captured exactly, or None when it can."""
    base = getattr(gym_env, "unwrapped", gym_env)
    if hasattr(base, "replay_state"):
        return base.why_not_replayable()
    module = type(base).__module__
    if not module.startswith(_FAMILIES):
        return f"{type(base).__name__} ({module}) is not a classic-control, MuJoCo or Minitaur env"
    generator = getattr(base, "_np_random", None)
    if generator is not None and type(generator.bit_generator).__name__ != "PCG64":
        return f"its np_random is a {type(generator.bit_generator).__name__}, expected PCG64"
    return None


def capturable(gym_env) -> bool:
    return why_not_capturable(gym_env) is None


def _bigint(value: int) -> torch.Tensor:
    """A non-negative int of up to 128 bits as 4 int64 limbs of 32 bits (a tensor holds 64 at most)."""
    return torch.tensor([(value >> (32 * i)) & 0xFFFFFFFF for i in range(4)], dtype=torch.int64)


def _from_bigint(limbs: torch.Tensor) -> int:
    return sum(int(v) << (32 * i) for i, v in enumerate(limbs.tolist()))


def _generator_state(generator: np.random.Generator) -> dict[str, torch.Tensor]:
    s = generator.bit_generator.state
    return {"state": _bigint(s["state"]["state"]), "inc": _bigint(s["state"]["inc"]),
            "has_uint32": torch.tensor(int(s["has_uint32"])), "uinteger": torch.tensor(int(s["uinteger"]))}


def _set_generator_state(generator: np.random.Generator, state: dict[str, torch.Tensor]) -> None:
    generator.bit_generator.state = {
        "bit_generator": "PCG64",
        "state": {"state": _from_bigint(state["state"]), "inc": _from_bigint(state["inc"])},
        "has_uint32": int(state["has_uint32"]), "uinteger": int(state["uinteger"]),
    }


def generator_state(generator: np.random.Generator) -> dict[str, torch.Tensor]:
    """A PCG64 generator's state as tensors (``set_generator_state`` puts it back)."""
    return _generator_state(generator)


def set_generator_state(generator: np.random.Generator, state: dict[str, torch.Tensor]) -> None:
    _set_generator_state(generator, state)


def _encode(value) -> tuple[str, torch.Tensor] | None:
    # bool before int: a bool is an int in Python
    if value is None:
        return _NONE, torch.zeros(0)
    if isinstance(value, (bool, np.bool_)):
        return _BOOL, torch.tensor(bool(value))
    if isinstance(value, int):
        return (_INT, torch.tensor(value)) if -2**63 <= value < 2**63 else None
    if isinstance(value, float):
        return _FLOAT, torch.tensor(value, dtype=torch.float64)
    if isinstance(value, np.ndarray) and value.dtype.kind in "biuf" and value.dtype != np.uint64:
        return _ARRAY, torch.from_numpy(value.copy())
    if isinstance(value, np.generic) and value.dtype.kind in "biuf" and value.dtype != np.uint64:
        return _SCALAR, torch.from_numpy(np.asarray(value).copy())
    return None


def _decode(kind: str, tensor: torch.Tensor):
    if kind == _NONE:
        return None
    if kind == _BOOL:
        return bool(tensor)
    if kind == _INT:
        return int(tensor)
    if kind == _FLOAT:
        return float(tensor)
    array = tensor.numpy().copy()
    return array if kind == _ARRAY else array[()]


def capture(gym_env) -> dict[str, torch.Tensor]:
    """``gym_env``'s state now (see the module's docstring); ``NotCapturable`` if it cannot be captured."""
    why = why_not_capturable(gym_env)
    if why is not None:
        raise NotCapturable(why)
    base = gym_env.unwrapped
    state: dict[str, torch.Tensor] = {}
    replays = hasattr(base, "replay_state")
    for i, layer in enumerate(_layers(gym_env)):
        if replays and layer is base:
            continue  # its replay rebuilds it; its numbers include pybullet's client id, this process's own
        for name, value in vars(layer).items():
            if name in ("_np_random", "np_random"):
                continue
            encoded = _encode(value)
            if encoded is not None:
                state[f"attr/{i}/{encoded[0]}/{name}"] = encoded[1]
    generator = getattr(base, "_np_random", None)
    if generator is not None:
        state.update({f"np_random/{k}": v for k, v in _generator_state(generator).items()})
    if hasattr(base, "replay_state"):
        state.update({f"replay/{k}": v for k, v in base.replay_state().items()})
    data = getattr(base, "data", None)
    if type(base).__module__.startswith("gymnasium.envs.mujoco.") and data is not None:
        import mujoco

        spec = mujoco.mjtState.mjSTATE_INTEGRATION
        buffer = np.empty(mujoco.mj_stateSize(base.model, spec), dtype=np.float64)
        mujoco.mj_getState(base.model, data, buffer, spec)
        state["mujoco/integration"] = torch.from_numpy(buffer)
    return state


def restore(gym_env, state: dict[str, torch.Tensor]) -> None:
    """Put ``capture``'s ``state`` into ``gym_env`` (an instance of the same env, reset at least once)."""
    why = why_not_capturable(gym_env)
    if why is not None:
        raise NotCapturable(why)
    base = gym_env.unwrapped
    if hasattr(base, "replay_state"):
        # the episode is played again first; the attributes below then land on its end state
        base.replay({k[len("replay/"):]: v for k, v in state.items() if k.startswith("replay/")})
    layers = _layers(gym_env)
    for key, tensor in state.items():
        if key.startswith("attr/"):
            _, i, kind, name = key.split("/", 3)
            setattr(layers[int(i)], name, _decode(kind, tensor))
    generator = getattr(base, "_np_random", None)
    if any(k.startswith("np_random/") for k in state):
        if generator is None:
            base._np_random = generator = np.random.Generator(np.random.PCG64())
        _set_generator_state(generator, {k[len("np_random/"):]: v for k, v in state.items()
                                         if k.startswith("np_random/")})
    if "mujoco/integration" in state:
        import mujoco

        spec = mujoco.mjtState.mjSTATE_INTEGRATION
        buffer = state["mujoco/integration"].numpy()
        mujoco.mj_setState(base.model, base.data, buffer, spec)
        mujoco.mj_forward(base.model, base.data)  # contacts, sensors, cfrc_ext: what observations read
        mujoco.mj_setState(base.model, base.data, buffer, spec)  # the warm start as it was, not mj_forward's


def describe(state: dict[str, Any]) -> str:
    """A short note of what a captured state holds (for messages)."""
    return ", ".join(sorted({k.split("/", 1)[0] for k in state}))
