"""Stop signals at the edges of a run, as supervisors and people send them: a storm of SIGTERMs or Ctrl-Cs (a
scheduler's repeated TERM, a key held down) ends ``rlpipe`` with the first signal's status (143, 130) and its one
line, whichever moment each lands in (the loop, the checkpoint, the run's end, the interpreter's exit), never by
the signal's default action or with a traceback; a stop that lands after the run's last safe point says that the
run had finished and exits as the signal asks.

Every run is a real ``rlpipe`` process held (SIGSTOP from the fault hook) at an exact iteration before the storm.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import threading

import pytest
from test_output_gone import HOLD, RUN, N, start, wait_held


def _storm(proc: subprocess.Popen, signum: int, every_s: float = 0.01) -> threading.Thread:
    """``signum`` to the run's process group every ``every_s`` seconds until it has exited."""

    def send():
        while proc.poll() is None:
            try:
                os.killpg(proc.pid, signum)
            except ProcessLookupError:
                return
            threading.Event().wait(every_s)

    thread = threading.Thread(target=send, daemon=True)
    thread.start()
    return thread


@pytest.mark.slow
@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_a_storm_of_stop_signals_ends_with_the_first_ones_status_and_one_line(tmp_path, signum):
    run = tmp_path / "run"
    proc = start(RUN, run, fault=HOLD, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    wait_held(proc)
    storm = _storm(proc, signum)
    os.killpg(proc.pid, signal.SIGCONT)
    try:
        _, err = proc.communicate(timeout=240)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    storm.join()
    assert proc.returncode == 128 + signum, f"exit {proc.returncode}:\n{err[-3000:]}"
    for sign in ("Traceback", "Exception ignored", "leaked semaphore", "rlpipe: error"):
        assert sign not in err, err[-3000:]
    said = [line for line in err.splitlines() if line.startswith("rlpipe: interrupted")]
    assert len(said) == 1, err[-3000:]


@pytest.mark.slow
@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_a_stop_after_the_runs_last_safe_point_says_it_had_finished_and_exits_as_the_signal_asks(tmp_path, signum):
    """The signal lands once the last checkpoint is written (the run's end): the run is whole, nothing is lost,
    and the exit is still the signal's, with a line saying why nothing was saved."""
    run = tmp_path / "run"
    name = signal.Signals(signum).name
    proc = start([*RUN, "--no-progress"], run, fault=f"checkpoint.written@{N}:{name}:self", stdout=subprocess.PIPE,
                 stderr=subprocess.PIPE, text=True)
    out, err = proc.communicate(timeout=240)
    assert proc.returncode == 128 + signum, f"exit {proc.returncode}:\n{err[-3000:]}"
    summary = json.loads((run / "summary.json").read_text())
    assert summary["iterations"] == N and (run / "policy" / "policy.onnx").exists()
    assert "came after the command's work was done: nothing was left to save" in err, err[-3000:]
    assert "Traceback" not in err and "continue with" not in err, err[-3000:]
