"""Peer benchmark: CleanRL's single-file SAC, TD3 and DQN scripts, timed on this machine.

``rlpipe bench`` compares our pipelines with CleanRL, and a figure quoted from someone else's run says
little about this machine on this day. So this module runs CleanRL's own scripts (``cleanrl`` 1.2.0 on
PyPI, MIT-licensed, ``cleanrl/{sac_continuous_action,td3_continuous_action,dqn}.py``) as subprocesses
in the same command, with their own defaults except the env id, seed and the logging switches.

The scripts of that release come from the middle of CleanRL's move from gym to gymnasium, so they
cannot share rlpipe's environment (gymnasium 1.x) and not all run unchanged in one venv:

* ``dqn.py`` uses gymnasium's pre-1.0 vector API (``final_info`` / ``final_observation``) and requires
  stable-baselines3 >= 2.0 for its ``ReplayBuffer``: gymnasium 0.28.1 with stable-baselines3 2.0.0a1
  (the release its error message names, which pins that gymnasium). It runs unchanged.
* ``sac_continuous_action.py`` and ``td3_continuous_action.py`` use the old ``gym`` (the package pins
  ``gym==0.23.1``: 4-tuple ``step``, ``env.seed``, list-of-dicts vector infos). stable-baselines3 2.x
  only accepts gymnasium spaces, so these two run from patched copies (``PATCH`` below: the two spaces
  handed to ``ReplayBuffer`` are rebuilt as gymnasium boxes, nothing else changes).
* gym 0.23.1's MuJoCo envs need mujoco-py (MuJoCo 2.1 binaries, not installable here). So the venv
  also holds ``cleanrl-peer-envs`` (``ENV_SHIM``), a gym env plugin (entry point group ``gym.envs``,
  gym's own route for third-party envs) that registers gymnasium 0.28.1's MuJoCo v4 envs under the same
  ids in gym: ``--env-id HalfCheetah-v4``. gymnasium 0.28.1 has MuJoCo v4 only, so ``-v5`` is run as
  ``-v4``: for HalfCheetah, v5 changed no dynamics, reward or observation (it added constructor options
  and renamed an info key); both reset to the same observation for the same seed.

The venv lives under ``$RLPIPE_PEERS_DIR/cleanrl`` (default ``~/.cache/rlpipe/peers/cleanrl``), built on
first use with every version pinned (``TORCH_PINS``, ``BUILD_PINS``, ``PINS``, ``CLEANRL``); about 1.3 GB,
two to four minutes here.

Speed is taken from two runs of different lengths, ``learning_starts + n1`` and ``learning_starts + n2``
env steps: updates/s = (U2 - U1) / (t2 - t1) over the subprocesses' wall times, so start-up (imports,
the random-action warm-up, buffer allocation) cancels out. The longer run's own output gives a second
figure: its ``global_step=...`` lines are time-stamped as they arrive, and the env steps between the
first and last of them after ``learning_starts`` over the time between them is its in-run rate.
"""

from __future__ import annotations

import ast
import os
import re
import shlex
import subprocess
import tempfile
import threading
import time
from collections import deque
from collections.abc import Sequence
from pathlib import Path

from rlpipe.scripts.bench.peers import _venv

ALGOS = {"sac": "sac_continuous_action.py", "td3": "td3_continuous_action.py", "dqn": "dqn.py",
         "dqn_atari": "dqn_atari.py"}
