"""The run directory: everything a person wants after a run, in one folder.

    config.json      the resolved config (and which pipeline made it)
    metrics.csv      one row per evaluation/log point
    events.*         TensorBoard events (TorchRL's TensorboardLogger), under tb/
    checkpoints/     what --resume continues from
    policy/          the exported policy (loads with torch alone)
    returns.png      average return against iterations
    summary.json     final figures, wall time, frames, speeds

One process writes a run directory at a time: ``RunDir.create`` and ``RunDir.resume`` lock it
(an OS lock on the folder itself, released when the process ends however it ends), and a second
writer stops with one line naming the first.
"""

from __future__ import annotations

import csv
import fcntl
import io
import json
import os
import time
from pathlib import Path
from typing import Any

from rlpipe.pipelines.artifacts import checkpoint as ckpt
from rlpipe.pipelines.artifacts.files import (
    FileWriteError,
    atomic_path,
    fsync_path,
    remove_temporaries,
    write_json_atomic,
)
from rlpipe.pipelines.errors import InputError
from rlpipe.pipelines.system.runtime import say

__all__ = ["MetricsCSV", "RunDir", "default_run_dir"]

BASE_COLUMNS = ["step", "frames", "updates", "average_return", "average_episode_length"]
SPEED_COLUMNS = ["train_episode_return", "train_episode_length", "episodes", "steps_per_s", "updates_per_s", "wall_time"]
# files a training run writes at the top of its folder (their temporaries are its to clear)
RUN_FILES = ("config.json", "metrics.csv", "summary.json", "returns.png", "report.html")
# collector workers alive, and the restarts of the collector and the background evaluator (blank for
# a run that has none of them); see supervision.Supervisor
WORKER_COLUMNS = ["workers_alive", "collector_restarts", "evaluator_restarts"]


def default_run_dir(algo: str, env_id: str) -> Path:
    stamp = time.strftime("%Y%m%d-%H%M%S")
    return Path("runs") / f"{algo}-{env_id.replace('/', '_').replace(':', '_')}-{stamp}"


def notice(message: str) -> None:
    """One line on stderr about what a run does on its own (resumes elsewhere than asked, restarts); dropped where
    stderr cannot take it (its reader gone, the terminal closed): the run goes on."""
    say(f"rlpipe: {message}")


