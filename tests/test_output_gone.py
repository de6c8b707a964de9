"""A run whose output cannot be written: the reader of its pipe gone (``2>&1 | tee log`` with ``tee`` ended by
the same Ctrl-C, ``| head -5``), its terminal closed, its descriptors closed. It trains on, writes its files, saves
at a stop signal and exits with that signal's status; what cannot be shown is dropped. And the stop's one line
from the first instant (Ctrl-C during the imports), and a full disk said as one line naming the file.

Every run is a real ``rlpipe`` process on a real pipe or pseudo-terminal, held (SIGSTOP from the fault hook,
``RLPIPE_FAULT``) at an exact iteration while its reader goes away, then let go: nothing waits on time.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import select
import signal
import subprocess
import sys
import termios
import time
from pathlib import Path

import pytest
import torch

from rlpipe.pipelines.artifacts import checkpoint as ckpt
from rlpipe.pipelines.artifacts.files import FileWriteError
from rlpipe.pipelines.system.runtime import DroppingStream

ENTRY_POINT = str(Path(sys.executable).parent / "rlpipe")
N = 200
# td3-pendulum saves only at its start and end (checkpoint_interval = its num_iterations): a stop that does not
# save loses the whole run. 100 random steps, then blocks of 50 iterations; held after iteration 100's block.
RUN = ["train", "td3-pendulum", f"num_iterations={N}", "initial_collect_steps=100", "learning_starts=100",
       "eval_interval=200", "num_eval_episodes=1", "log_interval=50"]
HOLD = "collected@100:SIGSTOP"
DEADLINE_S = 240  # generous: the machine is shared; nothing waits on time, only on events


def start(args: list, run: Path, *, fault: str = HOLD, **popen) -> subprocess.Popen:
    """``rlpipe ARGS --out RUN`` in a session of its own (the fault's SIGSTOP holds the run alone)."""
    env = {**os.environ, "RLPIPE_FAULT": fault, "PYTHONFAULTHANDLER": "1"}
    return subprocess.Popen([ENTRY_POINT, *map(str, args), "--out", str(run)], cwd=run.parent, env=env,
                            start_new_session=True, **popen)


def held(proc: subprocess.Popen) -> bool:
    return Path(f"/proc/{proc.pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "T"


def wait_held(proc: subprocess.Popen, drain: int | None = None) -> None:
    """Until ``proc`` is stopped at its fault point, reading what it writes to ``drain`` (a descriptor) meanwhile."""
    deadline = time.monotonic() + DEADLINE_S
    while not held(proc):
        assert proc.poll() is None, f"the run ended (exit {proc.returncode}) before its fault point"
        assert time.monotonic() < deadline, "the run did not reach its fault point"
        if drain is not None and select.select([drain], [], [], 0.02)[0]:
            with contextlib.suppress(OSError):
                os.read(drain, 1 << 16)
        else:
            time.sleep(0.02)


def let_go(proc: subprocess.Popen, signum: int | None = None) -> int:
    """``signum`` to the run's process group (as a terminal or a scheduler sends it), then SIGCONT; its exit status."""
    if signum is not None:
        os.killpg(proc.pid, signum)
    os.killpg(proc.pid, signal.SIGCONT)
    try:
        return proc.wait(timeout=DEADLINE_S)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def saved_at(run: Path) -> int:
    """The iteration of the checkpoint a resume would continue from."""
    return int(ckpt.latest_checkpoint(run / "checkpoints").name.rpartition("_")[2])


def assert_finished(run: Path) -> None:
    summary = json.loads((run / "summary.json").read_text())
    assert summary["iterations"] == N and summary["exact"], summary
    assert saved_at(run) == N and (run / "report.html").exists() and (run / "policy" / "policy.onnx").exists()
    assert not (run / "error.log").exists(), (run / "error.log").read_text()


def assert_stopped_with_a_checkpoint(run: Path, status: int, signum: int) -> None:
    assert status == 128 + signum, f"exit {status}" + _error_log(run)
    assert 100 <= saved_at(run) < N, sorted(ckpt.checkpoint_steps(run / "checkpoints"))  # where it stopped, not step 0
    assert not (run / "error.log").exists(), _error_log(run)


def _error_log(run: Path) -> str:
    log = run / "error.log"
    return f"; error.log:\n{log.read_text()[-3000:]}" if log.exists() else ""


# --- the reader of the run's output gone ----------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("signum, options", [
    (None, []),  # no signal at all: the progress bar's next update meets the closed pipe
    (signal.SIGINT, []),  # `2>&1 | tee log` and Ctrl-C: tee is gone when the run's handler says it stops
    (signal.SIGTERM, ["--no-progress"]),
], ids=["no-signal", "SIGINT", "SIGTERM-no-progress"])
def test_a_run_whose_pipe_reader_is_gone_trains_on_and_a_stop_saves(tmp_path, signum, options):
    """``rlpipe train ... 2>&1 | tee log``, ``tee`` gone at iteration 100: the run goes on to its end (exit 0),
    or stops at a stop signal with a checkpoint of where it was (exit 128 + the signal)."""
    run = tmp_path / "run"
    read, write = os.pipe()
    proc = start([*RUN, *options], run, stdout=write, stderr=write)
    os.close(write)
    try:
        wait_held(proc, drain=read)
    finally:
        os.close(read)  # the reader is gone: every write to the pipe from now on fails (EPIPE)
    status = let_go(proc, signum)
    if signum is None:
        assert status == 0, f"exit {status}" + _error_log(run)
        assert_finished(run)
    else:
        assert_stopped_with_a_checkpoint(run, status, signum)