CLEANRL = "cleanrl==1.2.0"  # installed with --no-deps: its metadata pins stable-baselines3==1.2.0, wandb, ...
# torch first, with its own dependencies: this exact spec takes the CPU build that lies on this disk.
TORCH_PINS: tuple[str, ...] = (
    "torch==2.13.0",
    "filelock==4.2.11",
    "fsspec==2026.9.0",
    "jinja2==3.1.6",
    "markupsafe==3.0.4",
    "mpmath==1.3.0",
    "networkx==3.6.1",
    "sympy==1.14.0",
    "typing-extensions==4.16.0",
)
# gym 0.23.1 is on PyPI as an sdist only; it is built with these, without build isolation.
BUILD_PINS: tuple[str, ...] = ("setuptools==84.2.1", "wheel==0.48.0")
# What the scripts import, and what that pulls in: the rest of a working install's ``pip freeze``.
PINS: tuple[str, ...] = (
    "gym==0.23.1",
    "gym-notices==0.1.0",
    # gym 0.23.1's classic_control imports pygame at import; cleanrl pins 2.1.0, which has no Python 3.11 wheel
    "pygame==2.1.3",
    "gymnasium==0.28.1",
    "jax-jumpy==1.0.0",
    "farama-notifications==0.0.6",
    "cloudpickle==3.1.2",
    "stable-baselines3==2.0.0a1",
    "pandas==3.1.1",
    "python-dateutil==4.0.0",
    "tzdata==2026.6",
    "matplotlib==3.11.2",
    "contourpy==1.3.3",
    "cycler==0.12.1",
    "fonttools==4.68.0",
    "kiwisolver==1.5.1",
    "pyparsing==3.3.3",
    "pillow==13.0.0",
    "packaging==26.3",
    "numpy==2.4.6",
    "tensorboard==2.21.0",
    "tensorboard-data-server==0.7.2",
    "absl-py==2.5.1",
    "grpcio==1.85.1",
    "markdown==3.11.3",
    "protobuf==7.36.2",
    "werkzeug==3.1.9",
    "mujoco==4.0.0",
    "mujoco-core==4.0.0",
    "mujoco-studio==4.0.0",
    "glfw==2.11.0",
    "pyopengl==3.1.10",
    "websockets==17.4",
    "imageio==2.38.1",
    # dqn_atari.py: gymnasium 0.28.1's Atari envs come through shimmy 0.2.1 over ale-py 0.8.1 (the versions its
    # install line names); cv2 for its ResizeObservation. ale-py 0.8.1 ships no ROMs: ``ALE_PY_ROM_DIR`` points it
    # at the ROM files of the ale-py rlpipe[atari] installs (``_atari_roms``), which ale-py checks by MD5.
    "ale-py==0.8.1",
    "shimmy==0.2.1",
    "importlib-resources==7.1.0",
    "opencv-python-headless==5.1.0.95",
)
# The distributions whose versions a benchmark report names.
REPORTED: tuple[str, ...] = ("cleanrl", "torch", "gym", "gymnasium", "stable-baselines3", "numpy", "mujoco", "tensorboard")
_PATCHED = "rlpipe-patched"  # folder in the venv with the patched SAC/TD3 copies and the env plugin's source

