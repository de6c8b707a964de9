"""A collector's envs in the middle of their episodes, for a checkpoint: TorchRL's ``Collector`` with
the state that decides its next block added to its ``state_dict`` / ``load_state_dict``.

TorchRL's collectors move ``state_dict``s between the learner and their workers already (the
multi-process collectors' ``"state_dict"``/``"load_state_dict"`` messages, Ray's remote calls), and
take the class of collector their workers run (``collector_class``): ``SnapshotCollector`` is that
class. What it adds, under ``SNAPSHOT``, all tensors:

* ``env/...``: each gymnasium env's own state (``rlpipe.envs.snapshot.capture``), where capturable;
* ``carrier/...``: the collector's in-flight TensorDict (current observation, step count, the
  episode's return so far, trajectory id): what the next step is taken from; ``traj_pool``: the
  next trajectory's id;
* ``rng/...``: the worker process's torch and NumPy generators (exploration noise, random actions),
  only in a worker process of its own (``WorkerSnapshotCollector``): in-process, those are the
  learner's, which the checkpoint keeps already (and which updates made after the snapshot move on);
* ``capturable``: False when an env cannot be captured (the episode in progress then restarts).

``TorchRL`` has no such state: its collectors' ``state_dict`` holds transforms and policy weights,
and a new collector starts new episodes.
"""

from __future__ import annotations

from collections import OrderedDict
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.envs import EnvBase, TransformedEnv

from rlpipe.envs.snapshot import NotCapturable, capture, restore, why_not_capturable
from rlpipe.pipelines.compat.torchrl import prompt_block_hand_over, ray_weight_sync_deadline
from rlpipe.pipelines.system.faults import fault_point

__all__ = ["SNAPSHOT", "SnapshotCollector", "WorkerSnapshotCollector", "gym_envs_of", "seed_worker", "why_not_exact"]

SNAPSHOT = "rlpipe_snapshot"


def gym_envs_of(env: EnvBase) -> list | None:
    """The gymnasium envs a TorchRL env steps (one, or a ``SyncVectorEnv``'s copies); None when it is not
    a gymnasium env wrapped by TorchRL's ``GymEnv``/``GymWrapper`` (a user's own env, a batched env)."""
    while isinstance(env, TransformedEnv):
        env = env.base_env
    gym_env = getattr(env, "_env", None)
    if gym_env is None:
        return None
    import gymnasium

    if isinstance(gym_env, gymnasium.vector.SyncVectorEnv):
        return list(gym_env.envs)
    if isinstance(gym_env, gymnasium.vector.VectorEnv):
        return None
    return [gym_env] if isinstance(gym_env, gymnasium.Env) else None


def why_not_exact(env: EnvBase) -> str | None:
    """Why a checkpoint cannot hold ``env``'s episode in progress, or None when it can."""
    envs = gym_envs_of(env)
    if envs is None:
        return f"{type(env).__name__} is not a gymnasium env stepped by TorchRL's GymEnv"
    for gym_env in envs:
        why = why_not_capturable(gym_env)
        if why is not None:
            return why
    return None


def _numpy_state() -> dict[str, torch.Tensor]:
    _, key, pos, has_gauss, cached = np.random.get_state()
    return {"key": torch.from_numpy(key.astype(np.int64)), "pos": torch.tensor(int(pos)),
            "has_gauss": torch.tensor(int(has_gauss)), "cached": torch.tensor(float(cached), dtype=torch.float64)}


def _set_numpy_state(state: dict[str, torch.Tensor]) -> None:
    np.random.set_state(("MT19937", state["key"].numpy().astype(np.uint32), int(state["pos"]),
                         int(state["has_gauss"]), float(state["cached"])))


def _flat(prefix: str, tree: dict[str, Any]) -> dict[str, torch.Tensor]:
    return {f"{prefix}/{k}": v for k, v in tree.items()}


def _under(prefix: str, flat: dict[str, Any]) -> dict[str, Any]:
    return {k[len(prefix) + 1:]: v for k, v in flat.items() if k.startswith(prefix + "/")}


