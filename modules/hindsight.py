"""Hindsight Experience Replay (Andrychowicz et al. 2017) over a TorchRL ``ReplayBuffer``: the "future" strategy.

A share (``her_ratio``) of each sampled batch gets, in place of the episode's goal, a goal the same
episode achieved at that step or later, and the reward the env's ``compute_reward`` gives for it, as
SB3's ``HerReplayBuffer`` does (its ``future`` strategy, ``n_sampled_goal=4``: ratio 0.8).

Why not TorchRL's ``HERReplayBuffer``: it finds an episode's later steps by reading the done flags of the
whole storage (rebuilt after every write) and assumes an episode's steps lie side by side in it, which
does not hold when several collector workers' blocks interleave; and it relabels goals held as entries of
their own, while rlpipe's observation is one vector (``rlpipe.envs.observations.DictObservation``). Here
each episode is written whole, side by side (its steps wait in ``pending`` until it ends), with the number
of steps left after each (``("her", "steps_left")``), so a future step's index is ``index + offset``:
no search, whatever the collectors' layout.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import ReplayBuffer

__all__ = ["HindsightReplayBuffer", "STEPS_LEFT", "TRAJ_IDS"]

STEPS_LEFT = ("her", "steps_left")
TRAJ_IDS = ("collector", "traj_ids")


class HindsightReplayBuffer(ReplayBuffer):
    """A TorchRL ``ReplayBuffer`` of whole episodes whose ``sample`` relabels goals ("future" strategy).

    Args:
        compute_reward: the env's ``compute_reward(achieved_goal, desired_goal, info)`` on NumPy batches.
        achieved, desired: ``(start, stop)`` of the achieved and desired goal in the observation vector.
        observation_key: the observation entry (and ``("next", observation_key)``) that holds them.
        her_ratio: share of each batch relabelled.
        max_pending: an episode longer than this is written in pieces of this many steps (futures are
            then drawn within a piece).
        **kwargs: TorchRL ``ReplayBuffer``'s (``storage``, ``batch_size``; the sampler must be uniform and
            the writer round-robin, so that an episode's steps stay side by side).

    ``extend`` takes blocks of transitions with ``("collector", "traj_ids")`` (one id per episode, as
    TorchRL's collectors number them) and ``("next", "done")``.
    """

    def __init__(self, *, compute_reward: Callable, achieved: tuple[int, int], desired: tuple[int, int],
                 observation_key: str = "observation", her_ratio: float = 0.8, max_pending: int = 10_000, **kwargs):
        super().__init__(**kwargs)
        self.compute_reward = compute_reward
        self.achieved, self.desired = slice(*achieved), slice(*desired)
        self.observation_key = observation_key
        self.her_ratio = her_ratio
        self.max_pending = max_pending
        self.pending: dict[int, list[TensorDictBase]] = {}

    # --- writing whole episodes --------------------------------------------------------------------

    def extend(self, data: TensorDictBase, *args, **kwargs):
        data = data.reshape(-1)
        ids = data.get(TRAJ_IDS).reshape(-1)
        done = data.get(("next", "done")).reshape(-1)
        for traj in dict.fromkeys(ids.tolist()):  # in order of first appearance
            rows = data[ids == traj]
            self.pending.setdefault(traj, []).append(rows)
            length = sum(len(part) for part in self.pending[traj])
            if bool(done[ids == traj][-1]) or length >= self.max_pending:
                self._write(self.pending.pop(traj))

    def _write(self, parts: list[TensorDictBase]) -> None:
        episode = torch.cat(parts) if len(parts) > 1 else parts[0]
        steps = len(episode)
        episode = episode.exclude(TRAJ_IDS)
        if "collector" in episode.keys() and episode.get("collector").is_empty():
            episode = episode.exclude("collector")
        episode.set(STEPS_LEFT, torch.arange(steps - 1, -1, -1, device=episode.device))
        super().extend(episode)

    def flush(self) -> None:
        """Write every episode under way as it stands (its futures end where it does so far)."""
        for traj in list(self.pending):
            self._write(self.pending.pop(traj))

    # --- sampling with relabelled goals ------------------------------------------------------------

    def sample(self, batch_size: int | None = None, return_info: bool = False, **kwargs):
        if len(self) == 0:
            self.flush()  # the first updates come before any episode ended
        size = batch_size if batch_size is not None else self._batch_size
        with self._replay_lock:
            index, info = self._sampler.sample(self._storage, size)
            data = self._storage.get(index)
        relabelled = int(size * self.her_ratio)
        if relabelled:
            self._relabel(data, index[:relabelled])
        data = data.exclude(STEPS_LEFT)
        return (data, info) if return_info else data

    def _relabel(self, data: TensorDictBase, index: torch.Tensor) -> None:
        count, key = len(index), self.observation_key
        left = data.get(STEPS_LEFT)[:count].to(index.device)
        offset = (torch.rand(count, device=index.device) * (left + 1)).long().clamp(max=left)
        future = (index + offset) % self._storage.max_size
        goals = self._next_observations()[future, self.achieved]
        observation = data.get(key).clone()
        next_observation = data.get(("next", key)).clone()
        observation[:count, self.desired] = goals
        next_observation[:count, self.desired] = goals
        reward = data.get(("next", "reward")).clone()
        achieved = next_observation[:count, self.achieved].cpu().numpy()
        relabelled = np.asarray(self.compute_reward(achieved, goals.cpu().numpy(), {}), dtype=np.float32)
        reward[:count] = torch.as_tensor(relabelled, device=reward.device).reshape(reward[:count].shape)
        data.set(key, observation)
        data.set(("next", key), next_observation)
        data.set(("next", "reward"), reward)

    def _next_observations(self) -> torch.Tensor:
        """Every stored next observation, as the storage's own tensor: one entry read at the future indices.
        ``LazyTensorStorage.get`` would gather every stored entry of each transition (~0.5 ms a batch of 256
        here); the TensorDict it keeps (``_storage``, TorchRL 0.14) is read where there is one."""
        stored = getattr(self._storage, "_storage", None)
        if stored is not None and hasattr(stored, "get"):
            return stored.get(("next", self.observation_key))
        return self._storage.get(torch.arange(len(self._storage))).get(("next", self.observation_key))

    # --- what a checkpoint keeps besides the stored transitions --------------------------------------

    def extra_state(self) -> dict[str, torch.Tensor]:
        """The episodes under way (their steps, trajectory ids included), flattened to tensors."""
        parts = [part for traj in self.pending.values() for part in traj]
        if not parts:
            return {}
        pending = torch.cat(parts)
        return {"pending_len": torch.tensor(len(pending)),
                **{f"pending/{key}": value for key, value in pending.flatten_keys("/").items()}}

    def load_extra_state(self, state: dict[str, torch.Tensor]) -> None:
        self.pending = {}
        if not state:
            return
        fields = {key.removeprefix("pending/"): value for key, value in state.items() if key.startswith("pending/")}
        pending = TensorDict(fields, batch_size=[int(state["pending_len"])]).unflatten_keys("/")
        ids = pending.get(TRAJ_IDS).reshape(-1)
        for traj in dict.fromkeys(ids.tolist()):
            self.pending[traj] = [pending[ids == traj]]

    def empty(self, *args, **kwargs):
        super().empty(*args, **kwargs)
        self.pending = {}
