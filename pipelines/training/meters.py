"""What the loop measures between two log rows: training time, speeds, losses, episode returns and lengths."""

from __future__ import annotations

import contextlib
import time
from typing import Any

import torch
from tensordict import TensorDictBase

__all__ = ["Clock", "IntervalStats"]


class Clock:
    """Wall time, and training time with evaluations and saving taken out (for steps per second), of the
    whole run: a resumed run's clock starts from the times its checkpoint recorded (``wall``, ``train``)."""

    def __init__(self, wall: float = 0.0, train: float = 0.0):
        self._t0 = time.perf_counter()
        self._paused = 0.0
        self._train_start: float | None = None
        self._wall_before, self._train_before = float(wall), float(train)

    def start(self) -> None:
        self._train_start = time.perf_counter()
        self._paused = 0.0

    def wall(self) -> float:
        """Seconds of the whole run: earlier stretches (to their last checkpoint) and this one."""
        return self._wall_before + time.perf_counter() - self._t0

    def train_seconds(self) -> float:
        """Training seconds of the whole run."""
        return self._train_before + self.session_train_seconds()

    def session_train_seconds(self) -> float:
        """Training seconds since this stretch (this process's ``train`` call) started."""
        if self._train_start is None:
            return 0.0
        return time.perf_counter() - self._train_start - self._paused

    @contextlib.contextmanager
    def paused(self):
        """Time spent inside does not count as training time."""
        t = time.perf_counter()
        try:
            yield
        finally:
            if self._train_start is not None:
                self._paused += time.perf_counter() - t


class IntervalStats:
    """Means of losses, finished training episodes' returns and lengths, and speeds since the last log row."""

    def __init__(self):
        self._reset(0.0)

    def state_dict(self) -> dict[str, Any]:
        """The interval's losses and episodes so far (not its speeds): a run stopped mid-interval and
        resumed writes the row an uninterrupted run would."""
        return {"loss_sums": dict(self.loss_sums), "loss_counts": dict(self.loss_counts),
                "episode_returns": torch.tensor(self.episode_returns, dtype=torch.float64),
                "episode_lengths": torch.tensor(self.episode_lengths, dtype=torch.float64)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.loss_sums, self.loss_counts = dict(state["loss_sums"]), dict(state["loss_counts"])
        self.episode_returns = state["episode_returns"].tolist()
        self.episode_lengths = state["episode_lengths"].tolist()

    def _reset(self, t: float) -> None:
        self.loss_sums: dict[str, torch.Tensor] = {}
        self.loss_counts: dict[str, int] = {}
        self.episode_returns: list[float] = []
        self.episode_lengths: list[float] = []
        self.frames = 0
        self.updates = 0
        self.t = t

    def add_frames(self, batch: TensorDictBase) -> int:
        """A collected block, flat; the returns (``RewardSum``'s ``episode_reward``) and lengths
        (``StepCounter``'s ``step_count``, where the env has one) of the episodes it ends; returns
        how many it ends."""
        self.frames += batch.numel()
        done = batch["next", "done"]
        if not done.any():
            return 0
        self.episode_returns += batch["next", "episode_reward"][done].tolist()
        steps = batch.get(("next", "step_count"), None)
        if steps is not None:
            self.episode_lengths += steps[done].tolist()
        return int(done.sum())

    def add_losses(self, losses: dict[str, torch.Tensor]) -> None:
        self.updates += 1
        for k, v in losses.items():  # some losses are not made every update (TD3's delayed actor)
            self.loss_sums[k] = self.loss_sums.get(k, 0.0) + v
            self.loss_counts[k] = self.loss_counts.get(k, 0) + 1

    def flush(self, clock: Clock) -> dict[str, Any]:
        """The row of means and speeds since the last flush; starts the next interval."""
        now = clock.session_train_seconds()
        dt = max(now - self.t, 1e-9)
        row: dict[str, Any] = {f"loss_{k}": float(v) / self.loss_counts[k] for k, v in self.loss_sums.items()}
        if self.episode_returns:
            row["train_episode_return"] = sum(self.episode_returns) / len(self.episode_returns)
        if self.episode_lengths:
            row["train_episode_length"] = sum(self.episode_lengths) / len(self.episode_lengths)
        row["steps_per_s"] = self.frames / dt
        row["updates_per_s"] = self.updates / dt
        row["wall_time"] = clock.wall()
        self._reset(now)
        return row
