"""Checkpoints that resume a run exactly: modules, optimisers, replay buffer, counters, RNG states,
and (``RunState``) the collector workers' envs mid-episode (``workers.snapshot_collector``).

Everything is one ``torch.save`` of tensors and plain data, read back with ``weights_only=True``
so a checkpoint can never run code. That includes the replay buffer's contents: TorchRL's own
``ReplayBuffer.dumps``/``loads`` unpickles a file of the checkpoint on load, so it is not used.

On disk, ``checkpoints/`` holds ``step_NNNNNNNNNN/state.pt`` folders and ``latest``, a file naming
the newest. A save is crash-safe at every instant:

1. the new checkpoint is written into a ``.tmp-*`` folder, its file and the folder fsynced;
2. it takes its final name: renamed in, or, when a checkpoint of that step exists already,
   exchanged with it in one atomic step (Linux ``renameat2(RENAME_EXCHANGE)``), the old one
   removed only afterwards; the ``checkpoints`` folder is fsynced;
3. only then ``latest`` moves (an atomic replace, fsynced), and the oldest are pruned.

A kill or a power cut anywhere leaves ``latest`` naming a whole checkpoint. Resuming tolerates
what such a crash leaves (:func:`remove_leftovers`) and what a damaged disk does: a checkpoint
whose file fails its zip checksums is skipped for the newest whole one (:func:`newest_whole`).
"""

from __future__ import annotations

import ctypes
import errno
import os
import random
import re
import secrets
import shutil
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

from rlpipe.pipelines.artifacts.files import FileWriteError, fsync_path, remove_temporaries, write_text_atomic
from rlpipe.pipelines.compat.torchrl import write_cursor
from rlpipe.pipelines.config import TrainConfig
from rlpipe.pipelines.errors import InputError
from rlpipe.pipelines.system.faults import fault_point

__all__ = [
    "save_checkpoint", "load_checkpoint", "latest_checkpoint", "newest_whole", "remove_leftovers",
    "checkpoint_steps", "rng_state", "set_rng_state", "replay_buffer_state", "load_replay_buffer",
]

FORMAT = "rlpipe-checkpoint/1"
KEEP = TrainConfig.checkpoint_keep
"""checkpoints kept by default: ``checkpoint_keep``'s default (the newest and one to fall back on)"""
_NAME = re.compile(r"step_(\d{10,})")
_TMP, _OLD = ".tmp-", ".old-"


def checkpoint_name(step: int) -> str:
    return f"step_{step:010d}"


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
    """The buffer's transitions as plain tensors, oldest first (so FIFO eviction resumes in order), and what a
    buffer of rlpipe's own keeps besides them (``extra_state``: HER's episodes under way, the frame ring)."""
    n = len(replay_buffer)
    extra = {"extra": replay_buffer.extra_state()} if hasattr(replay_buffer, "extra_state") else {}
    if n == 0:
        return {"len": 0, **extra}
    storage = replay_buffer.storage
    index = torch.arange(n)
    if n == storage.max_size:
        index = (index + write_cursor(replay_buffer)) % n
    data = storage.get(index)
    return {"len": n, "data": {key: value for key, value in data.flatten_keys("/").items()}, **extra}


def load_replay_buffer(replay_buffer, state: dict[str, Any], keys=None) -> None:
    """Refill ``replay_buffer`` (a fresh one) from ``replay_buffer_state`` output.

    ``keys``: store only these (a checkpoint saved with every key, loaded by a run that stores
    fewer); None stores what the checkpoint has. A buffer with ``extra_state`` gets its transitions
    back as they were stored (past its own ``extend``) and its extra state.
    """
    from tensordict import TensorDict
    from torchrl.data import ReplayBuffer

    own = hasattr(replay_buffer, "load_extra_state")
    if own:
        replay_buffer.load_extra_state(state.get("extra", {}))
    if state["len"] == 0:
        return
    data = TensorDict(state["data"], batch_size=[state["len"]]).unflatten_keys("/")
    if own:
        ReplayBuffer.extend(replay_buffer, data)
        return
    replay_buffer.extend(data if keys is None else data.select(*keys))


# --- writing ----------------------------------------------------------------------------------------


def save_checkpoint(folder: Path, step: int, state: dict[str, Any], keep: int = KEEP) -> Path:
    """Write checkpoint ``step`` under ``folder`` (see the module's docstring for how), point
    ``latest`` at it, then keep the newest ``keep`` (0: all) of those up to ``step``.

    Checkpoints of later steps are removed as well: they are what a run resumed from an earlier
    checkpoint has left behind (a damaged one it skipped). A failure to write raises
    ``FileWriteError`` and leaves ``folder`` as it was.
    """
    folder = Path(folder)
    final = folder / checkpoint_name(step)
    # mkdir's mode is the umask's, as for the run directory itself (mkdtemp would make 0700)
    tmp = folder / f"{_TMP}{final.name}-{secrets.token_hex(4)}"
    try:
        with FileWriteError.on_failure(folder):
            folder.mkdir(parents=True, exist_ok=True)
            tmp.mkdir()
        with FileWriteError.on_failure(final / "state.pt"):  # the file a reader knows, not its temporary name
            # A Python file object: a full disk is an OSError under torch's own error ("unexpected pos", from
            # its zip writer), which on_failure takes for that OSError.
            with open(tmp / "state.pt", "wb") as fh:
                torch.save({"format": FORMAT, "step": step, **state}, fh)
                fault_point("checkpoint.write", step)
                fh.flush()
                os.fsync(fh.fileno())
            fsync_path(tmp)
        fault_point("checkpoint.written", step)
        with FileWriteError.on_failure(final):
            if final.exists():
                _replace_folder(tmp, final, step)
            else:
                os.rename(tmp, final)
            fsync_path(folder)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)  # the new one not moved in, or the old one exchanged out
    write_text_atomic(folder / "latest", final.name + "\n")
    fault_point("checkpoint.latest", step)
    _prune(folder, step, keep)
    return final


