"""Supervision of a run's workers: the collector backend's (processes or Ray actors) and the background
evaluator. A worker that dies, or a wait on one that runs past its time, is a ``WorkerFailure``; the
``Supervisor`` counts it against ``collector.max_restarts`` and the part is started again, with the
learner's current weights and a seed stream of its own. Past the budget, ``NoRestartLeft``: the loop
saves a checkpoint and the run stops with one line.

Why this is ours: TorchRL 0.14's multi-process collectors notice a dead worker only inside their
iterator, where they terminate the others and then ``close()`` them 0.1 s later (a
``ValueError: Cannot close a process while it is still running`` when one is slower to go); their
weight push waits for each worker's acknowledgement with no timeout (``_wait_for_ack``), so a push
to a dead worker blocks for good; and a worker that hangs is waited for forever (``MAX_IDLE_COUNT``
is unbounded by default). Nothing there restarts a worker. So: the weight-sync schemes below wait
with a deadline and a liveness check (the patched wait is ``compat.torchrl.AckDeadline``), a
``Watchdog`` puts a deadline on every other wait by killing the workers waited on (TorchRL then sees
them dead within its 1 s poll), and ``SupervisedCollector`` tears a failed collector down and starts
another. ``SupervisedCollector`` knows a collector only as a ``backend.CollectorBackend`` (local
processes or Ray actors alike): its blocks, ``push_weights``, ``health`` (which workers live, which
died and why), ``kill`` and ``close``.
"""

from __future__ import annotations

import contextlib
import signal
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any

import psutil
from tensordict import TensorDictBase
from torchrl.weight_update import SharedMemWeightSyncScheme

from rlpipe.pipelines.compat.torchrl import AckDeadline, close_weight_sync_queues
from rlpipe.pipelines.system.runtime import say

if TYPE_CHECKING:
    from rlpipe.pipelines.workers.backend import CollectorBackend

__all__ = [
    "MIN_START_TIMEOUT_S", "NoRestartLeft", "Supervisor", "SupervisedCollector", "close_weight_sync_queues",
    "TimedSharedMemScheme", "Watchdog", "WorkerFailure", "dead_worker", "describe_exit",
    "first_line", "is_running", "kill_new_children", "kill_processes", "start_timeout",
]

MIN_START_TIMEOUT_S = 300.0
"""starting workers (each imports torch and TorchRL and makes its env; a Ray actor is placed by Ray first)
takes a minute on a loaded 2-core machine: every start-up wait, of a process or a Ray actor, waits at
least this long, however short ``collector.timeout`` is"""


def start_timeout(timeout: float) -> float:
    """The seconds a start-up of workers may take, for a run whose other waits take ``timeout``."""
    return max(float(timeout), MIN_START_TIMEOUT_S)


def first_line(exc: BaseException) -> str:
    """An error's first line (200 characters at most), or its type's name: for one-line messages."""
    text = str(exc).strip()
    return text.splitlines()[0][:200] if text else type(exc).__name__


class WorkerFailure(RuntimeError):
    """A worker of ``role`` ("collector", "evaluator") died, or did not answer in time: restart it
    (``Supervisor.failed`` counts it, or raises ``NoRestartLeft``)."""

    def __init__(self, role: str, message: str):
        super().__init__(message)
        self.role = role


class NoRestartLeft(RuntimeError):
    """A worker failed with no restart left: the run saved a checkpoint and stopped.

    ``exit_status`` 75 is sysexits' EX_TEMPFAIL ("try again later"): the run can be resumed.
    """

    exit_status = 75

    def __init__(self, message: str):
        super().__init__(message)
        self.saved_at: int | None = None  # the iteration of the checkpoint saved on the way out

    def __str__(self) -> str:
        saved = "" if self.saved_at is None else f"; checkpoint saved at iteration {self.saved_at}"
        return super().__str__() + saved


# --- processes --------------------------------------------------------------------------------------------


