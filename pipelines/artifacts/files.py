"""Files written whole or not at all, and a write that fails said in one line.

Everything a run, an export or a report writes goes to a temporary file in the destination's
folder and is moved over the destination with :func:`os.replace`, so a reader (a person, a
resumed run, ``rlpipe plot`` on a live run) sees the old file or the new one, never half of one,
and a crash mid-write leaves the old one intact (its temporary file is cleared by
:func:`remove_temporaries`).

A write the system refuses (disk full, no permission, a read-only file system) raises
:class:`FileWriteError`: an ``InputError``, so the command line prints it as one line naming the
file and the reason.
"""

from __future__ import annotations

import contextlib
import errno
import json
import math
import os
import re
import tempfile
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from rlpipe.pipelines.errors import InputError

__all__ = [
    "FileWriteError", "atomic_path", "fsync_path", "remove_temporaries", "write_bytes_atomic", "write_json_atomic",
    "write_text_atomic",
]

# What the system says when the storage, not the program, is the problem.
STORAGE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EFBIG, errno.EIO})


class FileWriteError(InputError):
    """``path`` could not be written: the disk is full, permission is missing, or the like."""

    def __init__(self, path: str | os.PathLike, cause: OSError):
        self.path, self.errno = Path(path), cause.errno
        super().__init__(f"cannot write {path}: {cause.strerror or cause}")

    @classmethod
    @contextmanager
    def on_failure(cls, path: str | os.PathLike, errnos: Iterable[int] | None = None) -> Iterator[None]:
        """Turn an ``OSError`` raised inside into a ``FileWriteError`` about ``path`` (only those with
        an errno in ``errnos`` when given: code that may fail for other reasons, such as a writer
        library looking for its program)."""
        try:
            yield
        except FileWriteError:
            raise
        except OSError as exc:
            if errnos is not None and exc.errno not in errnos:
                raise
            raise cls(path, exc) from exc
        except Exception as exc:
            # A writer library's own error over the OSError it met: torch's zip writer, on a full disk, raises
            # "RuntimeError: [enforce fail at inline_container.cc:672] . unexpected pos 209984 vs 209872".
            cause = _storage_error_under(exc, STORAGE_ERRNOS if errnos is None else STORAGE_ERRNOS & set(errnos))
            if cause is None:
                raise
            raise cls(path, cause) from exc


def _storage_error_under(exc: BaseException, errnos: Iterable[int]) -> OSError | None:
    """The ``OSError`` with one of ``errnos`` that ``exc`` was raised while handling (or from), if any."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, OSError) and exc.errno in errnos:
            return exc
        exc = exc.__cause__ or exc.__context__
    return None


@contextmanager
def atomic_path(path: str | os.PathLike, suffix: str = "") -> Iterator[Path]:
    """A temporary path beside ``path`` to write to; on success it becomes ``path``.

    The temporary file is ``.NAME.XXXXXXXX`` + ``suffix`` in ``path``'s folder (a writer that
    picks its format by extension, such as an mp4 or pt2 writer, gets it from ``suffix``); the
    folder must exist. When the block ends normally the file is synced to disk, made readable
    like any other file (0o644: ``mkstemp`` makes 0600), moved over ``path`` and the folder
    synced, so the rename survives a power cut. When the block raises, the temporary file is
    removed and ``path`` is left as it was. A write the storage refuses raises ``FileWriteError``.
    """
    path = Path(path)
    with FileWriteError.on_failure(path):
        fd, name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=suffix)
        os.close(fd)
    tmp = Path(name)
    try:
        with FileWriteError.on_failure(path, STORAGE_ERRNOS):
            yield tmp
        with FileWriteError.on_failure(path):
            fsync_path(tmp)
            os.chmod(tmp, 0o644)
            os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    with FileWriteError.on_failure(path):
        fsync_path(path.parent)


def fsync_path(path: str | os.PathLike) -> None:
    """Flush a file's (or a folder's entries') data to the disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


# mkstemp's names: the prefix, 8 of these characters, the suffix
_TEMPORARY = re.compile(r"\.(?P<name>.+)\.[a-z0-9_]{8}(\.[A-Za-z0-9]+)?")


def remove_temporaries(folder: str | os.PathLike, names: Iterable[str] | None = None) -> list[Path]:
    """Remove the temporary files that writes through ``atomic_path`` into ``folder`` left when
    their process was killed: those for the files ``names``, or all of them. Returns them.

    Only for a folder's one writer (a run directory's lock holder): another writer's temporary
    file looks the same."""
    folder = Path(folder)
    wanted = None if names is None else set(names)
    removed = []
    with contextlib.suppress(FileNotFoundError, NotADirectoryError):
        for path in folder.iterdir():
            match = _TEMPORARY.fullmatch(path.name)
            if match and (wanted is None or match.group("name") in wanted) and path.is_file():
                path.unlink(missing_ok=True)
                removed.append(path)
    return removed


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
    """Write ``data`` as JSON (indent 2, trailing newline) to ``path`` through :func:`atomic_path`.

    NaN and infinities, which JSON has no words for, are written as ``null``: the file is valid
    JSON for any reader (``json.dump`` would write bare ``NaN``)."""
    return write_text_atomic(path, json.dumps(_json_safe(data), indent=2, allow_nan=False) + "\n")


def _json_safe(data: Any) -> Any:
    if isinstance(data, float) and not math.isfinite(data):
        return None
    if isinstance(data, dict):
        return {key: _json_safe(value) for key, value in data.items()}
    if isinstance(data, (list, tuple)):
        return [_json_safe(value) for value in data]
    return data
