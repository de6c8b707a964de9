"""Peer benchmarks: TF-Agents' SAC-on-Minitaur and DQN-on-CartPole tutorials, timed on this machine.

``rlpipe bench sac`` and ``rlpipe bench dqn`` compare our pipelines with the tutorials they are built
from, and a figure quoted from someone else's run says little about this machine on this day. So this
module runs the tutorials themselves (``benchmarks/tfagents_tutorials/tfagents_sac_minitaur.py`` and
``tfagents_dqn_cartpole.py`` beside it, each notebook as a script) in the same command.

The tutorials need TensorFlow 2.15, TF-Agents 0.19, Reverb 0.14 and, through ``suite_pybullet`` ->
``pybullet_envs`` and ``suite_gym``, the old ``gym`` (TF-Agents 0.19 requires ``gym<=0.23.0``) with
``numpy<2``; none of that may enter rlpipe's own environment. It therefore lives in a venv of its own,
built on first use from PyPI with every version pinned (``PINS``), under ``$RLPIPE_PEERS_DIR/tfagents``
(default ``~/.cache/rlpipe/peers/tfagents``); about 1.7 GB, a minute or so to build.

The speed is taken from two runs of different lengths, (n2 - n1) / (t2 - t1) over the loop's time,
so TensorFlow's tracing of the train step and the first iterations' warm-up cancel out.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import tempfile
import time
from pathlib import Path

from rlpipe.scripts.bench.peers import _venv

# Every distribution in the venv, exactly (``pip freeze --all`` of a working install, pip aside).
# Installed first: the tools that build gym 0.23.0 (an sdist only on PyPI; built without build isolation
# so that they are pinned too). setuptools is also a run-time need: pybullet_envs imports ``pkg_resources``,
# which setuptools 82 removed.
BUILD_PINS: tuple[str, ...] = ("setuptools==80.9.0", "wheel==0.48.0")
PINS: tuple[str, ...] = (
    "tf-agents==0.19.0",
    "tensorflow-cpu==2.15.1",
    "dm-reverb==0.14.0",
    "rlds==0.1.8",
    "tensorflow-probability==0.23.0",
    "gym==0.23.0",
    "gym-notices==0.1.0",
    "pybullet==3.2.7",
    "numpy==1.26.4",
    "absl-py==2.5.1",
    "astunparse==1.6.3",
    "attrs==26.1.0",
    "certifi==2026.10.18",
    "cffi==2.1.1",
    "charset-normalizer==3.5.2",
    "cloudpickle==3.1.2",
    "cryptography==50.0.2",
    "decorator==5.3.1",
    "dm-tree==0.1.10",
    "flatbuffers==25.12.19",
    "gast==0.7.0",
    "gin-config==0.5.0",
    "google-auth==2.62.2",
    "google-auth-oauthlib==1.5.0",
    "google-pasta==0.2.0",
    "grpcio==1.74.0",
    "h5py==3.16.0",
    "idna==3.20",
    "keras==2.15.0",
    "libclang==18.1.1",
    "markdown==3.11.3",
    "markupsafe==3.0.4",
    "ml-dtypes==0.3.2",
    "oauthlib==4.0.1",
    "opt-einsum==3.4.0",
    "packaging==26.3",
    "pillow==13.0.0",
    "portpicker==1.6.0",
    "protobuf==4.25.9",
    "psutil==7.2.2",
    "pyasn1==0.6.5",
    "pyasn1-modules==0.4.2",
    "pycparser==3.12",
    "pygame==2.1.3",
    "requests==2.34.2",
    "requests-oauthlib==2.0.0",
    "six==1.17.0",
    "tensorboard==2.15.2",
    "tensorboard-data-server==0.7.2",
    "tensorflow-estimator==2.15.0",
    "tensorflow-io-gcs-filesystem==0.37.1",
    "termcolor==3.3.0",
    "typing-extensions==4.5.0",
    "urllib3==2.8.0",
    "werkzeug==3.1.9",
    "wrapt==1.14.2",
)
# The distributions whose versions a benchmark report names.
REPORTED: tuple[str, ...] = ("tf-agents", "tensorflow-cpu", "dm-reverb", "tensorflow-probability", "gym", "pybullet", "numpy")
# The tutorials as scripts run by the peer venv's python, never imported by rlpipe: they are this repository's
# (benchmarks/, outside the installed package), so this peer runs from a checkout.
TUTORIALS = Path(__file__).resolve().parents[3] / "benchmarks" / "tfagents_tutorials"
SCRIPT = TUTORIALS / "tfagents_sac_minitaur.py"
DQN_SCRIPT = TUTORIALS / "tfagents_dqn_cartpole.py"
# TensorFlow on the CPU, quiet C++ logs; thread pools stay at TensorFlow's defaults.
RUN_ENV = {"CUDA_VISIBLE_DEVICES": "", "TF_CPP_MIN_LOG_LEVEL": "2"}


def venv_dir() -> Path:
    return _venv.venv_dir("tfagents")


def ensure_venv(quiet: bool = False) -> Path:
    """The peer venv's python, building the venv first if it is missing or was built from other pins."""
    return _venv.ensure("tfagents", "TF-Agents", "the newest TensorFlow 2.15 and dm-reverb 0.14 have wheels for", [
        (BUILD_PINS, "installing the build tools"),
        (("--no-build-isolation", *PINS), "pip install"),
    ], quiet=quiet)