def describe_exit(exitcode: int | None) -> str:
    if exitcode is None:
        return "gone"
    if exitcode < 0:
        try:
            return f"killed by {signal.Signals(-exitcode).name}"
        except ValueError:
            return f"killed by signal {-exitcode}"
    return f"exited with status {exitcode}"


def is_running(proc) -> bool:
    # A process object TorchRL has already closed (after terminating it) counts as dead.
    if getattr(proc, "_closed", False):
        return False
    try:
        return proc.is_alive()
    except ValueError:
        return False


def dead_worker(role: str, procs) -> WorkerFailure | None:
    """The first of ``procs`` that is no longer running, as a failure; None if all are."""
    for i, proc in enumerate(procs):
        if not is_running(proc):
            pid = getattr(proc, "pid", None)
            code = None if getattr(proc, "_closed", False) else proc.exitcode
            return WorkerFailure(role, f"{role} worker {i} (pid {pid}) died: {describe_exit(code)}")
    return None


def kill_processes(procs, timeout: float = 5.0) -> None:
    """SIGKILL each of ``procs`` still running and reap it (at most ``timeout`` seconds in all).

    SIGKILL, not SIGTERM: workers start with the stop signals blocked (``runtime.stop_signals_blocked``),
    and a worker being replaced has nothing to save.
    """
    deadline = time.monotonic() + timeout
    for proc in procs:
        if is_running(proc):
            with contextlib.suppress(OSError, ValueError, AttributeError):
                proc.kill()
    for proc in procs:
        if not getattr(proc, "_closed", False):
            with contextlib.suppress(OSError, ValueError, AssertionError):
                proc.join(timeout=max(0.0, deadline - time.monotonic()))


# --- a deadline on TorchRL's waits -------------------------------------------------------------------------


class _SupervisedAcks(AckDeadline):
    """The acknowledgement deadline (``compat.torchrl.AckDeadline``) with this module's failures: a worker
    found dead between reads (``context.procs[i]``, the collector the scheme serves) or a missed deadline
    is a ``WorkerFailure``."""

    role = "collector"

    def worker_failure(self, worker: int) -> WorkerFailure | None:
        procs = getattr(self.context, "procs", None) or []
        return dead_worker(self.role, procs[worker:worker + 1]) if worker < len(procs) else None

    def ack_timed_out(self, worker: int) -> WorkerFailure:
        return WorkerFailure(self.role, f"{self.role} worker {worker} did not take new weights within "
                                        f"{self.ack_timeout:g} s")


class TimedSharedMemScheme(_SupervisedAcks, SharedMemWeightSyncScheme):
    """TorchRL's weight sync for multi-process collectors (shared memory), with a deadline on its acks."""

    def __init__(self, ack_timeout: float, role: str = "collector", **kwargs):
        super().__init__(**kwargs)
        self.ack_timeout, self.role = float(ack_timeout), role


class Watchdog:
    """Runs an action if a wait outlives its deadline: ``with watchdog.limit(s, action): wait()``.

    One thread for the run (arming and disarming cost a lock each, not a thread per wait). The action
    runs in the watchdog's thread and must make the wait end: here it kills the processes waited on,
    which TorchRL's own loops notice within a second.
    """

    def __init__(self):
        self._cond = threading.Condition()
        self._deadline: float | None = None
        self._action: Callable[[], None] | None = None
        self._closed = False
        self._wakes_at = float("inf")  # when the thread wakes next by itself
        self.expired = 0
        self._thread = threading.Thread(target=self._watch, name="rlpipe-watchdog", daemon=True)
        self._thread.start()

    @contextlib.contextmanager
    def limit(self, seconds: float, action: Callable[[], None]):
        with self._cond:
            # A deadline past the thread's next wake-up needs no notify: it re-reads the deadline
            # when it wakes. (A wake-up per block would be a context switch per block.)
            self._deadline, self._action = time.monotonic() + seconds, action
            if self._deadline < self._wakes_at:
                self._cond.notify()
        try:
            yield
        finally:
            with self._cond:
                self._deadline = self._action = None

    def _watch(self) -> None:
        with self._cond:
            while not self._closed:
                if self._deadline is None:
                    self._wakes_at = float("inf")
                    self._cond.wait()
                    continue
                left = self._deadline - time.monotonic()
                if left > 0:
                    self._wakes_at = self._deadline
                    self._cond.wait(left)
                    continue
                action, self._deadline, self._action = self._action, None, None
                self.expired += 1
                if action is not None:
                    action()

    def close(self, timeout: float = 5.0) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify()
        self._thread.join(timeout)


