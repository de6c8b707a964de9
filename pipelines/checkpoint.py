"""Checkpoints that resume a run exactly: modules, optimisers, replay buffer, counters, RNG states.

Everything is one ``torch.save`` of tensors and plain data, read back with ``weights_only=True``
so a checkpoint can never run code. That includes the replay buffer's contents: TorchRL's own
``ReplayBuffer.dumps``/``loads`` unpickles a file of the checkpoint on load, so it is not used. Each checkpoint is written into a temporary folder and renamed into place, and
the ``latest`` pointer is replaced atomically: a crash mid-save leaves the previous one intact.
"""

from __future__ import annotations

import os
import random
import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

from rlpipe.pipelines.errors import InputError
from rlpipe.pipelines.files import write_text_atomic

__all__ = [
    "save_checkpoint", "load_checkpoint", "latest_checkpoint", "rng_state", "set_rng_state",
    "replay_buffer_state", "load_replay_buffer",
]

FORMAT = "rlpipe-checkpoint/1"
KEEP = 2


def rng_state() -> dict[str, Any]:
    np_state = np.random.get_state()
    return {
        "torch": torch.get_rng_state(),
        "numpy": {"key": torch.from_numpy(np_state[1].astype(np.int64)), "pos": int(np_state[2]),
                  "has_gauss": int(np_state[3]), "cached": float(np_state[4])},
        "python": random.getstate(),
    }


def set_rng_state(state: dict[str, Any]) -> None:
    torch.set_rng_state(state["torch"])
    n = state["numpy"]
    np.random.set_state(("MT19937", n["key"].numpy().astype(np.uint32), n["pos"], n["has_gauss"], n["cached"]))
    py = state["python"]
    random.setstate((py[0], tuple(py[1]), py[2]))


def replay_buffer_state(replay_buffer) -> dict[str, Any]:
    """The buffer's transitions as plain tensors, oldest first (so FIFO eviction resumes in order)."""
    n = len(replay_buffer)
    if n == 0:
        return {"len": 0}
    storage = replay_buffer.storage
    index = torch.arange(n)
    if n == storage.max_size:
        # TorchRL's round-robin writer has no public getter for its next write position.
        index = (index + int(replay_buffer._writer._cursor)) % n
    data = storage.get(index)
    return {"len": n, "data": {key: value for key, value in data.flatten_keys("/").items()}}


def load_replay_buffer(replay_buffer, state: dict[str, Any], keys=None) -> None:
    """Refill ``replay_buffer`` (a fresh one) from ``replay_buffer_state`` output.

    ``keys``: store only these (a checkpoint saved with every key, loaded by a run that stores
    fewer); None stores what the checkpoint has.
    """
    from tensordict import TensorDict

    if state["len"] == 0:
        return
    data = TensorDict(state["data"], batch_size=[state["len"]]).unflatten_keys("/")
    replay_buffer.extend(data if keys is None else data.select(*keys))


def save_checkpoint(folder: Path, step: int, state: dict[str, Any]) -> Path:
    """Write checkpoint ``step`` under ``folder`` atomically; keep the newest ``KEEP``."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    final = folder / f"step_{step:010d}"
    tmp = Path(tempfile.mkdtemp(dir=folder, prefix=".tmp-"))
    try:
        torch.save({"format": FORMAT, "step": step, **state}, tmp / "state.pt")
        if final.exists():
            shutil.rmtree(final)
        os.replace(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    write_text_atomic(folder / "latest", final.name + "\n")
    for old in sorted(p for p in folder.glob("step_*") if p.is_dir())[:-KEEP]:
        shutil.rmtree(old, ignore_errors=True)
    return final


def latest_checkpoint(folder: Path) -> Path:
    folder = Path(folder)
    pointer = folder / "latest"
    if not pointer.exists():
        raise InputError(f"{folder}: no checkpoint to resume from (no 'latest'); expected a run that saved one")
    path = folder / pointer.read_text().strip()
    if not (path / "state.pt").exists():
        raise InputError(f"{path}: checkpoint is missing its state.pt; expected a complete checkpoint folder")
    return path


def load_checkpoint(path: Path, algo: str, env_id: str) -> dict[str, Any]:
    """Read a checkpoint written by ``save_checkpoint`` for the same pipeline and env."""
    path = Path(path)
    try:
        state = torch.load(path / "state.pt", weights_only=True, map_location="cpu")
    except Exception as exc:  # noqa: BLE001 - torch.load raises any kind on arbitrary bytes (IndexError, KeyError, ...)
        raise InputError(f"{path / 'state.pt'}: corrupt or not an rlpipe checkpoint ({type(exc).__name__})") from exc
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        raise InputError(f"{path / 'state.pt'}: not an rlpipe checkpoint (expected format {FORMAT!r})")
    if state.get("algo") != algo or state.get("env") != env_id:
        raise InputError(
            f"{path}: checkpoint is for {state.get('algo')} on {state.get('env')}; expected {algo} on {env_id}"
        )
    return state
