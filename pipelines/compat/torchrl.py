"""Workarounds for TorchRL 0.14 (the floor and the ceiling today: ``torchrl>=0.14,<0.15``).

Each says what 0.14 does, and when it can go. Most reach into TorchRL's private attributes, which is
why they live here, together: an upgrade breaks them here first, and here is where to look.
"""

from __future__ import annotations

import contextlib
import queue
import sys
import time

__all__ = ["COLLECTOR_KWARGS", "AckDeadline", "close_weight_sync_queues", "prompt_block_hand_over",
           "ray_weight_sync_deadline", "set_model_version", "write_cursor"]


class AckDeadline:
    """A mixin for TorchRL's weight-sync schemes (``SharedMemWeightSyncScheme``,
    ``MultiProcessWeightSyncScheme``): their acknowledgements read with a deadline.

    TorchRL 0.14's ``_wait_for_ack`` reads each worker's acknowledgement with no timeout (and ``send``
    passes none): a worker that died holds the learner in that read for good. This reads with a
    deadline, asking ``worker_failure(i)`` between reads whether worker ``i`` is gone; what a dead worker
    or a missed deadline means (an exception to raise) is the subclass's: ``worker_failure`` and
    ``ack_timed_out``. Delete when TorchRL's ``send`` takes a timeout and notices a dead worker
    (not in 0.14; check at each TorchRL upgrade).
    """

    ack_timeout = 60.0
    _POLL_S = 0.2

    def worker_failure(self, worker: int) -> BaseException | None:
        """The exception for worker ``worker`` if it is gone, else None."""
        return None

    def ack_timed_out(self, worker: int) -> BaseException:
        return TimeoutError(f"worker {worker} did not take new weights within {self.ack_timeout:g} s")

    def __del__(self):
        # TorchRL 0.14's __del__ shuts the scheme down, which starts a queue thread: at the interpreter's
        # exit that start waits forever (Python 3.11). The process's end frees what it would.
        if not sys.is_finalizing():
            super().__del__()

    def _wait_for_ack(self, worker_ids=None, timeout=None) -> None:
        if not self._ack_queues:
            return
        if worker_ids is None:
            targets = list(self._ack_queues)
        else:
            targets = [worker_ids] if isinstance(worker_ids, int) else list(worker_ids)
        deadline = time.monotonic() + (self.ack_timeout if timeout is None else timeout)
        for i in targets:
            while True:
                try:
                    self._ack_queues[i].get(timeout=self._POLL_S)
                    break
                except queue.Empty:
                    pass
                failure = self.worker_failure(i)
                if failure is not None:
                    raise failure
                if time.monotonic() > deadline:
                    raise self.ack_timed_out(i)


def close_weight_sync_queues(collector) -> None:
    """Shut a collector's weight-sync schemes down (TorchRL 0.14's collector shutdown leaves them, and
    their ``__del__`` would do it later, perhaps at the interpreter's exit, where starting the queue
    thread it needs hangs). Their queues may have a dead reader: never wait for them to drain.
    Delete when ``collector.shutdown()`` shuts its schemes down (not in 0.14)."""
    for scheme in (getattr(collector, "_weight_sync_schemes", None) or {}).values():
        with contextlib.suppress(Exception):
            for name in ("_weight_init_queues", "_instruction_queues", "_ack_queues"):
                for q in (getattr(scheme, name, None) or {}).values():
                    q.cancel_join_thread()
            scheme.shutdown()


def prompt_block_hand_over() -> None:
    """In a collector worker process: hand each block over as soon as it is collected.

    TorchRL 0.14's worker loop (``collectors/_runner.py``) polls its pipe for ``_MIN_TIMEOUT`` (1 ms)
    after every block before sending it, in case the learner sent a message meanwhile; with no message
    it waits the whole millisecond, every block. For one CartPole env in a worker that is a quarter of a
    50-frame block (~4 ms of stepping). A poll of 0 s sees a message that has arrived as well; one that
    arrives later is read at the top of the loop, after the block is queued (the queue does not block).
    Call it where the worker's collector is built (``WorkerGymCollector``, ``WorkerSnapshotCollector``).
    Delete when TorchRL's wait is configurable or gone (not in 0.14; check at each TorchRL upgrade).
    """
    from torchrl.collectors import _runner

    if getattr(_runner, "_MIN_TIMEOUT", None) is not None:
        _runner._MIN_TIMEOUT = 0.0


def ray_weight_sync_deadline(seconds: float) -> None:
    """In this process, give TorchRL's ``RayWeightSyncScheme`` ``seconds`` to connect its Gloo group (the learner
    and every collector actor) and to finish each weight transfer over it.

    TorchRL 0.14 fixes that deadline at 60 s (``weight_update/_ray.py``'s ``_DIST_TIMEOUT``, read when the learner
    and each actor connect): on a 2-core machine whose cores another job holds, an actor that is still importing
    TorchRL a minute after the learner began to wait ends the run with ``DistStoreError: wait timeout after
    60000ms``, where every other start-up wait of a worker waits at least ``MIN_START_TIMEOUT_S`` (300 s). Call it
    in the learner before the scheme connects and in each actor before its collector does (``WorkerSnapshotCollector``
    takes ``weight_sync_deadline``). Delete when the scheme takes a timeout (not in 0.14; check at each upgrade).
    """
    from datetime import timedelta

    from torchrl.weight_update import _ray

    if not isinstance(getattr(_ray, "_DIST_TIMEOUT", None), timedelta):  # tests/test_compat.py checks it too
        raise RuntimeError("torchrl.weight_update._ray._DIST_TIMEOUT is gone in this TorchRL: adapt "
                           "rlpipe.pipelines.compat.torchrl.ray_weight_sync_deadline to its weight sync's timeout")
    _ray._DIST_TIMEOUT = timedelta(seconds=seconds)


def set_model_version(scheme, version: int) -> None:
    """Stamp the weights a ``RayWeightSyncScheme`` sends next with ``version``. TorchRL 0.14 has no public
    setter; its own Ray trainer (``trainers/_ray_execution.py``) stamps so. Delete when one exists."""
    scheme._set_model_version(version)


def write_cursor(replay_buffer) -> int:
    """Where a full round-robin replay buffer writes next (its oldest item). TorchRL 0.14's
    ``RoundRobinWriter`` has no public getter for it. Delete when it has one."""
    return int(replay_buffer._writer._cursor)


# TorchRL 0.14's collectors leave a user's env without the transforms the policy reads (InitTracker)
# unless asked to append them; 0.15 appends them by default. Delete when torchrl>=0.15 is the floor.
COLLECTOR_KWARGS = {"auto_register_policy_transforms": True}