# --- the supervisor ---------------------------------------------------------------------------------------


class Supervisor:
    """What the run's workers are doing: alive counts per role, restarts made, the restart budget.

    ``max_restarts`` applies to each role (the collector, the evaluator) over this session of the run
    (a resumed run starts a new count). Parts report into it: ``report(role, alive, total)`` as they
    see their workers, ``failed(role, failure)`` when one fails; ``failed`` raises ``NoRestartLeft``
    when no restart is left.
    """

    ROLES = ("collector", "evaluator")

    def __init__(self, max_restarts: int, timeout: float, *, log: Callable[[str], None] | None = None):
        self.max_restarts, self.timeout = int(max_restarts), float(timeout)
        self.start_timeout = start_timeout(self.timeout)
        self.restarts: Counter[str] = Counter()
        self.alive: dict[str, tuple[int, int]] = {}
        self._log = log or say  # dropped where stderr cannot take it (its reader gone): the run goes on

    def report(self, role: str, alive: int, total: int) -> None:
        self.alive[role] = (alive, total)

    def failed(self, role: str, failure: Exception) -> None:
        """Count a failure of ``role``'s workers; ``NoRestartLeft`` if it has no restart left."""
        if self.restarts[role] >= self.max_restarts:
            spent = f"{self.restarts[role]} restart{'s' * (self.restarts[role] != 1)}"
            raise NoRestartLeft(f"{failure}; no restart left ({spent} made, collector.max_restarts="
                              f"{self.max_restarts})") from failure
        self.restarts[role] += 1
        self._log(f"rlpipe: {failure}; restarting the {role} "
                  f"(restart {self.restarts[role]} of {self.max_restarts})")

    def columns(self) -> dict[str, Any]:
        """Metrics columns: collector workers alive, restarts of each role (blank where none is watched)."""
        row: dict[str, Any] = {f"{role}_restarts": self.restarts[role] for role in self.ROLES if role in self.alive}
        if "collector" in self.alive:
            row["workers_alive"] = self.alive["collector"][0]
        return row


# --- the collector, restarted when it fails ---------------------------------------------------------------


