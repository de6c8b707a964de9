"""Where a command will write, checked before any work starts: ``--out`` of ``rlpipe train``, ``ablate``,
``video``, ``plot``. Bad paths are one ``InputError`` line; nothing is created by the checks."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

__all__ = ["check_output_dir", "check_output_file"]


def _nearest_existing(path: Path) -> Path:
    ancestor = path
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    return ancestor


def _check_writable(flag: str, path: Path, folder: Path) -> None:
    """``folder`` (an existing directory) takes new entries; nothing is left behind by the test."""
    try:  # os.access says yes to root on read-only mounts: only trying tells
        os.rmdir(tempfile.mkdtemp(prefix=".rlpipe-probe-", dir=folder))
    except OSError as exc:
        raise _input_error(f"{flag} {path}: cannot write in {folder} ({exc.strerror}); expected a writable place") from exc


def _input_error(message: str):
    from rlpipe.pipelines.errors import InputError

    return InputError(message)


def check_output_dir(path: Path, flag: str = "--out") -> None:
    """Raise ``InputError`` if a run directory cannot be made at ``path`` (under a file, or in a
    read-only place); creates nothing."""
    path = Path(path)
    ancestor = _nearest_existing(path)
    if not ancestor.is_dir():
        if ancestor == path:
            raise _input_error(f"{flag} {path}: exists and is not a directory; expected a new or empty directory")
        raise _input_error(f"{flag} {path}: {ancestor} is a file, not a directory; expected a path under a directory")
    if ancestor == path and any(path.iterdir()):
        return  # a run directory to continue, or a folder RunDir refuses as not empty: no test write in it
    _check_writable(flag, path, ancestor)


def check_output_file(path: Path, flag: str = "--out") -> None:
    """Raise ``InputError`` if a file cannot be written at ``path`` (a directory there, a file
    among its parents, or a read-only place); creates nothing. E.g. ``rlpipe video --out``."""
    path = Path(path)
    if path.is_dir():
        raise _input_error(f"{flag} {path}: is a directory; expected a file path such as {path / 'video.mp4'}")
    ancestor = _nearest_existing(path.parent)
    if not ancestor.is_dir():
        raise _input_error(f"{flag} {path}: {ancestor} is a file, not a directory; expected a path under a directory")
    _check_writable(flag, path, ancestor)