# The patch for sac_continuous_action.py and td3_continuous_action.py: (old, new) replacements, each of
# which must match exactly once. stable-baselines3 2.x's ReplayBuffer takes gymnasium spaces only (it
# raises NotImplementedError on gym's Box); the observation box keeps the float32 the script sets.
PATCH: tuple[tuple[str, str], ...] = (
    ("import gym\n", "import gym\nimport gymnasium  # rlpipe patch\n"),
    ("        envs.single_observation_space,\n        envs.single_action_space,\n",
     "        gymnasium.spaces.Box(envs.single_observation_space.low, envs.single_observation_space.high, dtype=np.float32),  # rlpipe patch\n"
     "        gymnasium.spaces.Box(envs.single_action_space.low, envs.single_action_space.high, dtype=envs.single_action_space.dtype),  # rlpipe patch\n"),
)
_PATCH_HEADER = """\
# Copy of {script} from cleanrl 1.2.0 (PyPI), MIT License, Copyright (c) 2019 CleanRL developers.
# Patched by rlpipe (scripts/bench/peers/cleanrl.py) to run with stable-baselines3 2.0.0a1: the lines marked
# "rlpipe patch" hand ReplayBuffer gymnasium boxes equal to the env's gym boxes. Nothing else differs.
"""
ENV_SHIM = '''\
"""gym 0.23 ids for gymnasium 0.28's MuJoCo v4 envs, written by rlpipe's scripts/bench/peers/cleanrl.py.

CleanRL 1.2.0's SAC/TD3 scripts use gym 0.23.1, whose MuJoCo envs need mujoco-py. ``register`` is a gym
env plugin (entry point ``gym.envs: __root__``, run by ``import gym``): it registers each gymnasium MuJoCo
v4 env under the same id in gym. The gymnasium env runs unwrapped; gym's TimeLimit, registered with the
gymnasium spec's ``max_episode_steps``, ends the episodes and sets ``TimeLimit.truncated`` as for gym's
own envs. It runs while ``gym`` is still being imported, hence the imports from gym's submodules.
"""
import gymnasium
from gym.core import Env
from gym.envs.registration import register as gym_register
from gym.spaces import Box


def _box(space):
    return Box(space.low, space.high, dtype=space.dtype)


class GymnasiumEnv(Env):
    def __init__(self, env_id):
        self._env = gymnasium.make(env_id).unwrapped
        self.observation_space = _box(self._env.observation_space)
        self.action_space = _box(self._env.action_space)
        self._seed = None

    def seed(self, seed=None):
        self._seed = seed  # used by the next reset, as gymnasium seeds through reset
        return [seed]

    def reset(self, *, seed=None, return_info=False, options=None):
        obs, info = self._env.reset(seed=self._seed if seed is None else seed, options=options)
        self._seed = None
        return (obs, info) if return_info else obs

    def step(self, action):
        obs, reward, terminated, _, info = self._env.step(action)  # unwrapped: never truncated
        return obs, reward, terminated, info

    def close(self):
        self._env.close()


def register():
    for spec in list(gymnasium.envs.registry.values()):
        if spec.id.endswith("-v4") and "mujoco" in str(spec.entry_point):
            gym_register(id=spec.id, entry_point="cleanrl_peer_envs:GymnasiumEnv",
                         max_episode_steps=spec.max_episode_steps, kwargs={"env_id": spec.id})
'''
ENV_SHIM_PROJECT = """\
[build-system]
requires = ["setuptools"]
build-backend = "setuptools.build_meta"

[project]
name = "cleanrl-peer-envs"
version = "0"

[project.entry-points."gym.envs"]
__root__ = "cleanrl_peer_envs:register"

[tool.setuptools]
py-modules = ["cleanrl_peer_envs"]
"""
# CleanRL prints ``global_step=123, episodic_return=[-1234.5]`` (a bare float for the gym scripts).
_EPISODE = re.compile(r"global_step=(\d+), episodic_return=\[?\s*([-+0-9.eEinfa]+)")
_RESERVED = {"seed", "env_id", "total_timesteps", "track", "capture_video", "save_model"}


def venv_dir() -> Path:
    return _venv.venv_dir("cleanrl")


def _package_dir(root: Path) -> Path:
    found = sorted(root.glob("lib/python3*/site-packages/cleanrl"))
    if not found:
        raise RuntimeError(f"CleanRL peer venv {root}: no cleanrl package in it; remove the folder to rebuild it")
    return found[0]


def _patched(source: str, script: str) -> str:
    for old, new in PATCH:
        if source.count(old) != 1:
            raise RuntimeError(f"CleanRL peer: the patch for {script} expects {old.strip()!r} exactly once")
        source = source.replace(old, new)
    return _PATCH_HEADER.format(script=f"cleanrl/{script}") + source


def _write_if_changed(path: Path, text: str) -> bool:
    if path.exists() and path.read_text() == text:
        return False
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return True


