"""The learner's torch threads: how many this machine and collector layout give it (``num_threads=-1``),
and setting them for the length of a run.

The count decides the float summation order of every matrix product, so it is part of a run's arithmetic:
it comes from a rule over facts that do not move while a machine is busy (its cores, the collector layout,
``OMP_NUM_THREADS``), is written in ``config.json`` and is reused by ``--resume``. No timing decides it.
"""

from __future__ import annotations

import contextlib
import os

import torch

from rlpipe.pipelines.config import TrainConfig, steps_in_learner

__all__ = ["MAX_LEARNER_THREADS", "choose_threads", "cores", "omp_threads", "threads_rule",
           "torch_threads"]

MAX_LEARNER_THREADS = 4
"""the most threads the rule gives a learner: the networks rlpipe trains (two or three layers of 64-256 units,
batches of 256) gain little past that on a CPU"""


def cores() -> int:
    """The cores this process may run on (its CPU affinity, else the machine's count)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def choose_threads(cfg: TrainConfig) -> int:
    """The learner's torch threads for ``cfg`` on this machine (``num_threads=-1``): see ``threads_rule``."""
    return threads_rule(cfg)[0]


def threads_rule(cfg: TrainConfig) -> tuple[int, str]:
    """(the learner's torch threads, one line saying how they were counted) for ``cfg`` on this machine.

    Collector processes each keep a core busy stepping envs, so the learner may use the cores they leave (at
    least one; every core where the env steps in the learner's own process, taking turns with the updates).
    It takes half of those, at most ``MAX_LEARNER_THREADS``: a learner holding every core stalls whenever
    anything else wants one (torch's threads wait on each other at every operation), and on a shared or
    desktop machine something always does. On 2 cores that is one thread: `rlpipe train td3
    collector.sync=true` made 432 updates/s alone on 1 thread and 433 on 2, and beside one busy process 365
    on 1 and 28 on 2 (BENCHMARKS.md, "The learner's threads on a busy machine", `rlpipe bench threads`).
    ``OMP_NUM_THREADS``, where it is set, caps the count: a user (or a test suite, or a study running several
    runs at once) who gave torch that many threads keeps them.
    """
    c = cfg.collector
    have = cores()
    free = max(1, have - (0 if steps_in_learner(c) else c.workers))
    n = max(1, min(MAX_LEARNER_THREADS, free // 2))
    why = f"half the {free} of {have} cores the collectors leave" if free != have else f"half of {have} cores"
    why += f", at most {MAX_LEARNER_THREADS}" if free // 2 > MAX_LEARNER_THREADS else ""
    cap = omp_threads()
    if cap is not None and cap < n:
        n, why = cap, f"OMP_NUM_THREADS={cap}"
    return n, why


def omp_threads() -> int | None:
    """``OMP_NUM_THREADS`` when it is a positive count, else None."""
    try:
        n = int(os.environ.get("OMP_NUM_THREADS", ""))
    except ValueError:
        return None
    return n if n > 0 else None


@contextlib.contextmanager
def torch_threads(n: int):
    """torch's intra-op threads set to ``n`` (0: leave them) while inside, then put back."""
    before = torch.get_num_threads()
    if n:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)
