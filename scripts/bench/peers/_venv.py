"""A peer's own venv, built on first use from pinned requirements: what the CleanRL and TF-Agents
peers share (where it lives, which Python builds it, one locked build, a stamp of the pins).

The peers cannot share rlpipe's environment (old ``gym``, ``numpy<2``, TensorFlow), so each lives
in ``$RLPIPE_PEERS_DIR/<name>`` (default ``~/.cache/rlpipe/peers/<name>``), rebuilt when its pins
change; a file lock makes two benchmarks started together build it once. A peer that runs on rlpipe's
own packages but for a few of its own (TorchRL's recipes: Hydra, which pins an older OmegaConf) gets
only those, in a folder put first on its ``PYTHONPATH`` (``ensure_target``).
"""

from __future__ import annotations

import fcntl
import os
import shlex
import shutil
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

_STAMP = "rlpipe-pins.txt"
PIP = ("-m", "pip", "install", "--disable-pip-version-check", "--no-input")


def venv_dir(name: str) -> Path:
    """Where peer ``name``'s venv lives: ``$RLPIPE_PEERS_DIR/name``, by default under ``~/.cache/rlpipe/peers``."""
    peers = os.environ.get("RLPIPE_PEERS_DIR") or Path.home() / ".cache" / "rlpipe" / "peers"
    return Path(peers).expanduser() / name


def base_python(why: str) -> str:
    """A Python 3.11 to build the venv with (this one, or ``python3.11`` on PATH); ``why`` says what needs it."""
    if sys.version_info[:2] == (3, 11):
        return sys.executable
    found = shutil.which("python3.11")
    if found is None:
        raise RuntimeError(f"the peer venv needs Python 3.11 ({why}); none found on PATH")
    return found


def run_step(cmd: list[str], log: Path, what: str) -> None:
    """Run one build command, appending its output to ``log``; a failure raises with pip's own last error line."""
    with log.open("a") as out:
        out.write(f"$ {shlex.join(cmd)}\n")
        out.flush()
        rc = subprocess.run(cmd, stdout=out, stderr=subprocess.STDOUT, check=False).returncode
    if rc:
        lines = [line.strip() for line in log.read_text().splitlines() if line.strip()]
        errors = [line for line in lines if line.startswith("ERROR")]
        raise RuntimeError(f"{log.stem}: {what} failed (exit {rc}): {(errors or lines or ['no output'])[-1]} "
                           f"(full log: {log})")


def ensure(name: str, label: str, why_311: str, installs: Sequence[tuple[Sequence[str], str]], quiet: bool = False,
           then: Callable[[Path, Path, Path], None] | None = None) -> Path:
    """The python of peer ``name``'s venv, building it first if it is missing or was built from other pins.

    ``installs``: ``(pip install arguments, what it is)`` in order; their arguments are the pins the
    stamp compares. ``then(root, python, log)`` runs under the lock after every call (files the
    peer keeps in its venv beside the packages).
    """
    root = venv_dir(name)
    python = root / "bin" / "python"
    wanted = "\n".join(arg for args, _ in installs for arg in args if not arg.startswith("--")) + "\n"

    def build(log: Path) -> None:
        run_step([base_python(why_311), "-m", "venv", str(root)], log, "creating the venv")
        for args, what in installs:
            run_step([str(python), *PIP, *args], log, what)

    _built_once(name, label, "venv", wanted, lambda: python.exists(), build, quiet,
                None if then is None else lambda log: then(root, python, log))
    return python


def ensure_target(name: str, label: str, pins: Sequence[str], quiet: bool = False) -> Path:
    """The folder holding ``pins`` (exact versions, installed without their dependencies by this python's pip),
    built first if it is missing or holds other pins: put it first on ``PYTHONPATH`` to run this python on
    rlpipe's packages with those in front."""
    root = venv_dir(name)

    def build(log: Path) -> None:
        run_step([sys.executable, *PIP, "--no-deps", "--target", str(root), *pins], log, "installing " + " ".join(pins))

    _built_once(name, label, "packages", "\n".join(pins) + "\n", root.is_dir, build, quiet)
    return root


def _built_once(name: str, label: str, kind: str, wanted: str, present: Callable[[], bool],
                build: Callable[[Path], None], quiet: bool, then: Callable[[Path], None] | None = None) -> None:
    """Under the peer's lock: ``build(log)`` into a fresh ``venv_dir(name)`` unless it is ``present()`` with the stamp
    of ``wanted`` (the pins); ``then(log)`` after, every call."""
    root = venv_dir(name)
    root.parent.mkdir(parents=True, exist_ok=True)
    log = root.parent / f"{name}-install.log"
    with (root.parent / f"{name}.lock").open("w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # two benchmarks started together build it once
        stamp = root / _STAMP
        if not (present() and stamp.exists() and stamp.read_text() == wanted):
            if not quiet:
                print(f"building the {label} peer {kind} in {root} (once{'; a minute or more' if kind == 'venv' else ''})",
                      file=sys.stderr)
            start = time.perf_counter()
            shutil.rmtree(root, ignore_errors=True)
            log.write_text("")
            build(log)
            stamp.write_text(wanted)
            if not quiet:
                print(f"{label} peer {kind} ready in {time.perf_counter() - start:.0f} s", file=sys.stderr)
        if then is not None:
            then(log)