def _install_patched(root: Path, python: Path, log: Path) -> None:
    """The patched SAC/TD3 copies and the env plugin, (re)made when this module's version of them differs."""
    package, folder = _package_dir(root), root / _PATCHED
    for algo in ("sac", "td3"):
        _write_if_changed(folder / ALGOS[algo], _patched((package / ALGOS[algo]).read_text(), ALGOS[algo]))
    source = folder / "cleanrl-peer-envs"
    changed = _write_if_changed(source / "cleanrl_peer_envs.py", ENV_SHIM)
    changed |= _write_if_changed(source / "pyproject.toml", ENV_SHIM_PROJECT)
    if changed or not (package.parent / "cleanrl_peer_envs.py").exists():
        _venv.run_step([str(python), *_venv.PIP, "--no-deps", "--no-build-isolation", "--force-reinstall", str(source)],
                       log, "installing the env plugin")


def ensure_venv(quiet: bool = False) -> Path:
    """The peer venv's python, building the venv first if it is missing or was built from other pins."""
    return _venv.ensure("cleanrl", "CleanRL", "the scripts import distutils, gone in 3.12", [
        (TORCH_PINS, "installing torch"),
        (BUILD_PINS, "installing the build tools"),
        (("--no-build-isolation", *PINS), "pip install"),
        (("--no-deps", "--ignore-requires-python", CLEANRL), "installing cleanrl"),
    ], quiet=quiet, then=_install_patched)


def _script(algo: str) -> Path:
    if algo not in ALGOS:
        raise ValueError(f"algo={algo!r}: expected one of {sorted(ALGOS)}")
    root = venv_dir()
    return root / _PATCHED / ALGOS[algo] if algo in ("sac", "td3") else _package_dir(root) / ALGOS[algo]


def _atari_roms() -> str:
    """The ROM folder of the ale-py installed beside rlpipe (``rlpipe[atari]``), for the peer's ale-py 0.8.1."""
    import importlib.util

    spec = importlib.util.find_spec("ale_py")
    roms = Path(spec.submodule_search_locations[0]) / "roms" if spec and spec.submodule_search_locations else None
    if roms is None or not any(roms.glob("*.bin")):
        raise RuntimeError("CleanRL's dqn_atari.py needs the Atari ROMs that ale-py ships: pip install -e \".[atari]\"")
    return str(roms)


def _literal(node: ast.expr) -> object:
    """A default as written in the script: a literal, or ``int(...)``/``float(...)`` of one (``int(1e6)``)."""
    if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in ("int", "float"):
        return {"int": int, "float": float}[node.func.id](ast.literal_eval(node.args[0]))
    return ast.literal_eval(node)


def defaults(algo: str) -> dict:
    """The script's hyperparameters, from its ``parse_args`` (cleanrl 1.2.0 uses argparse, not tyro).

    Keys are the flags' names with ``_`` (``learning_starts``, ``batch_size``, ...), values converted as
    the flag's ``type`` converts a command-line value (``--learning-starts`` defaults to ``5e3``, an int
    5000 here). Defaults that are not literals (``exp_name``, from the file name) are left out.
    """
    ensure_venv(quiet=True)
    tree = ast.parse(_script(algo).read_text())
    found: dict[str, object] = {}
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "add_argument"):
            continue
        keywords = {k.arg: k.value for k in node.keywords}
        try:
            value = _literal(keywords["default"])
        except (KeyError, ValueError):
            continue
        kind = keywords.get("type")
        if isinstance(kind, ast.Name) and kind.id in ("int", "float") and value is not None:
            value = {"int": int, "float": float}[kind.id](value)
        elif isinstance(kind, ast.Lambda):  # the scripts' strtobool flags
            value = bool(value)
        found[ast.literal_eval(node.args[0]).lstrip("-").replace("-", "_")] = value
    return found


def _overrides(extra_args: Sequence[str]) -> dict[str, str]:
    """``--key value`` / ``--key=value`` pairs of ``extra_args``, keyed like :func:`defaults`."""
    out, args = {}, list(extra_args)
    while args:
        flag = args.pop(0)
        if not flag.startswith("--"):
            raise ValueError(f"extra_args: expected --flag value pairs, got {flag!r}")
        key, eq, value = flag[2:].partition("=")
        if not eq:
            if not args:
                raise ValueError(f"extra_args: {flag} has no value")
            value = args.pop(0)
        out[key.replace("-", "_")] = value
    return out