class SnapshotCollector(Collector):
    """TorchRL's ``Collector`` whose ``state_dict`` carries its envs' episodes in progress (see the module)."""

    own_rng = False

    def snapshot(self) -> dict[str, torch.Tensor]:
        """The state that decides this collector's next block, as flat tensors."""
        state = {"capturable": torch.tensor(False)}
        envs = gym_envs_of(self.env)
        try:
            if envs is None:
                raise NotCapturable("not a gymnasium env")
            for i, gym_env in enumerate(envs):
                state.update(_flat(f"env/{i}", capture(gym_env)))
            state["capturable"] = torch.tensor(True)
        except NotCapturable:
            state = {"capturable": torch.tensor(False)}
        carrier = getattr(self, "_carrier", None)
        if carrier is not None:
            state.update({f"carrier/{k}": v.clone() for k, v in carrier.flatten_keys("/").items()
                          if isinstance(v, torch.Tensor)})
        if getattr(self, "track_traj_ids", False):
            state["traj_pool"] = self._traj_pool.state_dict()["traj_id"]  # the next trajectory's id
        state.update(self._rng_state())
        return state

    def _rng_state(self) -> dict[str, torch.Tensor]:
        if not self.own_rng:
            return {}
        return {"rng/torch": torch.get_rng_state(), **_flat("rng/numpy", _numpy_state())}

    def load_snapshot(self, state: dict[str, torch.Tensor]) -> bool:
        """Put ``snapshot``'s ``state`` into this (new) collector; False if its envs' episodes could not be
        restored (it then goes on from the episodes it started)."""
        if not bool(state.get("capturable", False)):
            self._restore_rng(state)
            return False
        envs = gym_envs_of(self.env)
        saved = _under("env", state)
        if envs is None or {int(k.split("/", 1)[0]) for k in saved} != set(range(len(envs))):
            self._restore_rng(state)
            return False
        for i, gym_env in enumerate(envs):
            restore(gym_env, _under(str(i), saved))
        carrier = _under("carrier", state)
        if carrier:
            batch = self._carrier.batch_size
            self._carrier = TensorDict(carrier, batch_size=batch, device=self._carrier.device).unflatten_keys("/")
        if "traj_pool" in state and getattr(self, "track_traj_ids", False):
            self._traj_pool.load_state_dict({"traj_id": state["traj_pool"]})
        self._restore_rng(state)
        return True

    def _restore_rng(self, state: dict[str, torch.Tensor]) -> None:
        if self.own_rng and "rng/torch" in state:
            torch.set_rng_state(state["rng/torch"])
            _set_numpy_state(_under("rng/numpy", state))

    def set_seed(self, seed: int, static_seed: bool = False) -> int:
        out = super().set_seed(seed, static_seed=static_seed)
        # TorchRL's reseeds (resets) the env but keeps the in-flight step of the reset before it: the
        # first transition's observation came from another episode (an entropy-seeded one in a Ray
        # actor, so two runs of one seed differed there)
        self.reset()
        return out

    def state_dict(self) -> OrderedDict:
        # only what a resume needs: TorchRL's own adds the policy's weights, which the learner has
        return OrderedDict({SNAPSHOT: self.snapshot(), "frames": self._frames, "iter": self._iter})

    def load_state_dict(self, state_dict: OrderedDict, **kwargs) -> None:
        if SNAPSHOT in state_dict:
            self.load_snapshot(state_dict[SNAPSHOT])
        else:
            super().load_state_dict(state_dict, **kwargs)


class WorkerSnapshotCollector(SnapshotCollector):
    """``SnapshotCollector`` in a worker process of its own: its generators are part of its state, and
    ``set_seed`` seeds them (TorchRL's multi-process workers do so themselves; its Ray actors do not)."""

    own_rng = True

    def __init__(self, *args, weight_sync_deadline: float | None = None, **kwargs):
        """``weight_sync_deadline``: on a Ray actor, the seconds its weight sync may take to connect (the run's
        start-up deadline; ``compat.torchrl.ray_weight_sync_deadline``)."""
        prompt_block_hand_over()  # no 1-ms wait after each block in TorchRL's worker loop
        if weight_sync_deadline is not None:
            ray_weight_sync_deadline(weight_sync_deadline)
        super().__init__(*args, **kwargs)

    def set_seed(self, seed: int, static_seed: bool = False) -> int:
        seed_worker(seed)
        return super().set_seed(seed, static_seed=static_seed)

    def cascade_execute(self, attr_path: str, *args, **kwargs):
        if attr_path.endswith(".connect"):  # TorchRL's RayCollector: an actor joins the learner's weight sync
            fault_point("ray_weight_connect", 0)
        return super().cascade_execute(attr_path, *args, **kwargs)


def seed_worker(seed: int) -> None:
    """Seed a worker process's own generators (TorchRL's Ray actors leave them unseeded)."""
    torch.manual_seed(seed)
    np.random.seed(seed % 2**32)