@pytest.mark.slow
def test_a_finished_run_whose_stdout_is_gone_exits_0_with_no_logging_errors(tmp_path):
    """``rlpipe train ... --no-progress | head -5``: stdout's reader gone after a few lines, stderr still shown.
    The run trains and saves everything, exits 0, and its stderr holds no "--- Logging error ---" or traceback."""
    run, err_file = tmp_path / "run", tmp_path / "stderr.txt"
    read, write = os.pipe()
    with err_file.open("w") as err:
        proc = start([*RUN, "--no-progress"], run, stdout=write, stderr=err)
    os.close(write)
    try:
        wait_held(proc, drain=read)
    finally:
        os.close(read)
    status = let_go(proc)
    stderr = err_file.read_text()
    assert status == 0, f"exit {status}; stderr:\n{stderr[-3000:]}"
    assert "Logging error" not in stderr and "Traceback" not in stderr and "rlpipe: error" not in stderr, stderr[-3000:]
    assert_finished(run)


@pytest.mark.unit
def test_a_stream_whose_reader_is_gone_drops_writes_and_its_descriptor_goes_to_dev_null():
    """What ``rlpipe`` and a run write through: once the reader has gone, writes are dropped, and the descriptor
    is /dev/null, so that the stream's own flush (at the interpreter's exit) and C code writing there cannot fail."""
    read, write = os.pipe()
    stream = open(write, "w", buffering=1)  # line-buffered, as a terminal's stderr
    os.close(read)
    dropped = DroppingStream(stream)
    dropped.write("a line no one reads\n")
    dropped.flush()
    assert dropped.gone and os.readlink(f"/proc/self/fd/{write}") == os.devnull
    stream.write("more\n")
    stream.close()  # flushes: no BrokenPipeError any more


# --- the terminal closed, the descriptors closed ----------------------------------------------------------------


def _controlling_terminal() -> None:  # in the child, after setsid: the pty's slave (its stdin) becomes its terminal
    fcntl.ioctl(0, termios.TIOCSCTTY, 0)


@pytest.mark.slow
def test_the_terminal_closing_stops_the_run_at_a_safe_point_with_a_checkpoint(tmp_path):
    """The run on a pseudo-terminal whose master side closes (the terminal window closed): the system sends it
    SIGHUP and every write to the terminal fails (EIO). It saves at its next safe point and exits 129, and no
    write to the terminal is taken for a refused disk write (that path saved from wherever the run was)."""
    run = tmp_path / "run"
    master, slave = os.openpty()
    proc = start(RUN, run, stdin=slave, stdout=slave, stderr=slave, preexec_fn=_controlling_terminal)
    os.close(slave)
    try:
        wait_held(proc, drain=master)
    finally:
        os.close(master)  # the hang-up: SIGHUP (and SIGCONT) to the terminal's foreground group, the run's
    assert_stopped_with_a_checkpoint(run, let_go(proc), signal.SIGHUP)


