"""The learner's torch threads: how many this machine and collector layout should give it
(``num_threads=-1``), and setting them for the length of a run."""

from __future__ import annotations

import contextlib
import math
import os
import time
from typing import TYPE_CHECKING

import torch
from tensordict import TensorDictBase
from torchrl.objectives import LossModule

from rlpipe.pipelines.config import steps_in_learner

if TYPE_CHECKING:
    from rlpipe.pipelines.base import OffPolicyPipeline

__all__ = ["choose_threads", "loss_pass_seconds", "omp_threads", "torch_threads"]


def choose_threads(pipeline: OffPolicyPipeline) -> int:
    """The learner's torch threads for this machine and ``pipeline``'s collector layout (``num_threads=-1``).

    Collector processes each keep a core busy stepping envs, so the learner gets the cores
    they leave (at least one); within those, the thread count whose forward and backward pass
    of the loss on a replay-sized batch measured fastest (by 10% or more over fewer threads).
    The env steps in the learner's own process (``collector.workers=1``, ``sync=true``) take
    turns with the updates, so there every core is the learner's. ``OMP_NUM_THREADS``, where it is
    set, caps the count: a user (or a test suite, or a study running several runs at once) who gave
    torch that many threads keeps them. (The timing sees the machine for a moment only: a td3 learning
    check that takes ~40 s took 371 s in this project's CI on 2026-11-28, most likely on two threads of a
    2-core machine shared with another test worker.) Parameters, optimisers and
    the run's random state (and the loss's buffers) are left as they were; a loss that cannot run on the env's fake
    batch (a plug-in's own keys) gets one thread.
    """
    c = pipeline.config.collector
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    budget = max(1, cores - (0 if steps_in_learner(c) else c.workers))
    cap = omp_threads()
    if cap is not None:
        budget = min(budget, cap)
    if budget == 1:
        return 1
    candidates = sorted({*(2**k for k in range(budget.bit_length()) if 2**k <= budget), budget})
    batch = pipeline.env.fake_tensordict().reshape(-1)[:1].expand(pipeline.config.batch_size).clone()
    before = torch.get_num_threads()
    timings = {}
    # A forward pass in training mode moves batch-norm statistics (CrossQ's critics): put them back.
    buffers = [(b, b.clone()) for b in pipeline.loss_module.buffers()]
    with torch.random.fork_rng(devices=[]):
        try:
            for n in candidates:
                torch.set_num_threads(n)
                timings[n] = loss_pass_seconds(pipeline.loss_module, batch.to(pipeline.device))
        except Exception:  # the probe only picks a speed; it never stops a run
            return 1
        finally:
            torch.set_num_threads(before)
            pipeline.loss_module.zero_grad(set_to_none=True)
            with torch.no_grad():
                for b, saved in buffers:
                    b.copy_(saved)
    # More threads only for a clear gain (10%): on noise, the count (and its arithmetic) stays put.
    chosen = candidates[0]
    for n in candidates[1:]:
        if timings[n] < 0.9 * timings[chosen]:
            chosen = n
    return chosen


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


def loss_pass_seconds(loss: LossModule, batch: TensorDictBase, repeats: int = 5) -> float:
    """Best time of a forward and backward pass of ``loss`` on ``batch`` (its gradients are left for
    the caller to clear; no optimiser steps, so no parameter changes)."""
    best = math.inf
    for i in range(repeats + 2):
        t0 = time.perf_counter()
        out = loss(batch.clone())
        losses = [v for k, v in out.items() if (k == "loss" or k.startswith("loss_")) and v.requires_grad]
        if losses:
            sum(losses).backward()
        if i >= 2:  # the first passes warm up
            best = min(best, time.perf_counter() - t0)
    return best
