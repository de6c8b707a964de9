"""The fault hook: a test makes a run meet a signal, a full disk or a NaN at an exact point of its work.

Tests of what a run does when it is stopped, killed or frozen, when its disk fills, when a worker dies or when
its training diverges need that to happen at one known point, not at a moment chosen by a timer. A test names the
point in ``RLPIPE_FAULT`` (below) and runs rlpipe as a user does, in a process of its own; nothing is swapped
for a mock. In a run without ``RLPIPE_FAULT`` every point is one comparison against an empty list.

Where the points are:

* the training loop's own points (``collected``, ``collector_worker``, ``update``) are not in the loop: the
  ``training.faults.FaultTrigger`` that ``training.run`` adds when ``RLPIPE_FAULT`` names one of them presses
  them from the trigger hooks every run has (after each block; around each update, by wrapping
  ``pipeline.update_step``), so the loop has no test-only call;
* inside a piece of work a trigger does (``evaluate``, ``evaluator_worker``), inside a checkpoint's write
  (``checkpoint.write``, ``.written``, ``.latest``, ``.exchanged``, ``.aside``: between the file operations a
  kill may fall between), at a Ray weight connection (``ray_weight_connect``), and in the commands that run
  many runs (``tune_trial``, ``bench_run``).
"""

from __future__ import annotations

import errno
import os
import signal
import sys
from collections.abc import Callable

__all__ = ["LOOP_POINTS", "fault_point", "fault_set"]

# RLPIPE_FAULT="NAME@STEP" (or "NAME@STEP:SIGTERM", several steps "NAME@100,200:SIGKILL", several faults
# separated by ";"): a process reaching point NAME at iteration STEP sends the signal (default SIGINT)
# to its whole process group, as a terminal's Ctrl-C does (SIGSTOP holds it there until the group
# gets SIGCONT), or to the one process the point is about (a worker), or, with a third field "self"
# ("NAME@STEP:SIGTERM:self"), to itself alone. "NAME@STEP:ENOSPC" (any errno name) raises that
# OSError there instead, as a full disk (or a refused write) would. "NAME@STEP:NAN" sends nothing:
# fault_point returns True and the caller poisons its state (after an update: a parameter becomes NaN,
# ``training.faults.FaultTrigger``).
# RLPIPE_FAULT_ONCE=PATH: only the first process to get there (it creates PATH and writes its command
# line into it), so a study's other runs reaching the same point later do not press again.
_FAULTS = [f for f in os.environ.get("RLPIPE_FAULT", "").split(";") if f]


def fault_set(name: str) -> bool:
    """Whether ``RLPIPE_FAULT`` names point ``name``: a point inside a hot loop is put there only then."""
    return any(fault.partition(":")[0].partition("@")[0] == name for fault in _FAULTS)


def fault_point(name: str, step: int, worker: Callable[[], int | None] | None = None) -> bool:
    """Where tests inject a fault (see ``RLPIPE_FAULT`` above); does nothing in normal runs.

    ``worker``: for a point about a worker process, a function giving its pid (called only when the
    fault fires; None: no such worker now, and no signal). Returns True when the fault is one the
    caller carries out itself (``:NAN``).
    """
    for fault in _FAULTS:
        point, _, rest = fault.partition(":")
        what, _, target = rest.partition(":")
        point_name, _, steps = point.partition("@")
        if point_name != name or str(step) not in steps.split(","):
            continue
        pid = os.getpid() if target == "self" else None
        if worker is not None:
            pid = worker()
            if pid is None:
                continue
        if not _first_to_fire():
            continue
        if what == "NAN":
            return True
        if what.startswith("E"):
            code = getattr(errno, what)
            raise OSError(code, os.strerror(code))
        signum = getattr(signal, what or "SIGINT")
        if pid is None:
            os.killpg(os.getpgrp(), signum)
        else:
            os.kill(pid, signum)
    return False


def _first_to_fire() -> bool:
    marker = os.environ.get("RLPIPE_FAULT_ONCE")
    if not marker:
        return True
    try:
        fd = os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
    except FileExistsError:
        return False
    with os.fdopen(fd, "w") as fh:
        fh.write(" ".join(sys.argv) + "\n")
    return True


LOOP_POINTS = ("collected", "collector_worker", "update")
"""The training loop's points, pressed by ``training.faults.FaultTrigger``."""