class SupervisedCollector:
    """Blocks of env steps from a collector backend that is started again when one of its workers fails.

    ``make(restarts)`` makes a started, seeded ``backend.CollectorBackend`` (called again after each
    failure: the frame budget and seed it gets are the caller's business). A failure seen anywhere (a
    dead worker, a weight push or a block not back in ``supervisor.timeout`` seconds) closes the whole
    backend and makes a new one: TorchRL's multi-process collectors share one output queue and one
    control flow between their workers, and a worker killed while writing may leave that queue
    unusable, so one worker is never replaced alone. Blocks already handed out are the caller's (in
    its replay buffer); the new backend starts from the learner's weights as they are.
    """

    role = "collector"

    def __init__(self, make: Callable[[int], CollectorBackend], supervisor: Supervisor, watchdog: Watchdog):
        self._make, self.supervisor, self.watchdog = make, supervisor, watchdog
        self.collector: CollectorBackend | None = None
        self._failure: WorkerFailure | None = None
        self._timed_out: str | None = None

    def pids(self) -> list[int]:
        """The live workers' processes (none while the backend is replaced)."""
        return [] if self.collector is None else list(self.collector.health().pids)

    def __iter__(self) -> Iterator[TensorDictBase]:
        while True:
            self._start()
            try:
                yield from self._blocks()
                return
            except WorkerFailure as failure:
                self._stop()  # first: the failure line comes once the old workers are gone
                self.supervisor.failed(self.role, failure)
            finally:
                self._stop()

    def push_weights(self) -> None:
        """The backend's ``push_weights`` within the deadline; a failure is kept for the next block to act on."""
        if self.collector is None or self._failure is not None:
            return
        try:
            with self.watchdog.limit(self.supervisor.timeout + 5.0, self._kill_on_timeout("a weight push")):
                self.collector.push_weights()
        except WorkerFailure as failure:
            self._failure = failure

    def close(self) -> None:
        self._stop()

    @property
    def failed(self) -> bool:
        """Whether the backend collecting now has failed (a lost worker, a wait past its deadline)."""
        return self._failure is not None or self._timed_out is not None

    # --- inside ---------------------------------------------------------------------------------------

    def _start(self) -> None:
        self._failure = self._timed_out = None
        restarts = self.supervisor.restarts[self.role]
        try:
            with self.watchdog.limit(self.supervisor.start_timeout, kill_new_children()):
                self.collector = self._make(restarts)
        except (RuntimeError, ValueError, EOFError, OSError) as exc:
            if restarts == 0:
                raise  # the first start failing is a bad env or policy, not a lost worker
            self.supervisor.failed(self.role, WorkerFailure(self.role, f"the {self.role} did not start again: {exc}"))
            self._start()
            return
        self._report()

    def _blocks(self) -> Iterator[TensorDictBase]:
        iterator = iter(self.collector)
        while True:
            if self._failure is not None:
                raise self._failure
            with self.watchdog.limit(self.supervisor.timeout, self._kill_on_timeout("a block of env steps")):
                try:
                    batch = next(iterator)
                except StopIteration:
                    return
                except (RuntimeError, ValueError, EOFError, OSError) as exc:
                    # a worker lost (the backend's WorkerFailure), or killed by the watchdog: say so
                    failure = self._timeout_failure()
                    if failure is None:
                        raise
                    raise failure from exc
            self._report()
            yield batch

    def _report(self) -> None:
        health = self.collector.health()
        if health.total:  # none for in-process collection: nothing to watch, nothing to report
            self.supervisor.report(self.role, health.alive, health.total)

    def _kill_on_timeout(self, what: str) -> Callable[[], None]:
        collector = self.collector

        def expire():
            self._timed_out = f"{self.role}: {what} was not back within {self.supervisor.timeout:g} s"
            collector.kill()  # the wait on its workers then ends within ~1 s
        return expire

    def _timeout_failure(self) -> WorkerFailure | None:
        return None if self._timed_out is None else WorkerFailure(self.role, self._timed_out)

    def _stop(self) -> None:
        collector, self.collector = self.collector, None
        if collector is None:
            return
        if self._failure is not None or self._timed_out is not None:
            collector.kill()  # a failed backend's workers: nothing to wait for
        collector.close()


def kill_new_children() -> Callable[[], None]:
    """An action killing the child processes started from now on (a collector's workers, while its
    constructor waits for them: TorchRL 0.14 reads their first message with no timeout)."""
    me = psutil.Process()
    before = {p.pid for p in me.children(recursive=True)}

    def helper(child) -> bool:  # multiprocessing's, this process's own: its resource tracker, its fork server
        cmdline = " ".join(_cmdline(child))
        return "resource_tracker" in cmdline or ("multiprocessing.forkserver" in cmdline and child.ppid() == me.pid)

    def expire():
        # recursive: workers started from a fork server (runtime.start_fork_server) are its children
        for child in me.children(recursive=True):
            with contextlib.suppress(psutil.Error):
                if child.pid not in before and not helper(child):
                    child.kill()
    return expire


def _cmdline(proc) -> list[str]:
    try:
        return proc.cmdline()
    except psutil.Error:
        return []
