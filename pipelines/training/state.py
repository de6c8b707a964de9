"""Where a run is: its counters, the work its current iteration still owes, and its rate limiter.

Every checkpoint holds this state, so that ``--resume`` continues from the exact point where a run
stopped: the updates a collected block paid for and not yet made, the triggers not yet run at
that iteration, the background evaluations asked for and not yet back (with their weights).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any

from tensordict import TensorDict, TensorDictBase

from rlpipe.pipelines.config import TrainConfig
from rlpipe.pipelines.training.rate_limiter import SampleToInsertRatio

__all__ = ["EVAL", "EXPORT", "LOG", "SAVE", "TARGET", "VIDEO", "RunState"]

# The built-in triggers' names. Checkpoints record the triggers an iteration still owes by name
# (``counters.triggers``): these names are part of the checkpoint format, and never change.
LOG = "log"
EVAL = "eval"
EXPORT = "export"
SAVE = "save"
VIDEO = "video"
TARGET = "target"


@dataclass
class RunState:
    """Counters (``frames`` collected, ``updates`` made, ``iteration``: the frames' iteration) and
    what is owed at that iteration."""

    limiter: SampleToInsertRatio
    frames: int = 0
    updates: int = 0
    iteration: int = 0
    episodes: int = 0
    """training episodes finished (TF-Agents' NumberOfEpisodes)"""
    owed: list[str] = field(default_factory=list)
    """names of the triggers still to run at ``iteration``, in order"""
    pending_evals: deque[tuple[dict, TensorDictBase]] = field(default_factory=deque)
    """background evaluations asked for and not back yet: (position, policy weights), oldest first"""
    wall_time_s: float = 0.0
    """the run's wall time when this state was saved (all its stretches so far): a resumed run adds to it"""
    train_time_s: float = 0.0
    """the run's training time (evaluations and saving left out) when this state was saved"""
    envs: dict[str, Any] | None = None
    """the collector's envs between two blocks (``CollectorBackend.snapshot``), for the next collector to go
    on from; None: it starts new episodes (a run's first start, asynchronous collection)"""
    interval: dict[str, Any] | None = None
    """the log interval's losses and episodes so far (``meters.IntervalStats.state_dict``)"""
    workers: dict[str, Any] | None = None
    """the workers alive per role as last seen (``Supervisor.alive``): the rows a resumed run writes before
    its workers start report them as the uninterrupted run's do"""
    backend_metrics: dict[str, Any] | None = None
    """what the collector backend's ``metrics`` had gathered (``metrics_state``), for its next row"""
    inexact: str | None = None
    """why the run can no longer equal an uninterrupted one of its seed (None: it still does)"""
    traj_offset: int = 0
    """added to the current collector's trajectory ids (``("collector", "traj_ids")``): a collector made without
    its predecessor's envs (a restart, an asynchronous resume) numbers its trajectories from 0 again, and stored
    ids must not repeat (a ``SliceSampler`` on them would join two episodes into one)"""
    traj_next: int = 0
    """one above the largest trajectory id the replay buffer was given (offset included): the next fresh
    collector's offset"""
    arithmetic: dict[str, Any] | None = None
    """what besides the config decides the run's floats (``arithmetic.arithmetic_record``), as the stretch that
    saved this state computed them; a resume compares its own with it"""
    config_changes: list[dict[str, Any]] = field(default_factory=list)
    """the config keys a resume changed: ``{"iteration": N, "changed": {key: [before, after]}}``, oldest first"""
    best: dict[str, Any] | None = None
    """the best greedy evaluation so far: ``{"at": position, "return": mean return, "weights": the policy's weights
    (``keep_best``; else None)}``; a later one replaces it only by a higher return"""

    @classmethod
    def fresh(cls, cfg: TrainConfig) -> RunState:
        return cls(limiter=SampleToInsertRatio(1.0 / cfg.collect_steps_per_iteration, cfg.first_update_frame))

    def position(self) -> dict[str, int]:
        """Where the run is, as the first columns of a metrics row."""
        return {"step": self.iteration, "frames": self.frames, "updates": self.updates}

    def insert(self, frames: int, cfg: TrainConfig) -> tuple[int, int]:
        """Count ``frames`` new frames; return the iterations ``(before, now)``."""
        self.frames += frames
        self.limiter.insert(frames)
        before = self.iteration
        self.iteration = max(0, self.frames - cfg.initial_collect_steps) // cfg.collect_steps_per_iteration
        return before, self.iteration

    def not_exact(self, why: str) -> None:
        """Record (once: the first reason) that the run no longer equals an uninterrupted one (``inexact``)."""
        if self.inexact is None:
            self.inexact = why

    def updated(self) -> int:
        """Count one update made; return its number (1, 2, ...)."""
        self.updates += 1
        self.limiter.made(1)
        return self.updates

    def forget_done(self, rows: list[dict[str, str]]) -> None:
        """On resume: drop owed work whose metrics rows were written after the checkpoint was saved."""
        logged = {int(r["step"]) for r in rows if r.get("steps_per_s") not in ("", None)}
        evaluated = {int(r["step"]) for r in rows if r.get("average_return") not in ("", None)}
        if LOG in self.owed and self.iteration in logged:
            self.owed.remove(LOG)
        if EVAL in self.owed and self.iteration in evaluated:
            self.owed.remove(EVAL)
        self.pending_evals = deque((at, w) for at, w in self.pending_evals if at["step"] not in evaluated)

    # --- in checkpoints (the keys of rlpipe-checkpoint/1) -----------------------------------------

    def state_dict(self) -> dict[str, Any]:
        return {
            "counters": {"frames": self.frames, "updates": self.updates, "iteration": self.iteration,
                         "episodes": self.episodes, "triggers": list(self.owed),
                         "wall_time_s": self.wall_time_s, "train_time_s": self.train_time_s},
            "limiter": self.limiter.state_dict(),
            "trajectories": {"offset": self.traj_offset, "next": self.traj_next},
            "background_evals": [{"at": dict(at), "weights": dict(w.flatten_keys("/").items())}
                                 for at, w in self.pending_evals],
            **({"envs": self.envs} if self.envs is not None else {}),
            **({"inexact": self.inexact} if self.inexact is not None else {}),
            **({"arithmetic": self.arithmetic} if self.arithmetic is not None else {}),
            **({"config_changes": self.config_changes} if self.config_changes else {}),
            **({"best": _best_state(self.best)} if self.best is not None else {}),
            **({"interval": self.interval} if self.interval is not None else {}),
            **({"workers": self.workers} if self.workers is not None else {}),
            **({"backend_metrics": self.backend_metrics} if self.backend_metrics is not None else {}),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        counters = state["counters"]
        self.frames, self.updates, self.iteration = (int(counters[k]) for k in ("frames", "updates", "iteration"))
        self.episodes = int(counters.get("episodes", 0))  # a checkpoint without it: 0
        # a checkpoint without the times: the run's figures count from this stretch
        self.wall_time_s = float(counters.get("wall_time_s", 0.0))
        self.train_time_s = float(counters.get("train_time_s", 0.0))
        self.owed = list(counters.get("triggers", []))
        self.limiter.load_state_dict(state["limiter"])
        self.pending_evals = deque((dict(e["at"]), TensorDict(e["weights"]).unflatten_keys("/"))
                                   for e in state.get("background_evals", []))
        self.envs = state.get("envs")  # a checkpoint without envs: None, new episodes
        self.inexact = state.get("inexact")
        self.arithmetic = state.get("arithmetic")  # a checkpoint without it: None (a resume says it is not exact)
        self.config_changes = list(state.get("config_changes", []))
        best = state.get("best")
        self.best = None if best is None else {
            "at": dict(best["at"]), "return": float(best["return"]),
            "weights": None if best.get("weights") is None else TensorDict(best["weights"]).unflatten_keys("/")}
        self.interval = state.get("interval")
        self.workers = state.get("workers")
        self.backend_metrics = state.get("backend_metrics")
        # a checkpoint without trajectories: ids from 0, as its collector numbered them
        trajectories = state.get("trajectories", {})
        self.traj_offset, self.traj_next = int(trajectories.get("offset", 0)), int(trajectories.get("next", 0))


def _best_state(best: dict[str, Any]) -> dict[str, Any]:
    weights = best.get("weights")
    return {"at": dict(best["at"]), "return": best["return"],
            "weights": None if weights is None else dict(weights.flatten_keys("/").items())}
