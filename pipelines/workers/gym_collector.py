"""``GymCollector``: blocks of env steps from a gymnasium env stepped directly, as TorchRL's ``Collector`` gives them.

Why it exists (issue 22): with one env in the learner's process, TorchRL's ``Collector`` over
``GymEnv`` and the standard transforms (``StepCounter``, ``RewardSum``, ``InitTracker``) costs
~600-700 us a step on this 2-core CPU (CartPole 1,478 steps/s against ~120,000 for the raw env; a
cProfile of 2,000 steps: 72% in ``step_and_maybe_reset`` through the transforms and ``GymEnv``'s
TensorDict reads and writes, 11% the policy through TensorDicts, the rest the collector's own
TensorDict copies). CleanRL's loop (``obs -> policy -> env.step``, numpy in and out) pays only the
network and the env. TorchRL has no per-step path without TensorDicts (pytorch/rl#1247), so this
collector steps the gymnasium env with numpy, calls the collect policy on one observation tensor
(``rlpipe.modules.tensor_policy``: the built-in policies' own arithmetic, a user's policy through
a TensorDict), writes each row into per-block numpy arrays, and hands each block out as a
TensorDict with exactly the keys, shapes and dtypes TorchRL's ``Collector`` gives for the same env
(``observation``, ``action``, the policy's outputs, ``step_count``, ``episode_reward``, ``is_init``,
``done``/``terminated``/``truncated``, the same under ``next`` with ``reward``, and
``("collector", "traj_ids")``), so a TorchRL replay buffer and loss take them unchanged.
Figures (``rlpipe bench collect``): BENCHMARKS.md, "A collection path worth its cost".

Semantics kept from TorchRL's path: ``set_seed(s)`` resets the env with ``seed=s`` (later resets
unseeded, as ``GymEnv`` does); a block is random (the action spec's ``rand()``, torch's global
generator) while fewer than ``init_random_frames`` frames were collected before it; the policy's
exploration draws from torch's global generator, in the policy modules' own order; iteration ends
once ``total_frames`` are collected (whole blocks; -1: never).
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import gymnasium
import numpy as np
import torch
from tensordict import TensorDict
from torch import nn
from torchrl._utils import seed_generator
from torchrl.data import TensorSpec
from torchrl.envs import EnvBase, GymWrapper, TransformedEnv

from rlpipe.envs import is_discrete
from rlpipe.modules.tensor_policy import tensor_step

__all__ = ["GymCollector", "gym_env_of"]

_TRANSFORM_KEYS = {"step_count", "episode_reward", "is_init"}


def gym_env_of(env: EnvBase | None) -> gymnasium.Env | None:
    """The gymnasium env under ``env`` when ``env`` is ``rlpipe.envs.make_env``'s one-copy env (TorchRL's
    ``GymEnv``/``GymWrapper`` under the standard transforms), else None."""
    if not isinstance(env, TransformedEnv) or env.batch_size != torch.Size([]):
        return None
    base = env.base_env
    if not isinstance(base, GymWrapper) or base.batch_size != torch.Size([]):
        return None
    names = {type(t).__name__ for t in env.transform}
    if not names <= {"StepCounter", "RewardSum", "InitTracker", "DoubleToFloat"} or "RewardSum" not in names:
        return None
    gym_env = base._env
    return gym_env if isinstance(gym_env, gymnasium.Env) else None


class GymCollector:
    """TorchRL ``Collector``'s interface (iterate, ``set_seed``, ``shutdown``, ``update_policy_weights_``)
    over a gymnasium env stepped directly; see the module's docstring for why.

    Args:
        env: the TorchRL env ``make_env`` made (its specs give the block's keys and dtypes; its
            gymnasium env is what is stepped: the same object, so it is not closed here).
        policy: the collect policy (a TensorDict module reading ``observation_key``).
        frames_per_batch, total_frames, init_random_frames: as TorchRL's ``Collector``'s.
        device: where blocks are stored and the policy runs (the learner's device).
    """

    def __init__(self, env: EnvBase, policy: nn.Module, *, frames_per_batch: int, total_frames: int = -1,
                 init_random_frames: int = 0, device: torch.device | str = "cpu"):
        gym_env = gym_env_of(env)
        if gym_env is None:
            raise ValueError(f"GymCollector steps make_env's one-copy gymnasium envs; got {type(env).__name__}")
        self.env, self.gym_env, self.policy = env, gym_env, policy
        self.frames_per_batch, self.total_frames = int(frames_per_batch), int(total_frames)
        self.init_random_frames = int(init_random_frames)
        self.device = torch.device(device)
        obs_keys = [k for k in env.observation_spec.keys() if k not in _TRANSFORM_KEYS]
        if len(obs_keys) != 1:
            raise ValueError(f"GymCollector needs one observation entry; the env has {obs_keys}")
        self.observation_key = obs_keys[0]
        obs_spec = env.observation_spec[self.observation_key]
        self._obs_shape, self._obs_dtype = tuple(obs_spec.shape), _numpy_dtype(obs_spec.dtype)
        self._obs_torch_dtype = obs_spec.dtype
        self.action_spec: TensorSpec = env.action_spec_unbatched
        self._discrete = is_discrete(self.action_spec)
        self._reward_dtype = env.reward_spec.dtype
        self._act = tensor_step(policy, self.observation_key)
        # bookkeeping of the episode under way (state_dict holds it)
        self.frames = 0
        self._obs: np.ndarray | None = None  # None: the env needs a reset before the next step
        self._step_count = 0
        self._episode_reward = 0.0
        self._traj_id = -1
        self._next_traj_id = 0
        self.closed = False
        self._template: dict[str, torch.Tensor] | None = None

    # --- TorchRL Collector's interface ----------------------------------------------------------

    def set_seed(self, seed: int, static_seed: bool = False) -> int:
        """Reset the env with ``seed`` (a new episode); returns the next seed, as TorchRL's envs do."""
        self._reset(seed=seed)
        return seed if static_seed else seed_generator(seed)

    def update_policy_weights_(self, *args, **kwargs) -> None:
        """Nothing to send: the collector holds the learner's own policy."""

    def shutdown(self, *args, **kwargs) -> None:
        self.closed = True  # the env is the pipeline's: it closes it

    def __iter__(self) -> Iterator[TensorDict]:
        while self.total_frames < 0 or self.frames < self.total_frames:
            if self.closed:
                return
            block = self.rollout(random=self.frames < self.init_random_frames)
            self.frames += self.frames_per_batch
            yield block

    # --- the state a resume needs -----------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """The collector's own bookkeeping: frames counted, the episode under way (its observation, step,
        return, trajectory id) and the env's own state (``capture_env_state``). The exploration's state is
        the policy's (its state dict: epsilon, noise scale) and torch's global generator (the pipeline's
        checkpoint holds both)."""
        return {
            "frames": self.frames,
            "observation": None if self._obs is None else torch.as_tensor(self._obs.copy()),
            "step_count": self._step_count,
            "episode_reward": self._episode_reward,
            "traj_id": self._traj_id,
            "next_traj_id": self._next_traj_id,
            "env": self.capture_env_state(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.frames = int(state["frames"])
        obs = state["observation"]
        self._obs = None if obs is None else np.asarray(obs, dtype=self._obs_dtype).copy()
        self._step_count, self._episode_reward = int(state["step_count"]), float(state["episode_reward"])
        self._traj_id, self._next_traj_id = int(state["traj_id"]), int(state["next_traj_id"])
        if state.get("env") is not None:
            self.restore_env_state(state["env"])
        elif self._obs is not None:
            self._obs = None  # without the env's own state the episode cannot go on: start a new one

    def capture_env_state(self) -> dict[str, torch.Tensor] | None:
        """The gymnasium env's own state (physics, its random generator, the time limit's count), for an exact
        resume. The one place it is captured: wire ``rlpipe.envs.snapshot.capture(self.gym_env)`` here
        (issue 23). None: not captured, and a restored collector starts a new episode."""
        return None

    def restore_env_state(self, state: dict[str, torch.Tensor]) -> None:
        """Put back what ``capture_env_state`` captured: ``rlpipe.envs.snapshot.restore(self.gym_env, state)``
        (issue 23)."""
        raise NotImplementedError("env-state restore is wired with rlpipe.envs.snapshot (issue 23)")

    # --- stepping -----------------------------------------------------------------------------------

    def _reset(self, seed: int | None = None) -> None:
        obs, _ = self.gym_env.reset(seed=seed) if seed is not None else self.gym_env.reset()
        self._obs = np.asarray(obs, dtype=self._obs_dtype)
        self._step_count, self._episode_reward = 0, 0.0
        self._traj_id, self._next_traj_id = self._next_traj_id, self._next_traj_id + 1

    def _policy_template(self) -> dict[str, torch.Tensor]:
        """What the policy writes for one step (keys, shapes, dtypes), from one call whose random draws are
        undone (torch's generator forked); cached."""
        if self._template is None:
            observation = torch.zeros(self._obs_shape, dtype=self._obs_torch_dtype, device=self.device)
            with torch.random.fork_rng(devices=[]), torch.no_grad():
                self._template = {k: v.detach() for k, v in self._act(observation).items()}
        return self._template

    def _random_step(self, observation: torch.Tensor) -> dict:
        return {"action": self.action_spec.rand()}

    @torch.no_grad()
    def rollout(self, random: bool = False) -> TensorDict:
        """One block of ``frames_per_batch`` env steps (random actions with ``random=True``)."""
        n, env = self.frames_per_batch, self.gym_env
        obs_buf = np.empty((n, *self._obs_shape), self._obs_dtype)
        next_obs_buf = np.empty_like(obs_buf)
        reward = np.empty((n, 1), np.float64)
        terminated = np.empty((n, 1), bool)
        truncated = np.empty((n, 1), bool)
        step_count = np.empty((n, 1), np.int64)
        episode_reward = np.empty((n, 1), np.float64)
        next_episode_reward = np.empty((n, 1), np.float64)
        traj_ids = np.empty((n,), np.int64)
        outputs: list[dict] = []
        act = self._random_step if random else self._act
        on_cpu = self.device.type == "cpu"
        discrete = self._discrete
        if self._obs is None:
            self._reset()
        obs = self._obs
        for i in range(n):
            obs_buf[i] = obs
            observation = torch.from_numpy(obs_buf[i])
            out = act(observation if on_cpu else observation.to(self.device))
            outputs.append(out)
            action = out["action"]
            action = action.item() if discrete else action.cpu().numpy()
            next_obs, r, term, trunc, _ = env.step(action)
            step_count[i] = self._step_count
            episode_reward[i] = self._episode_reward
            traj_ids[i] = self._traj_id
            self._step_count += 1
            self._episode_reward += r
            reward[i], terminated[i], truncated[i] = r, term, trunc
            next_obs_buf[i] = next_obs
            next_episode_reward[i] = self._episode_reward
            if term or trunc:
                self._reset()
                obs = self._obs
            else:
                obs = next_obs
        self._obs = np.asarray(obs, dtype=self._obs_dtype)
        return self._block(n, obs_buf, next_obs_buf, reward, terminated, truncated, step_count, episode_reward,
                           next_episode_reward, traj_ids, outputs)

    def _block(self, n, obs_buf, next_obs_buf, reward, terminated, truncated, step_count, episode_reward,
               next_episode_reward, traj_ids, outputs) -> TensorDict:
        """The rows as TorchRL's ``Collector`` lays them out (``tests/test_gym_collector.py`` compares them)."""
        terminated_t, truncated_t = torch.from_numpy(terminated), torch.from_numpy(truncated)
        step_count_t = torch.from_numpy(step_count)
        reward_dtype = self._reward_dtype
        not_done = torch.zeros(n, 1, dtype=torch.bool)
        is_init = step_count_t == 0
        policy_out = {key: torch.stack([o[key] for o in outputs]) for key in outputs[0]}
        for key, value in self._policy_template().items():  # random rows: zeros where the policy writes, as TorchRL
            if key not in policy_out:
                policy_out[key] = value.new_zeros((n, *value.shape))
        action = policy_out.pop("action")
        obs_key = self.observation_key
        td = TensorDict({
            "step_count": step_count_t,
            "episode_reward": torch.from_numpy(episode_reward).to(reward_dtype),
            "action": action,
            obs_key: torch.from_numpy(obs_buf),
            "is_init": is_init,
            "done": not_done,
            "terminated": not_done.clone(),
            "truncated": not_done.clone(),
            "next": {
                obs_key: torch.from_numpy(next_obs_buf),
                "step_count": step_count_t + 1,
                "episode_reward": torch.from_numpy(next_episode_reward).to(reward_dtype),
                "is_init": torch.zeros(n, 1, dtype=torch.bool),
                "reward": torch.from_numpy(reward).to(reward_dtype),
                "done": terminated_t | truncated_t,
                "terminated": terminated_t,
                "truncated": truncated_t,
            },
            "collector": {"traj_ids": torch.from_numpy(traj_ids)},
            **policy_out,
        }, batch_size=[n])
        return td if self.device.type == "cpu" else td.to(self.device)


def _numpy_dtype(dtype: torch.dtype) -> np.dtype:
    return torch.empty((), dtype=dtype).numpy().dtype
