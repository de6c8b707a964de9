"""Files written whole or not at all.

Everything a run, an export or a report writes goes to a temporary file in the destination's
folder and is moved over the destination with :func:`os.replace`, so a reader (a person, a
resumed run, ``rlpipe plot`` on a live run) sees the old file or the new one, never half of one,
and a crash mid-write leaves the old one intact.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

__all__ = ["atomic_path", "write_bytes_atomic", "write_json_atomic", "write_text_atomic"]


@contextmanager
def atomic_path(path: str | os.PathLike, suffix: str = "") -> Iterator[Path]:
    """A temporary path beside ``path`` to write to; on success it becomes ``path``.

    The temporary file is ``.NAME.XXXX`` + ``suffix`` in ``path``'s folder (a writer that picks
    its format by extension, such as an mp4 or pt2 writer, gets it from ``suffix``); the folder
    must exist. When the block ends normally the file is synced to disk, made readable like any
    other file (0o644: ``mkstemp`` makes 0600), moved over ``path`` and the folder synced, so
    the rename survives a power cut. When the block raises, the temporary file is removed and
    ``path`` is left as it was.
    """
    path = Path(path)
    fd, name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=suffix)
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        _fsync(tmp)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync(path.parent)


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` through :func:`atomic_path`; returns ``path``."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return path


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` as UTF-8 to ``path`` through :func:`atomic_path` (newlines as given)."""
    return write_bytes_atomic(path, text.encode("utf-8"))


def write_json_atomic(path: str | os.PathLike, data: Any) -> Path:
    """Write ``data`` as JSON (indent 2, trailing newline) to ``path`` through :func:`atomic_path`."""
    return write_text_atomic(path, json.dumps(data, indent=2) + "\n")
