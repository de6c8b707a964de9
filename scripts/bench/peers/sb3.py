"""Peers of ``rlpipe bench time-to-return``: Stable-Baselines3 (PyTorch) and SBX (its JAX twin), with
RL-Zoo's tuned hyperparameters, each in a venv of its own built on first use (``_venv``).

Both venvs hold ``rl_zoo3`` for its hyperparameter files (``rl_zoo3/hyperparams/ALGO.yml``), read here
with PyYAML (``zoo_hyperparams``). ``torch==2.13.0`` goes in first (``cleanrl.TORCH_PINS``): SB3 pulls
torch in, and any other torch spec would download a multi-GB CUDA build. The rest are pinned to the ``pip freeze``
of an install that works.

The runner, ``ttr_sb3.py`` beside this file, runs with the venv's python.
"""

from __future__ import annotations

from pathlib import Path

from rlpipe.scripts.bench.peers import _venv
from rlpipe.scripts.bench.peers.cleanrl import TORCH_PINS

SB3_PINS: tuple[str, ...] = (
    "alembic==1.20.1", "anyio==4.16.0", "Box2D==2.3.10", "chardet==6.0.0.post1", "click==8.5.1", "cloudpickle==3.1.3",
    "colorlog==6.12.0", "DataProperty==1.1.1", "decorator==5.3.1", "Farama-Notifications==0.0.6", "glfw==2.11.0",
    "gymnasium==1.4.0", "gymnasium-robotics==1.4.2", "h11==0.16.0", "hf-xet==1.8.0", "httpcore2==2.16.2", "httpx2==2.16.2",
    "huggingface_hub==2.4.0", "idna==3.20", "imageio-ffmpeg==0.8.1", "ImageIO==2.38.1", "Mako==1.4.3", "markdown-it-py==4.3.0",
    "mbstrdecoder==1.1.5", "mdurl==0.1.2", "moviepy==2.2.1", "mujoco-core==4.0.0", "mujoco-studio==4.0.0",
    "mujoco==4.0.0", "numpy==2.4.6", "optuna==5.0.0", "packaging==26.4", "pathvalidate==3.3.1", "PettingZoo==1.27.0",
    "pillow==11.3.0",
    "proglog==0.1.12", "pybullet==3.2.7", "pygame-ce==2.5.8", "Pygments==2.21.0", "PyOpenGL==3.1.10",
    "pytablewriter==1.2.1", "python-dateutil==2.9.0.post0", "python-dotenv==1.2.4", "pytz==2026.6", "PyYAML==6.0.4",
    "rich==15.0.0", "rl_zoo3==2.9.2", "sb3-team-hf-integration==3.2", "sb3_contrib==2.9.2", "Shimmy==2.0.1",
    "six==1.17.0", "SQLAlchemy==2.1.9", "stable_baselines3==2.9.2", "tabledata==1.3.5", "tcolorpy==0.1.7",
    "tqdm==4.70.1", "truststore==0.10.5", "typepy==1.3.5", "wasabi==1.1.3", "websockets==17.4",
)
SBX_PINS: tuple[str, ...] = (
    "absl-py==2.5.1", "aiofiles==25.1.0", "alembic==1.20.1", "anyio==4.16.0", "attrs==26.1.0", "Box2D==2.3.10",
    "chardet==6.0.0.post1", "click==8.5.1", "cloudpickle==3.1.3", "colorlog==6.12.0", "DataProperty==1.1.1",
    "decorator==5.3.1", "dm-tree==0.1.10", "etils==1.15.0", "Farama-Notifications==0.0.6", "flax==0.12.8",
    "gast==0.7.0", "glfw==2.11.0", "gymnasium==1.4.0", "h11==0.16.0", "hf-xet==1.8.0", "httpcore2==2.16.2",
    "httpx2==2.16.2", "huggingface_hub==2.4.0", "humanize==4.17.0", "idna==3.20", "imageio-ffmpeg==0.8.1",
    "ImageIO==2.38.1", "jax==0.10.2", "jaxlib==0.10.2", "Mako==1.4.3", "markdown-it-py==4.3.0", "mbstrdecoder==1.1.5",
    "mdurl==0.1.2", "ml_dtypes==0.6.0", "moviepy==2.2.1", "msgpack==1.2.4", "mujoco-core==4.0.0",
    "mujoco-studio==4.0.0", "mujoco==4.0.0", "numpy==2.4.6", "opt_einsum==3.4.0", "optax==0.2.8", "optuna==5.0.0",
    "orbax-checkpoint==0.12.8", "packaging==26.4", "pathvalidate==3.3.1", "pillow==11.3.0", "proglog==0.1.12",
    "prometheus_client==0.26.0", "protobuf==7.36.2", "psutil==7.2.2", "pybullet==3.2.7", "pygame-ce==2.5.8",
    "Pygments==2.21.0", "PyOpenGL==3.1.10", "pytablewriter==1.2.1", "python-dateutil==2.9.0.post0",
    "python-dotenv==1.2.4", "pytz==2026.6", "PyYAML==6.0.4", "rich==15.0.0", "rl_zoo3==2.9.2",
    "sb3-team-hf-integration==3.2", "sb3_contrib==2.9.2", "sbx-rl==0.28.0", "scipy==1.17.1", "Shimmy==2.0.1",
    "simplejson==4.3.0", "six==1.17.0", "SQLAlchemy==2.1.9", "stable_baselines3==2.9.2", "tabledata==1.3.5",
    "tcolorpy==0.1.7", "tensorstore==0.1.86", "tfp-nightly==0.26.0.dev20261027", "tqdm==4.70.1", "treescope==0.1.10",
    "truststore==0.10.5", "typepy==1.3.5", "uvloop==0.23.0", "wasabi==1.1.3", "websockets==17.4", "wrapt==2.5.2",
    "zipp==4.1.2",
)
PINS = {"sb3": SB3_PINS, "sbx": SBX_PINS}
LABELS = {"sb3": "Stable-Baselines3", "sbx": "SBX"}
RUNNER = Path(__file__).with_name("ttr_sb3.py")


