"""What a training process needs from the operating system: Ctrl-C at safe points, workers started
deaf to Ctrl-C, Python's garbage collector kept off long-lived objects, and freed memory kept for
reuse.

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

__all__ = ["DeferredInterrupt", "Stopped", "fault_point", "gc_frozen", "keep_freed_memory", "sigint_blocked"]


class Stopped(Exception):
    """Ctrl-C reached a safe point (an ``Exception``, so cleanup code in libraries runs as usual)."""


class DeferredInterrupt:
    """While active (main thread only), Ctrl-C sets a flag that ``check`` turns into ``Stopped``.

    A ``KeyboardInterrupt`` raised wherever the learner happens to be can land inside an optimiser
    step or inside a library's context manager (tensordict's ``to_module`` turns it into an
    unrelated ``RuntimeError``), and the state it leaves is not one to checkpoint. The loop calls
    ``check`` where its state is whole. A second Ctrl-C raises ``KeyboardInterrupt`` at once.
    """

    def __init__(self):
        self.requested = False
        self._first = 0.0
        self._installed = False
        self._previous = None

    def __enter__(self) -> DeferredInterrupt:
        # A process started with SIGINT ignored (nohup, a background job) is meant to be immune to
        # Ctrl-C, as Python itself leaves it then: keep it so.
        if (threading.current_thread() is threading.main_thread()
                and signal.getsignal(signal.SIGINT) is not signal.SIG_IGN):
            self._previous = signal.signal(signal.SIGINT, self._handle)
            self._installed = True
        return self

    def __exit__(self, *exc) -> None:
        if self._installed:
            # None: the handler was not set from Python; the default one is the closest to it
            signal.signal(signal.SIGINT, signal.default_int_handler if self._previous is None else self._previous)
            self._installed = False

    # A second SIGINT this soon after the first is the same Ctrl-C delivered twice (the terminal's to
    # the process group, and a parent's such as `rlpipe ablate` forwarding it), not a second press.
    SAME_PRESS_S = 2.0

    def _handle(self, signum, frame) -> None:
        if self.requested:
            if time.monotonic() - self._first < self.SAME_PRESS_S:
                return
            raise KeyboardInterrupt
        self.requested = True
        self._first = time.monotonic()
        print("\nrlpipe: stopping at the next safe point to save a checkpoint (Ctrl-C again: stop now, unsaved)",
              file=sys.stderr, flush=True)

    def check(self) -> None:
        if self.requested:
            raise Stopped


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


@contextlib.contextmanager
def sigint_blocked():
    """Start processes (and threads) with SIGINT blocked, so a Ctrl-C reaches the learner alone.

    The block is inherited by threads started here and by the processes they spawn (the signal
    mask survives fork and exec); the learner's own SIGINT, if one comes meanwhile, waits until
    the block is lifted. The learner then shuts the workers down itself.
    """
    if threading.current_thread() is not threading.main_thread() or not hasattr(signal, "pthread_sigmask"):
        yield
        return
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


# --- the test hook: a signal at an exact point of a run ------------------------------------------------

# RLPIPE_FAULT="NAME@STEP" (or "NAME@STEP:SIGTERM"): a process reaching point NAME at iteration STEP
# sends the signal (default SIGINT) to its whole process group, as a terminal's Ctrl-C does
# (SIGSTOP holds the run there until the group gets SIGCONT). "NAME@STEP:ENOSPC" (any errno name)
# raises that OSError there instead, as a full disk (or a refused write) would. "NAME@STEP:NAN"
# sends nothing: fault_point returns True and the caller poisons its state (the loop: a parameter
# becomes NaN after update STEP).
# RLPIPE_FAULT_ONCE=PATH: only the first process to get there (it creates PATH and writes its command
# line into it), so a study's other runs reaching the same point later do not press again.
_FAULT = os.environ.get("RLPIPE_FAULT", "")


def fault_point(name: str, step: int) -> bool:
    """Where tests inject a fault (see ``RLPIPE_FAULT`` above); does nothing in normal runs.

    Returns True when the fault is one the caller carries out itself (``:NAN``)."""
    if not _FAULT:
        return False
    point, _, signame = _FAULT.partition(":")
    if point != f"{name}@{step}":
        return False
    marker = os.environ.get("RLPIPE_FAULT_ONCE")
    if marker:
        try:
            fd = os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            return
        with os.fdopen(fd, "w") as fh:
            fh.write(" ".join(sys.argv) + "\n")
    if signame == "NAN":
        return True
    if signame.startswith("E"):
        code = getattr(errno, signame)
        raise OSError(code, os.strerror(code))
    os.killpg(os.getpgrp(), getattr(signal, signame or "SIGINT"))
    return False
