"""Triggers: what the loop does every so many iterations, after the updates (TF-Agents' triggers).

A trigger has a ``name`` (saved in checkpoints: a run stopped between two triggers of the same
iteration resumes with those it still owes) and an ``interval`` in iterations, and is called with
the running ``Loop``. The built-in ones log, evaluate, export the policy and checkpoint; add your
own by passing them to ``train(triggers=[...])``::

    from rlpipe.pipelines.triggers import IntervalTrigger

    def print_return(loop):
        print(loop.state.iteration, loop.last_return)

    pipeline.train("runs/x", triggers=[IntervalTrigger(1000, print_return, name="print")])
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from rlpipe.pipelines.config import TrainConfig

if TYPE_CHECKING:
    from rlpipe.pipelines.loop import Loop

__all__ = [
    "CheckpointTrigger", "EvalTrigger", "ExportTrigger", "IntervalTrigger", "LogTrigger", "Trigger",
    "crossed", "default_triggers",
]


def crossed(previous: int, now: int, interval: int) -> bool:
    """Whether a multiple of ``interval`` lies in (previous, now]."""
    return interval > 0 and now // interval > previous // interval


class Trigger:
    """Runs every ``interval`` iterations; subclasses set ``name`` and define ``__call__(loop)``.

    ``at_last_iteration=False``: not at the run's last iteration (the loop's end does that work
    itself: the final evaluation, the final checkpoint).
    """

    name: str = ""
    at_last_iteration: bool = True
    crossed_off_first: bool = False
    """True: counted as done before it runs (a checkpoint, which records what is still owed, owes nothing more itself)"""

    def __init__(self, interval: int):
        self.interval = int(interval)

    def due(self, previous: int, now: int, last: int) -> bool:
        """Whether this trigger runs when the run moves from iteration ``previous`` to ``now``."""
        return crossed(previous, now, self.interval) and (self.at_last_iteration or now < last)

    def __call__(self, loop: Loop) -> None:
        raise NotImplementedError


class IntervalTrigger(Trigger):
    """``fn(loop)`` every ``interval`` iterations, under ``name``."""

    def __init__(self, interval: int, fn: Callable[[Loop], None], name: str | None = None):
        super().__init__(interval)
        self.fn = fn
        self.name = name or getattr(fn, "__name__", "trigger")

    def __call__(self, loop: Loop) -> None:
        self.fn(loop)


class LogTrigger(Trigger):
    """A metrics row of losses, speeds, training returns (TF-Agents' StepPerSecondLogTrigger) and the
    workers' state (alive, restarts)."""

    name = "log"

    def __call__(self, loop: Loop) -> None:
        loop.log({**loop.interval_stats.flush(loop.clock), **loop.supervisor.columns()})


class EvalTrigger(Trigger):
    """An evaluation of the deterministic policy (the last iteration's one runs after the loop)."""

    name = "eval"
    at_last_iteration = False

    def __call__(self, loop: Loop) -> None:
        loop.evaluate()


class ExportTrigger(Trigger):
    """The deterministic policy exported to ``RUN/policy`` (TF-Agents' PolicySavedModelTrigger)."""

    name = "export"

    def __call__(self, loop: Loop) -> None:
        loop.export()


class CheckpointTrigger(Trigger):
    """A checkpoint that ``--resume`` continues from (the last one is saved after the loop)."""

    name = "save"
    at_last_iteration = False
    crossed_off_first = True

    def __call__(self, loop: Loop) -> None:
        loop.save()


def default_triggers(cfg: TrainConfig) -> list[Trigger]:
    """The tutorials' triggers, in the order they run within an iteration."""
    return [
        LogTrigger(cfg.log_interval),
        EvalTrigger(cfg.eval_interval),
        ExportTrigger(cfg.policy_save_interval),
        CheckpointTrigger(cfg.checkpoint_interval),
    ]