class RunDir:
    """A run's folder. ``open`` reads one; ``create`` and ``resume`` also make this process its writer."""

    def __init__(self, path: Path | str):
        self.path = Path(path)
        self._lock: int | None = None

    # paths
    config_path = property(lambda self: self.path / "config.json")
    metrics_path = property(lambda self: self.path / "metrics.csv")
    summary_path = property(lambda self: self.path / "summary.json")
    checkpoints = property(lambda self: self.path / "checkpoints")
    policy_dir = property(lambda self: self.path / "policy")
    returns_png = property(lambda self: self.path / "returns.png")

    def holds_run(self) -> bool:
        return self.config_path.exists()

    def has_progress(self) -> bool:
        """Whether the run saved a checkpoint or wrote a metrics row (so it cannot be started again in place)."""
        return bool(ckpt.checkpoint_steps(self.checkpoints)) or (self.checkpoints / "latest").exists() or (
            self.metrics_path.exists() and bool(MetricsCSV.read_rows(self.metrics_path)))

    # --- opening -------------------------------------------------------------------------------------

    @classmethod
    def open(cls, path: Path | str) -> RunDir:
        """A run's folder to read (no lock: ``rlpipe eval``/``plot`` work while it trains)."""
        run = cls(path)
        if not run.holds_run():
            raise InputError(f"{run.path}: not a run directory (no config.json); expected the --out folder of a run")
        return run

    @classmethod
    def create(cls, path: Path | str, algo: str, config: dict) -> RunDir:
        """A new run in ``path`` (made if missing, else empty), locked, its config written.

        A folder holding a run that stopped before its first checkpoint and metrics row (killed
        while starting) is started again in place; any other run is refused.
        """
        run = cls(path)
        if run.path.exists() and not run.path.is_dir():
            raise InputError(f"--out {run.path}: exists and is not a directory; expected a new or empty directory")
        made = not run.path.exists()
        try:
            run.path.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise InputError(f"--out {run.path}: cannot make the directory ({exc.strerror or exc}); "
                             "expected a writable place") from exc
        run._take_lock()
        try:
            if run.holds_run():
                if run.has_progress():
                    raise InputError(f"--out {run.path}: already holds a run (config.json); pass --resume {run.path} "
                                     "to continue it, or choose another --out")
                notice(f"{run.path} holds a run stopped before its first checkpoint; starting it again in place")
            elif any(not _is_temporary_of(p, "config.json") for p in run.path.iterdir()):
                raise InputError(f"--out {run.path}: directory is not empty; expected a new or empty directory")
            run.remove_leftovers()
            run.write_config(algo, config)
        except BaseException:
            run.close()
            if made:
                _remove_if_empty(run.path)
            raise
        return run

    @classmethod
    def resume(cls, path: Path | str) -> RunDir:
        """The run in ``path``, locked, what a crash left behind cleared (``.tmp-*`` folders,
        temporary files), ready for ``--resume``."""
        run = cls.open(path)
        run._take_lock()
        try:
            run.remove_leftovers()
        except OSError as exc:
            run.close()
            raise FileWriteError(run.path, exc) from exc
        return run

    def close(self) -> None:
        """Stop being the run's writer (the lock also goes when the process ends, however it ends)."""
        if self._lock is not None:
            _LOCKED.discard(self._lock)
            os.close(self._lock)
            self._lock = None

    def __enter__(self) -> RunDir:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def remove_leftovers(self) -> None:
        """Temporary files and folders of writes a crash cut short (the writer's own: hold the lock)."""
        remove_temporaries(self.path, RUN_FILES)
        remove_temporaries(self.policy_dir)
        ckpt.remove_leftovers(self.checkpoints)

    # --- the writer's lock ----------------------------------------------------------------------------

    def _take_lock(self) -> None:
        # flock on the folder itself: nothing is written to take it (a refused command leaves the
        # folder as it was), a second open of it conflicts even within one process, and the system
        # drops it when the process dies. (The `filelock` package locks a file it creates and
        # truncates at every try, which could not say who holds it.)
        try:
            fd = os.open(self.path, os.O_RDONLY | os.O_DIRECTORY)
        except OSError as exc:
            raise InputError(f"{self.path}: cannot open the run directory ({exc.strerror or exc}); "
                             "expected a folder this user may read and write") from exc
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise InputError(f"{self.path}: another process is writing this run ({_lock_holder(self.path)}); "
                             "expected one writer at a time: wait for it to end, or stop it first") from None
        except OSError:  # a file system without flock on folders (some network ones): unlocked, as before
            os.close(fd)
            return
        self._lock = fd
        _LOCKED.add(fd)

    def being_written(self) -> bool:
        """Whether a process holds the run's writer lock now (a run training, or resumed, in it)."""
        try:
            fd = os.open(self.path, os.O_RDONLY | os.O_DIRECTORY)
        except OSError:
            return False
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return True
        except OSError:  # no flock here (some network file systems): no writer can be seen
            return False
        finally:
            os.close(fd)  # the shared lock, if taken, goes with it
        return False

    # --- config ----------------------------------------------------------------------------------------

    def write_config(self, algo: str, config: dict) -> None:
        write_json_atomic(self.config_path, {"algo": algo, "config": config})

    def read_config(self) -> tuple[str, dict]:
        try:
            data = json.loads(self.config_path.read_text())
            return data["algo"], data["config"]
        except (json.JSONDecodeError, KeyError, TypeError) as exc:
            raise InputError(f"{self.config_path}: not a valid rlpipe config.json ({exc})") from exc


# The lock's descriptor is closed in a forked child (a collector worker), so that a worker left
# running after its learner was killed does not keep the run locked.
_LOCKED: set[int] = set()


def _close_inherited_locks() -> None:
    for fd in _LOCKED:
        try:
            os.close(fd)
        except OSError:
            pass
    _LOCKED.clear()


os.register_at_fork(after_in_child=_close_inherited_locks)


def _lock_holder(path: Path) -> str:
    """'pid N: command line' of the process holding the flock on ``path`` (Linux /proc), or 'pid unknown'."""
    try:
        st = os.stat(path)
        with open("/proc/locks") as fh:
            lines = fh.read().splitlines()
    except OSError:
        return "pid unknown"
    device = f"{os.major(st.st_dev):02x}:{os.minor(st.st_dev):02x}:{st.st_ino}"
    pids = []
    for line in lines:
        fields = line.split()
        if "->" in fields or len(fields) < 6 or fields[1] != "FLOCK":  # '->': a waiter, not the holder
            continue
        if fields[5] == device or fields[5].rsplit(":", 1)[-1] == str(st.st_ino):
            pids.insert(0 if fields[5] == device else len(pids), fields[4])
    for pid in pids:
        try:
            command = Path(f"/proc/{pid}/cmdline").read_bytes().rstrip(b"\0").replace(b"\0", b" ").decode()
        except OSError:
            continue
        return f"pid {pid}: {command}"
    return "pid unknown"