@pytest.mark.slow
def test_a_run_started_with_its_descriptors_closed_saves_at_a_stop(tmp_path):
    """``rlpipe train ... <&- >&- 2>&-``: no stdin, stdout or stderr at all. Nothing the run opens may take their
    numbers (a checkpoint written to descriptor 2 by a warning); SIGTERM saves and exits 143."""
    run = tmp_path / "run"
    env = {**os.environ, "RLPIPE_FAULT": HOLD}
    proc = subprocess.Popen(["sh", "-c", 'exec "$0" "$@" <&- >&- 2>&-', ENTRY_POINT, *RUN, "--out", str(run)],
                            cwd=tmp_path, env=env, start_new_session=True, stdin=subprocess.DEVNULL,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wait_held(proc)
    assert_stopped_with_a_checkpoint(run, let_go(proc, signal.SIGTERM), signal.SIGTERM)


# --- Ctrl-C while the command starts --------------------------------------------------------------------------


@pytest.mark.parametrize("library", ["_multiarray_umath", "libtorch"])  # numpy's, the first to load; torch's
def test_ctrl_c_while_the_command_imports_is_one_line(tmp_path, library):
    """Ctrl-C while numpy or torch is being imported (the first seconds): one line and exit 130, not a traceback."""
    proc = subprocess.Popen([ENTRY_POINT, *RUN, "--out", str(tmp_path / "run")], cwd=tmp_path,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    deadline = time.monotonic() + DEADLINE_S
    maps = Path(f"/proc/{proc.pid}/maps")
    while library not in maps.read_text():  # the library's code is loading: its import is under way
        assert proc.poll() is None and time.monotonic() < deadline, f"the command never loaded {library}"
        time.sleep(0.002)
    os.killpg(proc.pid, signal.SIGINT)
    out, err = proc.communicate(timeout=DEADLINE_S)
    assert proc.returncode == 130 and err.strip() == "rlpipe: interrupted", f"exit {proc.returncode}:\n{err}"


# --- a full disk ----------------------------------------------------------------------------------------------


@pytest.fixture
def tiny_disk(tmpfs):
    """A 4 MiB file system of its own (tmpfs), to fill."""
    return tmpfs("4m")


def fill(disk: Path, leave_pages: int = 0) -> Path:
    """Fill ``disk`` but for ``leave_pages`` pages of 4 KiB; the file that fills it."""
    filler = disk / "filler"
    with filler.open("wb") as fh:
        with contextlib.suppress(OSError):
            while True:
                fh.write(b"\0" * (1 << 16))
                fh.flush()
    os.truncate(filler, max(0, filler.stat().st_size // 4096 - leave_pages) * 4096)
    return filler


def one_line(err: str) -> str:
    lines = [line for line in err.strip().splitlines() if line.strip()]
    assert "Traceback" not in err and len(lines) == 1, f"expected one line on stderr, got:\n{err}"
    return lines[0]


def test_a_checkpoint_that_fills_the_disk_says_so_naming_its_file(tiny_disk):
    """torch's writer fails on a full disk with its own error ("[enforce fail at inline_container.cc] unexpected
    pos"): the checkpoint's error is the disk's, one line naming the file, and the previous checkpoint stays."""
    folder = tiny_disk / "checkpoints"
    ckpt.save_checkpoint(folder, 1, {"w": torch.zeros(1000)})
    with pytest.raises(FileWriteError) as raised:
        ckpt.save_checkpoint(folder, 2, {"w": torch.zeros(2 << 20)})  # 8 MiB
    line = str(raised.value)
    assert raised.value.errno == errno.ENOSPC and len(line.splitlines()) == 1, line
    assert "No space left on device" in line and "step_0000000002/state.pt" in line and "enforce" not in line, line
    assert ckpt.latest_checkpoint(folder).name == "step_0000000001"
    assert sorted(p.name for p in folder.iterdir()) == ["latest", "step_0000000001"]


@pytest.mark.slow
def test_a_disk_that_fills_after_the_summary_leaves_the_page_to_resume(tiny_disk):
    """The disk fills after the run's last checkpoint, with room left for summary.json but not for the report
    page: the run says so in one line (the page's failure, not that of the checkpoint it then tries: torch's own
    error there), and once there is room, ``--resume`` writes the page it owes."""
    run = tiny_disk / "run"
    proc = start([*RUN, "--no-progress"], run, fault=f"checkpoint.latest@{N}:SIGSTOP",
                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    wait_held(proc)
    filler = fill(tiny_disk, leave_pages=3)  # summary.json (one page), not returns.png (~30 KB)
    status = let_go(proc)
    line = one_line(proc.stderr.read())
    assert status == 2 and "No space left on device" in line and f"--resume {run}" in line, line
    assert not (run / "report.html").exists()

    filler.unlink()
    resumed = subprocess.run([ENTRY_POINT, *RUN, "--resume", str(run), "--no-progress"], cwd=tiny_disk,
                             capture_output=True, text=True, timeout=DEADLINE_S)
    assert resumed.returncode == 0, resumed.stderr
    assert "report.html" in resumed.stderr, resumed.stderr  # it says what it did
    assert_finished(run)
