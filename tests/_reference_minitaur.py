"""Load pybullet's own ``MinitaurBulletEnv`` (the reference) for parity tests and benchmarks.

``pybullet_envs/bullet/minitaur_gym_env.py`` imports the dead ``gym`` package and
``pkg_resources`` (gone from recent setuptools).  This helper loads the reference
modules *unchanged* from pybullet's install folder, with

* a throw-away ``gym`` module built from gymnasium (``gym.Env``, ``gym.spaces``,
  ``gym.utils.seeding``) and, where missing, a tiny ``pkg_resources`` offering
  ``parse_version``, placed in ``sys.modules`` only while the modules import;
* a synthetic package (``_rlpipe_reference_minitaur``) whose ``__path__`` is pybullet's
  ``bullet`` folder, so the reference's relative imports (``from . import minitaur``)
  resolve without running ``pybullet_envs/__init__.py`` (which registers dozens of
  environments with ``gym``).

Nothing here is imported by the project itself: rlpipe never depends on ``gym``.
"""

from __future__ import annotations

import importlib
import os
import sys
import time
import types
import warnings

import gymnasium
import numpy as np

_PKG = "_rlpipe_reference_minitaur"
_cache: dict[str, types.ModuleType] = {}


def _find_bullet_dir() -> str:
    import importlib.util

    spec = importlib.util.find_spec("pybullet_envs")
    if spec is None or not spec.submodule_search_locations:
        raise ImportError("pybullet_envs is not installed (it ships with the pybullet wheel)")
    return os.path.join(list(spec.submodule_search_locations)[0], "bullet")


def _fake_gym() -> types.ModuleType:
    gym = types.ModuleType("gym")
    gym.__version__ = "0.26.2"
    gym.Env = gymnasium.Env
    gym.spaces = gymnasium.spaces
    utils = types.ModuleType("gym.utils")
    utils.seeding = gymnasium.utils.seeding
    gym.utils = utils
    return gym


def _fake_pkg_resources() -> types.ModuleType:
    mod = types.ModuleType("pkg_resources")

    def parse_version(v: str):
        out = []
        for part in str(v).split("."):
            digits = "".join(ch for ch in part if ch.isdigit())
            out.append(int(digits) if digits else 0)
        return tuple(out)

    mod.parse_version = parse_version
    return mod


def load_reference() -> types.ModuleType:
    """Return pybullet's ``minitaur_gym_env`` module, importable under gymnasium/numpy 2."""
    if "env" in _cache:
        return _cache["env"]
    shims = {"gym": _fake_gym(), "gym.spaces": gymnasium.spaces, "gym.utils": None,
             "gym.utils.seeding": gymnasium.utils.seeding}
    shims["gym.utils"] = shims["gym"].utils
    try:
        import pkg_resources  # noqa: F401
    except ImportError:
        shims["pkg_resources"] = _fake_pkg_resources()
    saved = {name: sys.modules.get(name) for name in shims}
    saved_path = list(sys.path)
    pkg = types.ModuleType(_PKG)
    pkg.__path__ = [_find_bullet_dir()]
    sys.modules[_PKG] = pkg
    try:
        sys.modules.update(shims)
        module = importlib.import_module(_PKG + ".minitaur_gym_env")
    finally:
        for name, old in saved.items():
            if old is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = old
        sys.path[:] = saved_path  # the reference inserts site-packages at sys.path[0]
    _cache["env"] = module
    return module


def make_reference_env(**kwargs):
    """Construct the reference ``MinitaurBulletEnv`` (its constructor prints ``urdf_root=``)."""
    module = load_reference()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # its float64 Box bounds make gymnasium warn
        return module.MinitaurBulletEnv(**kwargs)


def bench_reference_raw(steps: int, seed: int = 0, max_episode_steps: int = 1000) -> dict:
    """Steps/s of the reference with uniform random actions, resets (hard, its default) included.

    Same loop as ``rlpipe.scripts.bench.minitaur.bench_minitaur_raw``: the clock covers the
    first reset, every step and every reset after termination or ``max_episode_steps``
    (construction is not timed).
    """
    rng = np.random.default_rng(seed)
    np.random.seed(seed)  # the reference's randomiser draws from the global RNGs
    import random

    random.seed(seed)
    env = make_reference_env()  # its constructor already resets once (not timed)
    t0 = time.perf_counter()
    env.reset()
    resets, ep_len = 1, 0
    for _ in range(steps):
        _, _, done, _ = env.step(rng.uniform(-1.0, 1.0, 8))
        ep_len += 1
        if done or ep_len >= max_episode_steps:
            env.reset()
            resets += 1
            ep_len = 0
    elapsed = time.perf_counter() - t0
    env._pybullet_client.disconnect()
    return {"steps_per_s": steps / elapsed, "steps": steps, "resets": resets, "seconds": elapsed}