def _is_temporary_of(path: Path, name: str) -> bool:
    return path.name.startswith(f".{name}.") and path.is_file()


def _remove_if_empty(path: Path) -> None:
    try:
        path.rmdir()
    except OSError:
        pass


class MetricsCSV:
    """metrics.csv: one row per evaluation/log point; a key first logged later (a user's trigger or
    callback) gets a column of its own then.

    TorchRL's CSVLogger writes one file per scalar; a person comparing runs wants one table, so the
    table is written here (TensorBoard gets the same scalars through TorchRL's logger). Each row is
    appended whole and flushed to the system as it is written; ``sync`` puts the rows on the disk
    (before a checkpoint counts them). A row a crash cut short is dropped when the file is read.
    """

    def __init__(self, path: Path, loss_names: list[str], resume_after_step: int | None = None,
                 extra_columns: list[str] = ()):
        self.path = Path(path)
        # extra_columns: what a collector backend reports (Ray: weight versions; workers_alive is shared)
        self.columns = (BASE_COLUMNS + [f"loss_{n}" for n in loss_names] + SPEED_COLUMNS + WORKER_COLUMNS
                        + [c for c in extra_columns if c not in WORKER_COLUMNS])
        if resume_after_step is None:
            self._rewrite([])
        else:
            # Rows past the checkpoint will be produced again by the resumed run; the columns a
            # user's trigger added in an earlier session stay.
            rows = self.read_rows(self.path) if self.path.exists() else []
            self.columns += [c for c in self.read_header(self.path) if c not in self.columns]
            self._rewrite([r for r in rows if int(r["step"]) <= resume_after_step])

    def _rewrite(self, rows: list[dict]) -> None:
        with atomic_path(self.path) as tmp, tmp.open("w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=self.columns)
            writer.writeheader()
            writer.writerows(rows)

    def append(self, row: dict[str, Any]) -> None:
        new = [str(k) for k in row if str(k) not in self.columns]
        if new:
            # A CSV's header comes first: the table is written again with the new columns (atomically:
            # the old table or the new one, never half of each), once per new key.
            rows = self.rows()
            self.columns += new
            self._rewrite(rows)
        line = io.StringIO()
        csv.DictWriter(line, fieldnames=self.columns).writerow({str(k): _fmt(v) for k, v in row.items()})
        with FileWriteError.on_failure(self.path), self.path.open("a", newline="") as fh:
            fh.write(line.getvalue())  # one write: a row is in the file whole, or (disk full) torn at the end

    def sync(self) -> None:
        with FileWriteError.on_failure(self.path):
            fsync_path(self.path)

    def rows(self) -> list[dict[str, str]]:
        return self.read_rows(self.path)

    @staticmethod
    def read_header(path: Path) -> list[str]:
        """The file's columns ([] for a missing or empty file)."""
        try:
            with Path(path).open(newline="", encoding="utf-8", errors="replace") as fh:
                return next(csv.reader([fh.readline().rstrip("\r\n")]), [])
        except FileNotFoundError:
            return []

    @staticmethod
    def read_rows(path: Path) -> list[dict[str, str]]:
        """The file's whole rows: a last line without its newline (torn by a crash or a full disk)
        and any line that is not a row of the header's width with an integer step are left out."""
        text = Path(path).read_bytes().decode("utf-8", errors="replace")
        lines = text.split("\n")
        lines.pop()  # after the last newline: '' or a torn row
        if not lines:
            return []
        header = next(csv.reader([lines[0].rstrip("\r")]))
        rows = []
        for line in lines[1:]:
            try:
                fields = next(csv.reader([line.rstrip("\r")]))
            except (csv.Error, StopIteration):  # NUL bytes (a power cut's zeroed tail), an empty line
                continue
            if len(fields) == len(header) and fields[0].isdigit():
                rows.append(dict(zip(header, fields, strict=True)))
        return rows


def _fmt(v: Any) -> Any:
    if isinstance(v, float):
        return f"{v:.6g}"
    return v
