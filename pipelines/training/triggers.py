"""Triggers: what the loop does every so many iterations, after the updates (TF-Agents' triggers).

A trigger has a ``name`` (saved in checkpoints: a run stopped between two triggers of the same
iteration resumes with those it still owes) and an ``interval`` in iterations, and is called with
the running ``Loop``. The built-in ones log, evaluate, export the policy and checkpoint; add your
own by passing them to ``train(triggers=[...])``::

    from rlpipe.pipelines.training.triggers import IntervalTrigger

    def print_return(loop):
        print(loop.state.iteration, loop.last_return)

    pipeline.train("runs/x", triggers=[IntervalTrigger(1000, print_return, name="print")])
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from rlpipe.pipelines.config import TrainConfig

if TYPE_CHECKING:
    from rlpipe.pipelines.training.loop import Loop

__all__ = [
    "CheckpointTrigger", "EvalTrigger", "ExportTrigger", "IntervalTrigger", "LogTrigger", "Trigger",
    "crossed", "default_triggers", "eval_line", "log_line",
]

# What a pipeline's update returns besides the terms of its objective (SAC's temperature and policy
# entropy): left out of the total ``loss`` the tutorials print, shown after it.
DIAGNOSTICS = ("alpha_value", "entropy")


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
    """A metrics row of losses, speeds, training episodes' mean return and length, the episodes
    finished so far (TF-Agents' StepPerSecondLogTrigger and train metrics: NumberOfEpisodes,
    AverageReturnMetric, AverageEpisodeLengthMetric) and the workers' state (alive, restarts)."""

    name = "log"

    def __call__(self, loop: Loop) -> None:
        row = {**loop.interval_stats.flush(loop.clock), "episodes": loop.state.episodes, **loop.supervisor.columns()}
        if loop.collector is not None:  # the backend's own figures (Ray: weight versions)
            row.update(loop.collector.metrics())
        loop.log(row)
        if any(k.startswith("loss_") for k in row):  # nothing to say before the first update
            loop.echo(log_line(loop.state.iteration, row))


class EvalTrigger(Trigger):
    """An evaluation of the deterministic policy (the last iteration's one runs after the loop)."""

    name = "eval"
    at_last_iteration = False

    def __call__(self, loop: Loop) -> None:
        loop.evaluate()


class ExportTrigger(Trigger):
    """The deterministic policy exported to ``RUN/policy`` as ``step_NNNNNNN.onnx/.pt2`` and ``policy.onnx/.pt2``
    (TF-Agents' PolicySavedModelTrigger; ``policy_keep`` says how many steps stay)."""

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


# --- the live log: the tutorials' printed lines ------------------------------------------------------


def _num(value: float) -> str:
    return f"{value:.6g}" if math.isfinite(value) else "nan"


def log_line(step: int, row: Mapping[str, Any]) -> str:
    """``step = 200: loss = 0.41, ...``: the tutorials' loss line for a log row.

    ``loss`` is the total the TF-Agents agents report (SAC: actor + critic + alpha losses, TD3: actor
    + critic, DQN: its one loss), each term after it, then the diagnostics and the training episodes'
    mean return.
    """
    terms = {k.removeprefix("loss_"): float(v) for k, v in row.items() if k.startswith("loss_")}
    losses = {k: v for k, v in terms.items() if k not in DIAGNOSTICS}
    parts = [f"loss = {_num(sum(losses.values()))}"]
    if len(losses) > 1:
        parts += [f"{k}_loss = {_num(v)}" for k, v in losses.items()]
    parts += [f"{k} = {_num(v)}" for k, v in terms.items() if k in DIAGNOSTICS]
    if "train_episode_return" in row:
        parts.append(f"train episode return = {_num(float(row['train_episode_return']))}")
    return f"step = {step}: " + ", ".join(parts)


def eval_line(step: int, result: Mapping[str, Any], steps_per_s: float, updates_per_s: float) -> str:
    """``step = 1000: AverageReturn = ..., AverageEpisodeLength = ..., ...``: the tutorials' evaluation line.

    The speeds are training time's (evaluations and saving left out) since this session started.
    """
    return (f"step = {step}: AverageReturn = {result['average_return']:.6f}, "
            f"AverageEpisodeLength = {result['average_episode_length']:.6f}, "
            f"env steps/s = {steps_per_s:.1f}, updates/s = {updates_per_s:.1f}")
