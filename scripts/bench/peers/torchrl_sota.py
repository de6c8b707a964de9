"""Peer of ``rlpipe bench time-to-return``: TorchRL's own recipes, the ``sota-implementations`` scripts
(``sac/sac.py``, ``td3/td3.py``, ``dqn/dqn_cartpole.py``) of the pytorch/rl release that matches the installed
``torchrl``, with their published settings (the Hydra config beside each script), only the env id changed.

Where they come from. TorchRL's wheel (0.14.1) ships these scripts (a top-level ``sota-implementations`` folder
in site-packages) but not their configs, so they cannot run from it; its trainer configs
(``sota-implementations/*_trainer/config/``, not in the wheel either) write the networks' input and output sizes
for HalfCheetah, so no env id alone re-points them. The settings are TorchRL's and none is copied here:
``--torchrl-sota DIR`` names the user's checkout of pytorch/rl at the installed version's tag, and
``check_checkout`` refuses one of another release (its ``version.txt`` must name the installed major.minor, and
each script and helper it runs must be, byte for byte, the one the installed wheel ships, where it ships it).

How it runs. In rlpipe's own venv, on the same torch, TorchRL, tensordict, gymnasium and MuJoCo as rlpipe's
side. The scripts need Hydra; ``hydra-core`` 1.3.8 (the newest) pins ``omegaconf<2.4`` while rlpipe runs on 2.4,
so Hydra and that OmegaConf go in a folder of their own (``ensure_hydra``: three pinned wheels, a few seconds),
first on the runner's ``PYTHONPATH``. The runner, ``ttr_torchrl.py`` beside this file, runs the script
unchanged with Hydra overrides for the env id, the seed (SAC's and TD3's ``env.seed``; the DQN script has
none), the frame budget (the task's cap) and the logging switches (no W&B; Hydra's run folder is the run's own).
Everything else is the published config, its random frames, batch sizes, env workers and periodic
evaluation included. It runs on the torch peers' one thread (``--threads torchrl=N`` for another count);
under SAC's and TD3's configs TorchRL's ``ParallelEnv`` of 8 env workers sets the learner's torch threads to
the count less 8 workers, at least 1, whatever it is given.
"""

from __future__ import annotations

import base64
import hashlib
from dataclasses import dataclass
from pathlib import Path

from rlpipe.pipelines.errors import InputError
from rlpipe.scripts.bench.peers import _venv

HYDRA_PINS = ("hydra-core==1.3.8", "omegaconf==2.3.1", "antlr4-python3-runtime==4.9.3")
RUNNER = Path(__file__).with_name("ttr_torchrl.py")


@dataclass(frozen=True)
class Recipe:
    folder: str
    """its folder under ``sota-implementations``"""
    script: str
    config: str
    """the Hydra config beside the script that it loads by default"""
    helpers: tuple[str, ...]
    """the modules of its folder that it imports"""
    env_key: str
    seed_key: str | None
    shown: tuple[str, ...]
    """the config's keys the bench's table shows"""


RECIPES: dict[str, Recipe] = {
    "sac": Recipe("sac", "sac.py", "config.yaml", ("utils.py",), "env.name", "env.seed",
                  ("collector.init_random_frames", "collector.frames_per_batch", "collector.env_per_collector",
                   "optim.utd_ratio", "optim.batch_size", "optim.lr", "network.hidden_sizes", "logger.eval_iter")),
    "td3": Recipe("td3", "td3.py", "config.yaml", ("utils.py",), "env.name", "env.seed",
                  ("collector.init_random_frames", "collector.frames_per_batch", "collector.env_per_collector",
                   "optim.utd_ratio", "optim.batch_size", "optim.lr", "optim.policy_update_delay",
                   "network.hidden_sizes", "logger.eval_iter")),
    "dqn": Recipe("dqn", "dqn_cartpole.py", "config_cartpole.yaml", ("utils_cartpole.py",), "env.env_name", None,
                  ("collector.init_random_frames", "collector.frames_per_batch", "collector.annealing_frames",
                   "collector.eps_end", "buffer.buffer_size", "buffer.batch_size", "loss.num_updates",
                   "loss.hard_update_freq", "optim.lr", "logger.test_interval")),
}