def _replace_folder(new: Path, final: Path, step: int) -> None:
    """Put folder ``new`` in place of folder ``final``; afterwards ``new`` holds the old one."""
    if _exchange(new, final):
        fault_point("checkpoint.exchanged", step)
        return
    # No atomic exchange here (not Linux, or a file system without it): the old one steps aside
    # under a name that `remove_leftovers` puts back if a crash comes before the new one is in.
    aside = final.with_name(_OLD + final.name)
    shutil.rmtree(aside, ignore_errors=True)
    os.rename(final, aside)
    fault_point("checkpoint.aside", step)
    os.rename(new, final)
    os.rename(aside, new)


_RENAME_EXCHANGE = 2  # linux/fs.h
_AT_FDCWD = -100


def _exchange(a: Path, b: Path) -> bool:
    """Swap two paths atomically (Linux ``renameat2``); False where the system cannot.

    Python's ``os`` has no renameat2; glibc (2.28+) exports it.
    """
    try:
        renameat2 = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError):
        return False
    renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    if renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL, errno.EOPNOTSUPP):
        return False
    raise OSError(err, os.strerror(err), str(b))


def checkpoint_steps(folder: Path) -> dict[int, Path]:
    """The checkpoint folders under ``folder`` by step (symbolic links are not checkpoints of this run)."""
    folder = Path(folder)
    if not folder.is_dir():
        return {}
    found = {}
    for path in folder.iterdir():
        match = _NAME.fullmatch(path.name)
        if match and path.is_dir() and not path.is_symlink():
            found[int(match.group(1))] = path
    return dict(sorted(found.items()))


def _prune(folder: Path, step: int, keep: int) -> None:
    steps = checkpoint_steps(folder)
    kept = [s for s in steps if s <= step]
    kept = kept[-keep:] if keep > 0 else kept
    for s, path in steps.items():
        if s not in kept:
            shutil.rmtree(path, ignore_errors=True)


def remove_leftovers(folder: Path) -> None:
    """Clear what a crash mid-save leaves in ``folder``: ``.tmp-*`` folders, a ``latest`` half
    written, and an old checkpoint set aside (put back if its replacement never came in).

    Only for the run's one writer (``RunDir`` holds the lock): another writer's save in progress
    looks the same.
    """
    folder = Path(folder)
    if not folder.is_dir():
        return
    for path in folder.iterdir():
        if path.name.startswith(_TMP):
            _remove(path)
        elif path.name.startswith(_OLD):
            original = path.with_name(path.name[len(_OLD):])
            if _NAME.fullmatch(original.name) and not original.exists():
                os.rename(path, original)
            else:
                _remove(path)
    remove_temporaries(folder, ["latest"])


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


# --- reading ----------------------------------------------------------------------------------------


def _named_by_latest(folder: Path) -> Path | None:
    """The folder ``latest`` names (it may be missing or damaged); None without ``latest``.

    ``latest`` must be a plain file naming a checkpoint folder beside it: anything else (a
    symbolic link, ``../..``, an absolute path) is refused, so a crafted run directory cannot
    make rlpipe read outside itself.
    """
    pointer = folder / "latest"
    if pointer.is_symlink():
        raise InputError(f"{pointer}: is a symbolic link; expected a file naming a checkpoint folder of this run")
    if not pointer.exists():
        return None
    try:
        name = pointer.read_text(encoding="utf-8").strip()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{pointer}: unreadable ({exc}); expected a file naming a checkpoint folder") from exc
    if not _NAME.fullmatch(name):
        raise InputError(f"{pointer}: names {name[:80]!r}; expected a checkpoint folder of this run "
                         "(step_NNNNNNNNNN, beside it)")
    return folder / name


def _damage(path: Path) -> str | None:
    """Why the checkpoint folder ``path`` is not whole, or None when it is.

    torch's files are zip archives with a CRC-32 of every member: checking them finds a torn or
    bit-flipped file that ``torch.load`` would read without a word.
    """
    state = path / "state.pt"
    if path.is_symlink() or state.is_symlink():
        return "a symbolic link, not a checkpoint of this run"
    if not state.is_file():
        return "missing" if not path.exists() else "no state.pt"
    try:
        with zipfile.ZipFile(state) as archive:
            bad = archive.testzip()
    except (zipfile.BadZipFile, OSError, EOFError, ValueError) as exc:
        return f"state.pt damaged: {exc}"
    return f"state.pt damaged: checksum of {bad} fails" if bad else None


def newest_whole(folder: Path) -> tuple[Path | None, list[str]]:
    """The checkpoint to resume from: the one ``latest`` names if it is whole, else the newest
    whole one; and a note for each skipped (``"step_N: why"``). ``(None, [])``: none at all."""
    folder = Path(folder)
    named = _named_by_latest(folder)
    candidates = [named] if named is not None else []
    candidates += [p for p in reversed(checkpoint_steps(folder).values()) if p != named]
    skipped = []
    for path in candidates:
        problem = _damage(path)
        if problem is None:
            return path, skipped
        skipped.append(f"{path.name}: {problem}")
    return None, skipped


def latest_checkpoint(folder: Path) -> Path:
    """The newest whole checkpoint under ``folder`` (see ``newest_whole``); ``InputError`` if none."""
    path, skipped = newest_whole(folder)
    if path is None:
        if skipped:
            raise InputError(f"{folder}: no whole checkpoint to resume from ({'; '.join(skipped)})")
        raise InputError(f"{folder}: no checkpoint to resume from; expected a run that saved one")
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