def _convert(default: object, text: str) -> object:
    """A command-line value as the script reads it: the default's type, strtobool for the boolean flags."""
    if isinstance(default, bool):
        return text.lower() in ("y", "yes", "t", "true", "on", "1")
    return text if default is None else type(default)(text)


def _python_version() -> str:
    match = re.search(r"^version(?:_info)?\s*=\s*(\S+)", (venv_dir() / "pyvenv.cfg").read_text(), re.M)
    return match[1] if match else "unknown"


def _script_env_id(algo: str, env_id: str) -> str:
    """The id the script is given: for the gym-based SAC/TD3, a MuJoCo v5 id runs as the plugin's v4; for
    dqn_atari.py, ``ALE/Game-v5`` runs as ``GameNoFrameskip-v4`` (its own default's form: no frame skip, no sticky
    actions, which its wrappers and rlpipe's ``dqn-atari`` preset both set)."""
    if algo == "dqn_atari" and env_id.startswith("ALE/"):
        return env_id.removeprefix("ALE/").rpartition("-v")[0] + "NoFrameskip-v4"
    name, _, version = env_id.rpartition("-v")
    if algo in ("sac", "td3") and version == "5":
        return f"{name}-v4"
    return env_id


def _updates(algo: str, hp: dict, total: int) -> int:
    """Critic updates in a run: each ``global_step`` in (learning_starts, total) for SAC/TD3, and those that
    are multiples of ``train_frequency`` for DQN (its gradient steps)."""
    starts = int(hp["learning_starts"])
    if algo in ("dqn", "dqn_atari"):
        every = int(hp["train_frequency"])
        return max(0, (total - 1) // every - starts // every)
    return max(0, total - 1 - starts)


def _run(cmd: list[str], env: dict[str, str], cwd: str, timeout_s: float) -> dict:
    """One run; its ``global_step=..., episodic_return=...`` lines are time-stamped as they arrive, and the
    1-minute load average is noted before and after (these machines are shared: a load well above the
    run's own threads means the figure is not the script's)."""
    load_before = os.getloadavg()[0]
    start = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    timer = threading.Timer(timeout_s, proc.kill)
    timer.start()
    episodes: list[tuple[int, float, float]] = []
    tail: deque[str] = deque(maxlen=5)
    assert proc.stdout is not None
    for line in proc.stdout:
        match = _EPISODE.match(line)
        if match:
            episodes.append((int(match[1]), float(match[2]), time.perf_counter() - start))
        elif line.strip() and not line.startswith("SPS:"):
            tail.append(line.strip())
    rc = proc.wait()
    wall = time.perf_counter() - start
    timed_out = not timer.is_alive()
    timer.cancel()
    if timed_out:
        raise RuntimeError(f"CleanRL run timed out after {timeout_s:.0f} s: {shlex.join(cmd)}")
    if rc:
        raise RuntimeError(f"CleanRL run failed (exit {rc}): {(list(tail) or ['no output'])[-1]} ({shlex.join(cmd)})")
    return {"wall_s": wall, "episodes": episodes, "load": (load_before, os.getloadavg()[0])}


def cleanrl_speed(algo: str, env_id: str, lengths: tuple[int, int], seed: int = 0, threads: int | None = None,
                  extra_args: Sequence[str] = (), timeout_s: float = 1800) -> dict:
    """Updates/s and env steps/s of a CleanRL script after ``learning_starts``, from two runs.

    ``lengths`` = (n1, n2): env steps after ``learning_starts`` (the script's, or one set in ``extra_args``,
    e.g. ``("--learning-starts", "1000")``) for the two runs. ``threads``: None leaves torch's default
    (OMP_NUM_THREADS/MKL_NUM_THREADS removed from the environment), k sets both to k; the scripts set no
    thread count themselves. ``timeout_s`` bounds both runs together.

    Returns ``updates_per_s`` and ``env_steps_per_s`` (differences of the two runs), ``updates_per_s_in_run``
    (the longer run's episode lines after learning starts; None with fewer than two), ``runs``,
    ``threads``, ``episodic_returns`` / ``episodic_return_steps`` (the longer run's last ten),
    ``hyperparameters`` (the script's defaults with ``extra_args`` applied), ``env_id`` and
    ``script_env_id``, ``command`` (the longer run's, with its environment variables) and ``versions``.
    """
    n1, n2 = lengths
    if not 0 <= n1 < n2:
        raise ValueError(f"lengths must be two increasing counts of steps after learning_starts, got {lengths}")
    python = ensure_venv()
    hp = defaults(algo)
    overrides = _overrides(extra_args)
    if unknown := set(overrides) - set(hp):
        raise ValueError(f"extra_args: {ALGOS[algo]} has no flag {sorted(unknown)}")
    if reserved := set(overrides) & _RESERVED:
        raise ValueError(f"extra_args: {sorted(reserved)} are set by cleanrl_speed itself")
    hp.update({k: _convert(hp[k], v) for k, v in overrides.items()})
    starts = int(hp["learning_starts"])
    script_env = _script_env_id(algo, env_id)
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "PYTHONPATH", "PYTHONHOME")}
    run_env = {"PYTHONUNBUFFERED": "1"} | ({} if threads is None else {"OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)})
    if algo == "dqn_atari":
        run_env["ALE_PY_ROM_DIR"] = _atari_roms()
    flags = ["--track", "False", "--capture-video", "False"] + (["--save-model", "False"] if "save_model" in hp else [])
    deadline = time.monotonic() + timeout_s
    runs, episodes, command = [], [], ""
    for n in (n1, n2):
        total = starts + n
        cmd = [str(python), str(_script(algo)), "--seed", str(seed), "--env-id", script_env,
               "--total-timesteps", str(total), *flags, *extra_args]
        command = " ".join(f"{k}={v}" for k, v in run_env.items()) + " " + shlex.join(cmd)
        with tempfile.TemporaryDirectory(prefix="rlpipe-cleanrl-") as tmp:  # the script's runs/ goes here
            out = _run(cmd, env | run_env, tmp, max(1.0, deadline - time.monotonic()))
        episodes = out["episodes"]
        learning = [(step, t) for step, _, t in episodes if step > starts] or [(0, 0.0)]
        runs.append({"total_timesteps": total, "updates": _updates(algo, hp, total), "wall_s": out["wall_s"],
                     "episodes": len(episodes), "load_avg_1min": out["load"],
                     "learn_steps": learning[-1][0] - learning[0][0], "learn_s": learning[-1][1] - learning[0][1]})
    first, second = runs
    dt = second["wall_s"] - first["wall_s"]
    if dt <= 0:
        raise RuntimeError(f"CleanRL {algo}: the {n2}-step run took no longer than the {n1}-step one "
                           f"({second['wall_s']:.1f} s vs {first['wall_s']:.1f} s); the machine is too noisy for this")
    updates_per_step = (second["updates"] - first["updates"]) / (n2 - n1)
    pins = dict(p.split("==") for p in (*TORCH_PINS, *PINS, CLEANRL))
    return {
        "updates_per_s": (second["updates"] - first["updates"]) / dt,
        "env_steps_per_s": (n2 - n1) / dt,
        "updates_per_s_in_run": updates_per_step * second["learn_steps"] / second["learn_s"] if second["learn_s"] > 0 else None,
        "runs": runs,
        "threads": threads or "default",
        "episodic_returns": [r for _, r, _ in episodes[-10:]],
        "episodic_return_steps": [step for step, _, _ in episodes[-10:]],
        "hyperparameters": hp,
        "env_id": env_id,
        "script_env_id": script_env,
        "command": command,
        "versions": {"python": _python_version(), **{d: pins[d] for d in REPORTED}},
    }
