"""The training loop's fault points, pressed from outside the loop (``system.faults`` says what a fault is).

``training.run`` adds a ``FaultTrigger`` to a run's triggers only when ``RLPIPE_FAULT`` names one of the loop's
points; the loop itself has no call for them and no branch for tests.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING

import torch
from tensordict import TensorDictBase

from rlpipe.pipelines.system.faults import LOOP_POINTS, fault_point, fault_set
from rlpipe.pipelines.training.triggers import Trigger

if TYPE_CHECKING:
    from rlpipe.pipelines.training.loop import Loop

__all__ = ["FaultTrigger", "fault_triggers"]


class FaultTrigger(Trigger):
    """The loop's fault points, each at iteration (or update) N:

    * ``collected@N``: once the block that brought the run to iteration N is stored, paid for in updates and its
      triggers have run (this trigger's ``poll``, after every other trigger's);
    * ``collector_worker@N``: the same moment, the signal sent to the collector's first worker process;
    * ``update@N:NAN``: right after update N, a parameter of the loss module turned NaN, for the divergence check
      to find (the pipeline's ``update_step`` wrapped from ``start`` to ``close``).
    """

    name = "fault"

    def __init__(self):
        super().__init__(0)

    def due(self, previous: int, now: int, last: int) -> bool:
        return False  # pressed from its hooks alone

    def start(self, loop: Loop) -> None:
        if not fault_set("update"):
            return
        pipeline = loop.pipeline
        update_step, module = pipeline.update_step, pipeline.loss_module

        def poisoned(batch: TensorDictBase, index: int) -> Mapping[str, torch.Tensor]:
            losses = update_step(batch, index)
            if fault_point("update", index):
                next(module.parameters()).data.fill_(math.nan)
            return losses

        self._unwrap = lambda: setattr(pipeline, "update_step", update_step)
        pipeline.update_step = poisoned

    def poll(self, loop: Loop) -> None:
        if loop.finished_early is not None:  # the run ends with this block: no later point to press
            return
        iteration = loop.state.iteration
        fault_point("collected", iteration)
        collection = loop.collection
        fault_point("collector_worker", iteration,
                    worker=lambda: None if collection is None else next(iter(collection.pids()), None))

    def close(self, loop: Loop) -> None:
        unwrap = getattr(self, "_unwrap", None)
        if unwrap is not None:
            unwrap()


def fault_triggers() -> list[Trigger]:
    """``[FaultTrigger()]`` when ``RLPIPE_FAULT`` names a point of the loop, else none."""
    return [FaultTrigger()] if any(fault_set(point) for point in LOOP_POINTS) else []
