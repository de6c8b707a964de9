"""What a training process needs from the operating system: a stop signal (Ctrl-C, SIGTERM, SIGHUP)
obeyed at safe points, output that never fails the run when no one can read it any more, workers
started deaf to those signals, Python's garbage collector kept off long-lived objects, and freed
memory kept for reuse.

None of this is TorchRL's business (its collectors and evaluator leave signal handling to the
caller), so it lives here, once, for the loop and for anyone driving rlpipe's parts by hand.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import gc
import os
import signal
import sys
import threading
import time
from typing import Any

__all__ = [
    "STOP_SIGNALS", "DeferredInterrupt", "DroppingStream", "Interrupted", "Stopped", "dropping",
    "command_returned", "gc_frozen", "hold_stops_to_exit", "keep_freed_memory", "open_closed_descriptors", "output_dropped_when_gone", "say",
    "WORKER_MODULES", "start_fork_server", "start_resource_tracker", "stop_signals_blocked",
]

# What stops a run at its next safe point: Ctrl-C; what SLURM, Kubernetes, `timeout` and `kill` send;
# the terminal closing. Where a platform lacks one (SIGHUP on Windows), it is left out.
STOP_SIGNALS: tuple[signal.Signals, ...] = tuple(
    getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name))


class Stopped(Exception):
    """A stop signal reached a safe point (an ``Exception``, so cleanup code in libraries runs as usual)."""

    def __init__(self, signum: int = signal.SIGINT):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


class Interrupted(KeyboardInterrupt):
    """The run stopped on a signal (``signum``): after saving a checkpoint, or at once on a second signal.

    A ``KeyboardInterrupt``, as a Ctrl-C has always been; ``exit_status`` is the shell's convention for a
    process ended by that signal (128 + its number: 130 for SIGINT, 143 for SIGTERM, 129 for SIGHUP).
    """

    def __init__(self, signum: int = signal.SIGINT):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum

    @property
    def exit_status(self) -> int:
        return 128 + int(self.signum)


class DeferredInterrupt:
    """While active (main thread only), a stop signal sets a flag that ``check`` turns into ``Stopped``.

    The signals are ``STOP_SIGNALS``: Ctrl-C (SIGINT), SIGTERM (what schedulers and ``timeout`` send
    before they kill) and SIGHUP, each handled as Ctrl-C always was. A ``KeyboardInterrupt`` raised
    wherever the learner happens to be can land inside an optimiser step or inside a library's context
    manager (tensordict's ``to_module`` turns it into an unrelated ``RuntimeError``), and the state it
    leaves is not one to checkpoint. The loop calls ``check`` where its state is whole. A second
    signal raises ``Interrupted`` at once. ``immediate``: the first signal raises it too (where nothing
    needs a safe point: a parent waiting on child processes, such as ``rlpipe bench time-to-return``).
    """

    def __init__(self, signals: tuple[int, ...] = STOP_SIGNALS, *, immediate: bool = False):
        self.signals = tuple(signals)
        self.immediate = immediate
        self.requested = False
        self.signum: int | None = None
        self._first = 0.0
        self._previous: dict[int, object] = {}

    def __enter__(self) -> DeferredInterrupt:
        if threading.current_thread() is not threading.main_thread():
            return self
        for signum in self.signals:
            # A process started with a signal ignored (nohup ignores SIGHUP; a background job,
            # SIGINT) is meant to be immune to it, as Python itself leaves it then: keep it so.
            if signal.getsignal(signum) is not signal.SIG_IGN:
                self._previous[signum] = signal.signal(signum, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        for signum, previous in self._previous.items():
            # None: the handler was not set from Python; the default one is the closest to it
            if previous is None:
                previous = signal.default_int_handler if signum == signal.SIGINT else signal.SIG_DFL
            # in a program that holds its stops to the exit (the rlpipe command), a stop once taken is its answer
            # to every later one: the default action would end it by the signal, a KeyboardInterrupt in any code
            signal.signal(signum, _latch if _held["on"] and _held["first"] is not None else previous)
        self._previous = {}

    # A second signal this soon after the first is the same stop delivered twice (the terminal's to
    # the process group, and a parent's such as `rlpipe ablate` forwarding it), not a second press.
    SAME_PRESS_S = 2.0

    def _handle(self, signum, frame) -> None:
        seen, _held["first"] = _held["first"], _held["first"] or signum
        if self.immediate:
            if _held["on"] and seen is not None:
                return  # the program answers its first stop already (hold_stops_to_exit)
            raise Interrupted(signum)
        if self.requested:
            if time.monotonic() - self._first < self.SAME_PRESS_S:
                return
            raise Interrupted(signum)
        self.requested, self.signum = True, signum
        self._first = time.monotonic()
        what = "Ctrl-C" if signum == signal.SIGINT else signal.Signals(signum).name
        # said where it can be: the same Ctrl-C may have ended the `tee` reading stderr, and a closed terminal
        # sent the SIGHUP (an error raised here would surface wherever the learner is, not at a safe point)
        say(f"\nrlpipe: {what}: stopping at the next safe point to save a checkpoint ({what} again: stop now, unsaved)")

    def check(self) -> None:
        if self.requested:
            raise Stopped(self.signum)


# --- a program's stops, held to its exit ----------------------------------------------------------------------

# The first stop signal the process took ("first"), one taken once its command had returned ("late"), the status
# the command returned, and whether the program holds its stops to the exit ("on": hold_stops_to_exit).
_held: dict[str, Any] = {"on": False, "first": None, "late": None, "returned": None}


def _latch(signum, frame) -> None:
    """A stop signal after the one the program answers: noted, nothing else (see ``hold_stops_to_exit``)."""
    if _held["first"] is None:
        _held["first"] = signum
    if _held["returned"] is not None and _held["late"] is None:
        _held["late"] = signum


def _signal_name(signum: int) -> str:
    return "Ctrl-C" if signum == signal.SIGINT else signal.Signals(signum).name


def hold_stops_to_exit() -> None:
    """For a program (the ``rlpipe`` command, not a library call): any number of stop signals end it as the first
    one asked, with one line and the status 128 + its number (130 Ctrl-C, 143 SIGTERM, 129 SIGHUP), never by the
    signal's default action or a ``KeyboardInterrupt`` raised in code that does not expect one (a library's
    exit hook). ``DeferredInterrupt`` answers the first; from then on later ones are noted (``_latch``);
    ``command_returned`` gives the status; a stop during the interpreter's exit is answered by the exit hook
    registered here (first, so it runs after every other)."""
    import atexit

    _held["on"] = True
    atexit.register(_exit_as_signalled)
    for signum in STOP_SIGNALS:  # outside a run's DeferredInterrupt: the first raises, as Ctrl-C always did
        if signal.getsignal(signum) in (signal.SIG_DFL, signal.default_int_handler):
            signal.signal(signum, _first_raises)


def _first_raises(signum, frame) -> None:
    """A stop signal where no run is under way (the command's imports, its work around a run): the first raises
    ``Interrupted`` (a ``KeyboardInterrupt``: Ctrl-C's default), the later ones are noted."""
    if _held["first"] is not None:
        return _latch(signum, frame)
    _held["first"] = signum
    raise Interrupted(signum)


def command_returned(status: int) -> int:
    """The program's exit status once its command returned ``status``; from here on every stop signal is noted,
    not obeyed. A stop taken during a command that went on to finish (it came after the last safe point: the end of
    a run's work) is said, and the status is the signal's."""
    for signum in STOP_SIGNALS:
        if signal.getsignal(signum) is not signal.SIG_IGN:
            signal.signal(signum, _latch)
    first = _held["first"]
    if first is not None and status == 0:
        say(f"rlpipe: {_signal_name(first)} came after the command's work was done: nothing was left to save")
        status = 128 + int(first)
    _held["returned"] = status
    return status


def _exit_as_signalled() -> None:
    late = _held["late"]
    if late is not None and _held["returned"] == 0:
        say(f"rlpipe: {_signal_name(late)} while exiting: the command had finished, nothing was left to save")
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        os._exit(128 + int(late))
    for signum in STOP_SIGNALS:  # the interpreter's last steps: ignored (it restores the default for a Python handler)
        if signal.getsignal(signum) is _latch:
            signal.signal(signum, signal.SIG_IGN)


# --- output that no one may be reading any more ---------------------------------------------------------

# A write to a stream whose other end is gone for good: the pipe's reader ended (`| head -5`, a `tee` ended by
# the same Ctrl-C), the terminal closed (a pseudo-terminal's master side: EIO), the descriptor closed.
_GONE = frozenset({errno.EPIPE, errno.EIO, errno.EBADF, errno.ENXIO, errno.ECONNRESET})


class DroppingStream:
    """A text stream (``sys.stdout``, ``sys.stderr``) whose writes never raise: what the stream under it
    cannot take is dropped.

    A run's output is for a person watching; its files are what it is for. Where the reader of a pipe has gone,
    the terminal has closed or the descriptor was closed, a write raises (``BrokenPipeError``, ``OSError`` EIO or
    EBADF, ``ValueError`` on a closed file) from wherever the run writes: a signal handler, a progress bar's
    update, the live log, the last lines of a finished run. Once the other end is gone for good (``gone``), the
    descriptor is pointed at /dev/null, so that what else writes there (a C library's warning, Python's own
    flush of ``sys.__stdout__`` at exit) goes nowhere too, instead of failing again. A write that fails for
    another reason (a full disk under a redirected file; a signal handler writing while the same stream was
    being written to) drops just that write. Anything else (``fileno``, ``isatty``, ``encoding``) is the
    stream's; ``None`` (a stream Python had no descriptor for) drops everything.
    """

    def __init__(self, stream):
        self.stream = stream
        self.gone = stream is None

    def write(self, text: str) -> int:
        if not self.gone:
            try:
                return self.stream.write(text)
            except (OSError, ValueError, RuntimeError) as exc:  # RuntimeError: a reentrant call (a signal handler)
                self._failed(exc)
        return len(text)

    def writelines(self, lines) -> None:
        for line in lines:
            self.write(line)

    def flush(self) -> None:
        if not self.gone:
            try:
                self.stream.flush()
            except (OSError, ValueError, RuntimeError) as exc:
                self._failed(exc)

    def _failed(self, exc: Exception) -> None:
        if isinstance(exc, ValueError) or getattr(exc, "errno", None) in _GONE:  # ValueError: the file is closed
            self.gone = True
            with contextlib.suppress(Exception):
                fd = self.stream.fileno()
                null = os.open(os.devnull, os.O_WRONLY)
                try:
                    os.dup2(null, fd)
                finally:
                    os.close(null)

    def __getattr__(self, name: str):
        if name == "stream":  # not set yet (a copy being made): not the stream's own attribute either
            raise AttributeError(name)
        return getattr(self.stream, name)


def dropping(stream) -> DroppingStream:
    """``stream`` whose writes never raise (itself where it is already so)."""
    return stream if isinstance(stream, DroppingStream) else DroppingStream(stream)


def say(line: str) -> None:
    """``line`` on stderr, or nowhere where stderr cannot take it (never an error)."""
    stream = dropping(sys.stderr)
    stream.write(line + "\n")
    stream.flush()


@contextlib.contextmanager
def output_dropped_when_gone():
    """``sys.stdout`` and ``sys.stderr`` as ``DroppingStream``s inside (a program's whole run, as ``rlpipe``'s
    commands are): its prints, progress bars and log lines never fail it. Flushed on the way out, so that what
    they still hold cannot fail at the interpreter's exit either."""
    saved = sys.stdout, sys.stderr
    sys.stdout, sys.stderr = dropping(sys.stdout), dropping(sys.stderr)
    try:
        yield
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        sys.stdout, sys.stderr = saved


def open_closed_descriptors() -> None:
    """Open /dev/null on whichever of descriptors 0, 1 and 2 is closed (``rlpipe ... <&- >&- 2>&-``), as daemons
    do: else the next file opened takes its number, and what is written to stderr (a C library's warning, a
    worker's) lands in a checkpoint or a log. Python has set that stream to None; ``DroppingStream`` drops it."""
    for fd in (0, 1, 2):
        try:
            os.fstat(fd)
        except OSError:
            null = os.open(os.devnull, os.O_RDWR)
            if null != fd:
                os.dup2(null, fd)
                os.close(null)


@contextlib.contextmanager
def gc_frozen():
    """Keep Python's cyclic garbage collector off the objects that exist before training.

    Each update makes many short-lived objects, so the collector runs often, and its full
    collections scan every object of torch, TorchRL and the env (~0.1 s each here; ~0.03 s with
    them frozen). Frozen objects are left out of those scans; they are handed back at the end, so
    garbage among them is collected as usual afterwards.
    """
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt parameters (malloc.h)
_kept_freed_memory = False


def keep_freed_memory(mmap_threshold: int = 64 << 20, trim_threshold: int = 256 << 20) -> bool:
    """Ask glibc's allocator to keep freed blocks for reuse instead of handing them back to the OS.

    An update allocates and frees the same tensors again and again; blocks over glibc's mmap
    threshold (128 KiB at first, e.g. [2, 256, 256] activations) go back to the OS when freed,
    and touching them again costs page faults: 60-300 per SAC update here (a VM, where each
    fault is dear), ~0.5 with this. The process then keeps up to ``trim_threshold`` bytes of freed
    memory; blocks over ``mmap_threshold`` (a replay buffer's storage) are still mapped and
    returned one by one. Process-wide and one-way (glibc has no getter to restore); a no-op
    returning False where the C library is not glibc.
    """
    global _kept_freed_memory
    if _kept_freed_memory:
        return True
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    _kept_freed_memory = bool(mallopt(_M_MMAP_THRESHOLD, mmap_threshold) and mallopt(_M_TRIM_THRESHOLD, trim_threshold))
    return _kept_freed_memory


def start_resource_tracker() -> None:
    """Start Python's multiprocessing resource tracker now, deaf to the stop signals, if it does not run yet.

    Whatever first makes a multiprocessing lock or queue starts it (TorchRL's storages do), with the
    signals of that moment: it ignores SIGINT and SIGTERM itself, but SIGHUP to the process group
    kills it, and the tracker relaunched then prints a traceback for each lock the first one
    tracked. Call before anything else makes one (the pipeline does, first thing).
    """
    from multiprocessing import resource_tracker

    with stop_signals_blocked():
        resource_tracker.ensure_running()


WORKER_MODULES = ("rlpipe.pipelines.workers.local", "rlpipe.pipelines.workers.evaluation")
"""What a collector or evaluator process runs (torch, tensordict, TorchRL and gymnasium with them): what the
fork server imports once for all of them."""


def start_fork_server(preload: tuple[str, ...] = WORKER_MODULES) -> None:
    """Start the run's worker processes from now on as forks of one server process, started now with
    ``preload`` imported in it, deaf to the stop signals (multiprocessing's ``forkserver`` start method).

    Why: TorchRL starts its collector processes with ``spawn``, a fresh interpreter each that imports torch,
    tensordict, TorchRL and rlpipe again before its first env step: 4.0-4.3 s for the collector process of
    ``rlpipe train sac env=Pendulum-v1`` (from the start asked to its first block, on a 2-core machine;
    BENCHMARKS.md, "The fixed cost of a run, per part"), each time a worker starts or restarts. Forked from a server that
    has them imported, 0.5-0.7 s; the whole one-iteration run ends in 11.1-12.5 s instead of 17.2-17.8. And the
    server's own imports run beside the learner's start-up (the pipeline built, the random baseline), not
    before the first worker. Workers inherit the server's blocked stop signals (``stop_signals_blocked``), as
    spawned ones inherit the learner's; the server ends when this process does.

    Process-wide (it sets multiprocessing's start method): for a program's entry point, as ``rlpipe train``
    calls it, not for a library call; a user's program may call it first thing too. Python's default
    ``fork`` is not used: the learner has threads (torch's, the evaluator's), and a forked copy of their locks
    can hang the child.
    """
    import multiprocessing

    if "forkserver" not in multiprocessing.get_all_start_methods():  # Windows: workers spawn, as TorchRL's
        return
    from multiprocessing import forkserver

    multiprocessing.set_start_method("forkserver", force=True)  # TorchRL set "spawn" at its import
    multiprocessing.set_forkserver_preload(list(preload))
    # The server starts the resource tracker first if it does not run, and Python's start of the tracker
    # *unblocks* SIGINT and SIGTERM after it (CPython 3.11's resource_tracker.ensure_running): the server
    # would then inherit SIGHUP blocked alone, and a Ctrl-C to the group would end its workers ("collector worker 0
    # died: exited with status 0"; tests/test_resume_exact.py). So the tracker first.
    start_resource_tracker()
    with stop_signals_blocked():  # the server's children inherit its signal mask
        forkserver.ensure_running()


@contextlib.contextmanager
def stop_signals_blocked():
    """Start processes (and threads) with the stop signals blocked, so they reach the learner alone.

    Ctrl-C goes to a terminal's whole process group, and SLURM sends SIGTERM to every process of a
    job: a worker that died of it would look like a lost worker, and the learner would stop with its
    work half-saved. The block is inherited by threads started here and by the processes they spawn
    (the signal mask survives fork and exec); the learner's own signal, if one comes meanwhile, waits
    until the block is lifted. The learner then shuts the workers down itself (SIGKILL where one
    does not stop when asked: a blocked SIGTERM does not stop it).
    """
    if threading.current_thread() is not threading.main_thread() or not hasattr(signal, "pthread_sigmask"):
        yield
        return
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, set(STOP_SIGNALS))
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)