def installed_version() -> str:
    from importlib.metadata import version

    return version("torchrl")


def check_checkout(path: Path | None, algos) -> Path:
    """``path`` if it is a checkout of pytorch/rl whose recipes for ``algos`` are the installed release's; otherwise
    one line (``InputError``) naming what is wrong and the checkout expected."""
    version = installed_version()
    expected = f"a checkout of pytorch/rl at tag v{version} (the installed torchrl)"
    if path is None:
        raise InputError(f"--peers torchrl: needs --torchrl-sota DIR, {expected}: TorchRL's wheel ships its "
                         "sota-implementations scripts but not their configs")
    path = Path(path).expanduser()
    if not (path / "sota-implementations").is_dir():
        raise InputError(f"--torchrl-sota {path}: no sota-implementations folder there; expected {expected}")
    found = (path / "version.txt").read_text().strip() if (path / "version.txt").is_file() else None
    if found is None or found.split(".")[:2] != version.split(".")[:2]:
        raise InputError(f"--torchrl-sota {path}: its version.txt says {found or 'nothing'}; expected {expected}")
    shipped = _shipped_sha256()
    for algo in algos:
        recipe = RECIPES[algo]
        for name in (recipe.script, recipe.config, *recipe.helpers):
            rel = f"sota-implementations/{recipe.folder}/{name}"
            if not (path / rel).is_file():
                raise InputError(f"--torchrl-sota {path}: {rel} missing; expected {expected}")
            if rel in shipped and _sha256(path / rel) != shipped[rel]:
                raise InputError(f"--torchrl-sota {path}: {rel} is not the one torchrl {version} ships; "
                                 f"expected {expected}")
    return path


def _shipped_sha256() -> dict[str, str]:
    """The installed wheel's ``sota-implementations`` files and their sha256 (its RECORD's urlsafe base64)."""
    from importlib.metadata import files

    return {str(f): f.hash.value for f in files("torchrl") or ()
            if f.hash is not None and f.hash.mode == "sha256" and str(f).startswith("sota-implementations/")}


def _sha256(path: Path) -> str:
    return base64.urlsafe_b64encode(hashlib.sha256(path.read_bytes()).digest()).rstrip(b"=").decode()


def script(checkout: Path, algo: str) -> Path:
    recipe = RECIPES[algo]
    return checkout / "sota-implementations" / recipe.folder / recipe.script


def overrides(algo: str, env: str, seed: int, cap: int) -> list[str]:
    """The Hydra overrides the bench gives the script: env id, seed, frame budget, logging; nothing else."""
    recipe = RECIPES[algo]
    keys = [f"{recipe.env_key}={env}", f"collector.total_frames={cap}", "logger.backend=", "logger.video=false",
            "hydra.run.dir=.", "hydra.output_subdir=null"]
    if recipe.seed_key:
        keys.insert(1, f"{recipe.seed_key}={seed}")
    return keys


def settings(checkout: Path, algo: str) -> str:
    """The table's line for the side: the script, its published settings that matter for time, and what is changed."""
    import yaml

    recipe = RECIPES[algo]
    config = yaml.safe_load((script(checkout, algo).parent / recipe.config).read_text())
    shown = []
    for key in recipe.shown:
        value = config
        for part in key.split("."):
            value = value.get(part) if isinstance(value, dict) else None
        shown.append(f"{key.split('.')[-1]}={value}")
    seed = f", {recipe.seed_key}" if recipe.seed_key else " (it has no seed setting)"
    return (f"TorchRL {installed_version()} `sota-implementations/{recipe.folder}/{recipe.script}` with its "
            f"{recipe.config} ({', '.join(shown)}); given {recipe.env_key}{seed}, the cap as total_frames, no logger")


def ensure_hydra(quiet: bool = False) -> Path:
    """The folder holding Hydra and the OmegaConf it pins, for the runner's ``PYTHONPATH``."""
    return _venv.ensure_target("torchrl-hydra", "TorchRL recipes' Hydra", HYDRA_PINS, quiet=quiet)