def venv_dir(lib: str) -> Path:
    return _venv.venv_dir(lib)


def ensure_venv(lib: str, quiet: bool = False) -> Path:
    """The python of ``lib``'s venv (``sb3`` or ``sbx``), built first if missing or built from other pins."""
    return _venv.ensure(lib, LABELS[lib], "the pins are Python 3.11 wheels", [
        (TORCH_PINS, "installing torch"),
        (PINS[lib], "pip install"),
    ], quiet=quiet)


def zoo_file(lib: str, algo: str) -> Path:
    found = sorted(venv_dir(lib).glob(f"lib/python3*/site-packages/rl_zoo3/hyperparams/{algo}.yml"))
    if not found:
        raise RuntimeError(f"{LABELS[lib]} peer venv {venv_dir(lib)}: no rl_zoo3/hyperparams/{algo}.yml; "
                           "remove the folder to rebuild it")
    return found[0]


def zoo_hyperparams(lib: str, algo: str, env_id: str) -> tuple[dict, str]:
    """RL-Zoo's hyperparameters for ``env_id`` and where they came from: the env's own entry; else the
    entry of another version of the same env (MuJoCo ``-v5`` -> the zoo's ``-v4``: v5 changed no dynamics
    or reward of the tasks here, only constructor options; ``CartPole-v0`` -> ``CartPole-v1``: the same
    dynamics, episodes cut at 200 steps instead of 500); else the zoo's ``default`` entry. ``n_timesteps`` and ``policy`` are left out
    (the benchmark sets the step cap; every entry here is ``MlpPolicy``); where a value is a linear schedule
    (``lin_X``), ``schedule_timesteps`` is the entry's ``n_timesteps``, over which the zoo's schedule falls to 0."""
    import yaml

    table = yaml.safe_load(zoo_file(lib, algo).read_text())
    name = env_id.rpartition("-v")[0]
    twins = sorted((k for k in table if "-v" in k and k.rpartition("-v")[0] == name and k != env_id), reverse=True)
    twin = twins[0] if twins else None
    for key, source in ((env_id, f"RL-Zoo {algo}.yml {env_id}"),
                        (twin, f"RL-Zoo {algo}.yml {twin} (no {env_id} entry; same dynamics and reward)"),
                        ("default", f"RL-Zoo {algo}.yml default (no {env_id} entry)")):
        if key and key in table:
            hp = {k: v for k, v in table[key].items() if k not in ("n_timesteps", "policy")}
            if any(isinstance(v, str) and v.startswith("lin_") for v in hp.values()) and "n_timesteps" in table[key]:
                hp["schedule_timesteps"] = int(float(table[key]["n_timesteps"]))  # what the zoo's lin_X falls over
            return hp, source
    return {}, f"SB3 defaults (RL-Zoo {algo}.yml has no {env_id} or default entry)"
