"""Samples-per-insert control: Reverb's ``SampleToInsertRatio`` for TorchRL collectors.

TorchRL 0.14 has no rate limiter between a collector and a replay buffer, so this is ours. The
loop inserts each collected block, asks ``insert`` how many updates are owed, and makes them all
(reporting each with ``made``) before it takes the next block. TorchRL's multi-process collectors keep at most one
block per worker in flight (a worker starts its next block when the learner takes the last one),
so whatever the relative speeds, a fast learner waits for data and a fast collector waits for
the learner: updates per inserted frame stay at ``updates_per_frame`` to within one block.
"""

from __future__ import annotations

__all__ = ["SampleToInsertRatio"]


class SampleToInsertRatio:
    """Owes ``updates_per_frame`` updates for every frame inserted after the first ``min_frames``."""

    def __init__(self, updates_per_frame: float, min_frames: int = 0):
        if updates_per_frame <= 0:
            raise ValueError(f"updates_per_frame={updates_per_frame}: expected a positive ratio")
        self.updates_per_frame = updates_per_frame
        self.min_frames = min_frames
        self.frames = 0
        self.updates = 0
        self._credit = 0.0

    def insert(self, frames: int) -> int:
        """Record ``frames`` new frames; return how many updates are owed now (``owed``)."""
        before, self.frames = self.frames, self.frames + frames
        self._credit += self.updates_per_frame * max(0, self.frames - max(before, self.min_frames))
        return self.owed

    @property
    def owed(self) -> int:
        """Updates owed and not yet made."""
        return int(self._credit + 1e-9)

    def made(self, updates: int = 1) -> None:
        """Count ``updates`` as made; the state stays exact if the loop stops between updates."""
        self._credit -= updates
        self.updates += updates

    @property
    def ratio(self) -> float:
        """Updates made per frame inserted past ``min_frames`` so far."""
        return self.updates / max(1, self.frames - self.min_frames)

    def state_dict(self) -> dict:
        return {"frames": self.frames, "updates": self.updates, "credit": self._credit}

    def load_state_dict(self, state: dict) -> None:
        self.frames, self.updates, self._credit = int(state["frames"]), int(state["updates"]), float(state["credit"])