def _versions(python: Path) -> dict[str, str]:
    code = ("import importlib.metadata as m, json, sys; "
            f"print(json.dumps({{'python': sys.version.split()[0], **{{d: m.version(d) for d in {REPORTED!r}}}}}))")
    out = subprocess.run([str(python), "-c", code], capture_output=True, text=True, timeout=60, check=True).stdout
    return json.loads(out)


def _run_tutorial(cmd: list[str], env: dict[str, str], timeout_s: float) -> dict:
    """One run of the tutorial script; its last stdout line is its JSON summary."""
    try:
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout_s, check=False)
    except subprocess.TimeoutExpired:
        raise RuntimeError(f"TF-Agents tutorial run timed out after {timeout_s:.0f} s: {shlex.join(cmd)}") from None
    lines = proc.stdout.strip().splitlines()
    if proc.returncode or not lines or not lines[-1].startswith("{"):
        lines = [line.strip() for line in proc.stderr.splitlines() if line.strip()]
        # the exception's own line; gin appends "In call to configurable ..." lines after it
        errors = [line for line in lines if re.match(r"[\w.]+(Error|Exception|Exit)\b", line)]
        raise RuntimeError(f"TF-Agents tutorial run failed (exit {proc.returncode}): {(errors or lines or ['no output'])[-1]}")
    return json.loads(lines[-1])


def _iterations_per_s(script: Path, iterations: tuple[int, int], seed: int, timeout_s: float,
                      extra_args: tuple[str, ...] = ()) -> dict:
    """Iterations/s of a tutorial script's loop from a run of each length, (n2 - n1) / (t2 - t1) over ``train_s``.

    ``timeout_s`` bounds both runs together; ``extra_args`` go to both. Returns ``iterations_per_s``,
    ``runs`` (the script's two JSON summaries), ``versions`` and ``command`` (both command lines).
    """
    n1, n2 = iterations
    if not 0 < n1 < n2:
        raise ValueError(f"iterations must be two increasing positive counts, got {iterations}")
    if not script.exists():
        raise RuntimeError(f"TF-Agents peer: {script} is missing; the tutorial scripts are not in the wheel, "
                           "run this benchmark from a checkout of the rlpipe repository (pip install -e .)")
    python = ensure_venv()
    deadline = time.monotonic() + timeout_s
    runs, commands = [], []
    with tempfile.TemporaryDirectory(prefix="rlpipe-tfagents-") as tmp:
        # Reverb and the tutorials put their scratch directories under TMPDIR; this one is removed after.
        env = {**os.environ, **RUN_ENV, "TMPDIR": tmp}
        for n in (n1, n2):
            cmd = [str(python), str(script), "--iterations", str(n), "--seed", str(seed), *extra_args]
            commands.append(" ".join(f"{k}={shlex.quote(v)}" for k, v in {**RUN_ENV, "TMPDIR": tmp}.items())
                            + " " + shlex.join(cmd))
            runs.append(_run_tutorial(cmd, env, max(1.0, deadline - time.monotonic())))
    t1, t2 = runs[0]["train_s"], runs[1]["train_s"]
    if t2 <= t1:
        raise RuntimeError(f"TF-Agents tutorial: the {n2}-iteration loop took no longer than the {n1}-iteration one "
                           f"({t2:.1f} s vs {t1:.1f} s); the machine is too noisy for this measurement")
    return {"iterations_per_s": (n2 - n1) / (t2 - t1), "runs": runs, "versions": _versions(python),
            "command": "\n".join(commands)}


def sac_minitaur_iterations_per_s(iterations: tuple[int, int] = (300, 1300), seed: int = 0,
                                  timeout_s: float = 1800) -> dict:
    """Iterations/s of the SAC tutorial's loop (one env step + one update each), from two runs of different lengths.

    Each run does the tutorial's 10,000 random initial steps first (about a minute here); only the
    loop after it is timed. ``timeout_s`` bounds both runs together. Returns ``iterations_per_s``,
    ``runs`` (the script's two JSON summaries), ``versions`` and ``command`` (both command lines).
    """
    return _iterations_per_s(SCRIPT, iterations, seed, timeout_s)


def dqn_cartpole_iterations_per_s(iterations: tuple[int, int] = (2000, 12000), seed: int = 0,
                                  timeout_s: float = 1800, eval_episodes: int = 0) -> dict:
    """Iterations/s of the DQN tutorial's loop (one eager env step + one batch-64 update each), from two runs.

    Each run does the tutorial's 100 random initial steps first (a second or so); only the loop after
    it is timed. ``eval_episodes`` > 0 adds one evaluation after each loop (its AverageReturn is the run's
    ``final_average_return``; not timed). ``timeout_s`` bounds both runs together. Returns
    ``iterations_per_s``, ``runs`` (the script's two JSON summaries), ``versions`` and ``command``.
    """
    extra = ("--eval-episodes", str(eval_episodes)) if eval_episodes else ()
    return _iterations_per_s(DQN_SCRIPT, iterations, seed, timeout_s, extra)
