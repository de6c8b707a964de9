"""``GymCollector``: blocks of env steps from a gymnasium env stepped directly, as TorchRL's ``Collector`` gives them.

Why it exists: with one env in the learner's process, TorchRL's ``Collector`` over
``GymEnv`` and the standard transforms (``StepCounter``, ``RewardSum``, ``InitTracker``) costs
~600-700 us a step on this 2-core CPU (CartPole 1,478 steps/s against ~120,000 for the raw env; a
cProfile of 2,000 steps: 72% in ``step_and_maybe_reset`` through the transforms and ``GymEnv``'s
TensorDict reads and writes, 11% the policy through TensorDicts, the rest the collector's own
TensorDict copies). CleanRL's loop (``obs -> policy -> env.step``, numpy in and out) pays only the
network and the env. TorchRL has no per-step path without TensorDicts (pytorch/rl#1247), so this
collector steps the gymnasium env with numpy, calls the collect policy on one observation tensor
(``rlpipe.modules.fast.tensor_policy``: the built-in policies' own arithmetic, a user's policy through
a TensorDict), writes each row into per-block numpy arrays, and hands each block out as a
TensorDict with exactly the keys, shapes and dtypes TorchRL's ``Collector`` gives for the same env
(``observation``, ``action``, the policy's outputs, ``step_count``, ``episode_reward``, ``is_init``,
``done``/``terminated``/``truncated``, the same under ``next`` with ``reward``, and
``("collector", "traj_ids")``), so a TorchRL replay buffer and loss take them unchanged.
With it, one env with 50-frame blocks steps at 0.75-0.80 of the plain loop with the same network in the
learner's process (CartPole ~13,000 steps/s, Pendulum ~11,000: ~9x TorchRL's ``Collector``) and 0.58-0.65 in one
collector process (BENCHMARKS.md, "Collection only: `rlpipe bench collect`").

Semantics kept from TorchRL's path: ``set_seed(s)`` resets the env with ``seed=s`` (later resets
unseeded, as ``GymEnv`` does); a block is random (the action spec's ``rand()``, torch's global
generator) while fewer than ``init_random_frames`` frames were collected before it; the policy's
exploration draws from torch's global generator, in the policy modules' own order; iteration ends
once ``total_frames`` are collected (whole blocks; -1: never).
"""

from __future__ import annotations

import contextlib

import gymnasium
import numpy as np
import torch
from tensordict import TensorDict
from torchrl._utils import seed_generator
from torchrl.data import TensorSpec
from torchrl.envs import Compose, EnvBase, GymWrapper, TransformedEnv
from torchrl.envs.utils import set_exploration_type

from rlpipe.envs import is_discrete
from rlpipe.envs.snapshot import NotCapturable, capture, restore
from rlpipe.modules.fast.tensor_policy import tensor_step
from rlpipe.pipelines.compat.torchrl import prompt_block_hand_over
from rlpipe.pipelines.workers.snapshot_collector import SnapshotCollector, seed_worker

__all__ = ["GymCollector", "WorkerGymCollector", "gym_env_of"]

_TRANSFORM_KEYS = {"step_count", "episode_reward", "is_init"}


def gym_env_of(env: EnvBase | None) -> gymnasium.Env | None:
    """The gymnasium env under ``env`` when ``env`` is ``rlpipe.envs.make_env``'s one-copy env (TorchRL's
    ``GymEnv``/``GymWrapper`` under the standard transforms), else None."""
    if not isinstance(env, TransformedEnv) or env.batch_size != torch.Size([]):
        return None
    base = env.base_env
    if not isinstance(base, GymWrapper) or base.batch_size != torch.Size([]):
        return None
    transforms = env.transform if isinstance(env.transform, Compose) else [env.transform]
    names = {type(t).__name__ for t in transforms}
    if not names <= {"StepCounter", "RewardSum", "InitTracker", "DoubleToFloat"} or "RewardSum" not in names:
        return None
    gym_env = base._env
    return gym_env if isinstance(gym_env, gymnasium.Env) else None


class GymCollector(SnapshotCollector):
    """TorchRL's ``Collector`` whose ``rollout`` steps the gymnasium env under ``make_env``'s env directly;
    see the module's docstring for why.

    Everything else is TorchRL's: the constructor's arguments, iteration, frame counting, random initial
    frames, the weight-sync receivers, and its use as ``collector_class`` of ``MultiSyncCollector`` /
    ``MultiAsyncCollector`` (each worker process then steps its env so). The env must be ``make_env``'s
    one-copy env (``gym_env_of`` not None); its TorchRL specs give the block's keys and dtypes.
    """

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        gym_env = gym_env_of(self.env)
        if gym_env is None:
            raise ValueError(f"GymCollector steps make_env's one-copy gymnasium envs; got {type(self.env).__name__}")
        self.gym_env = gym_env
        obs_keys = [k for k in self.env.observation_spec.keys() if k not in _TRANSFORM_KEYS]
        if len(obs_keys) != 1:
            raise ValueError(f"GymCollector needs one observation entry; the env has {obs_keys}")
        self.observation_key = obs_keys[0]
        obs_spec = self.env.observation_spec[self.observation_key]
        self._obs_shape, self._obs_dtype = tuple(obs_spec.shape), _numpy_dtype(obs_spec.dtype)
        self._obs_torch_dtype = obs_spec.dtype
        self._action_spec: TensorSpec = self.env.action_spec_unbatched
        self._discrete = is_discrete(self._action_spec)
        self._reward_dtype = self.env.reward_spec.dtype
        self._act = None  # the policy on tensors, made at the first block (weight receivers are set up by then)
        self._template: dict[str, torch.Tensor] | None = None
        self._shared_block: TensorDict | None = None
        # Outside a worker process each block is a new TensorDict: TorchRL's iterator need not clone it
        # (~150 us a block, ~3 us a CartPole step) before handing it out.
        self._fresh_blocks = self.worker_idx is None and self.replay_buffer is None
        if self._fresh_blocks and (self.storing_device is None or self.storing_device.type == "cpu"):
            self.return_same_td = True
        # the episode under way (state_dict holds it): the env is reset at the first block
        self._obs: np.ndarray | None = None
        self._step_count = 0
        self._episode_reward = 0.0
        self._traj_id = int(self._carrier.get(("collector", "traj_ids")).reshape(-1)[0])  # TorchRL's first id

    # --- TorchRL Collector's hooks --------------------------------------------------------------------

    def set_seed(self, seed: int, static_seed: bool = False) -> int:
        """Reset the env with ``seed`` (a new episode); returns the next seed, as TorchRL's envs do."""
        self._reset(seed=seed)
        return seed if static_seed else seed_generator(seed)

    def reset(self, index=None, **kwargs) -> None:
        super().reset(index, **kwargs)  # TorchRL numbers the new trajectory
        self._traj_id = int(self._carrier.get(("collector", "traj_ids")).reshape(-1)[0])
        self._obs, self._step_count, self._episode_reward = None, 0, 0.0  # a new episode at the next block

    @torch.no_grad()
    def rollout(self) -> TensorDict:
        """One block of ``frames_per_batch`` env steps, random while ``_should_use_random_frames()``."""
        if self._act is None:
            self._act = tensor_step(self.policy, self.observation_key)
        with set_exploration_type(self.exploration_type):
            block = self._rollout(random=self._should_use_random_frames())
        if self._fresh_blocks or not self.return_same_td:
            return block
        # TorchRL's worker processes send the first block's shared memory once, then expect it filled in place
        if self._shared_block is None:
            self._shared_block = block
        else:
            self._shared_block.update_(block)
        return self._shared_block

    # --- the state a resume needs (SnapshotCollector's state_dict carries it) ------------------------

    def snapshot(self) -> dict[str, torch.Tensor]:
        """What decides the next block, as flat tensors: the gymnasium env's own state
        (``rlpipe.envs.snapshot``), the episode under way (observation, step, return, trajectory id), the
        next trajectory's id, and in a worker process of its own that process's generators. The
        exploration's state is the policy's and the learner's generator (the pipeline's checkpoint)."""
        state: dict[str, torch.Tensor] = {"capturable": torch.tensor(False)}
        if self._obs is not None:
            try:
                state.update({f"env/0/{k}": v for k, v in capture(self.gym_env).items()})
            except NotCapturable:
                pass
            else:
                state.update({"capturable": torch.tensor(True),
                              "episode/observation": torch.as_tensor(self._obs.copy()),
                              "episode/step_count": torch.tensor(self._step_count),
                              "episode/episode_reward": torch.tensor(self._episode_reward, dtype=torch.float64),
                              "episode/traj_id": torch.tensor(self._traj_id)})
        state["traj_pool"] = self._traj_pool.state_dict()["traj_id"]
        state.update(self._rng_state())
        return state

    def load_snapshot(self, state: dict[str, torch.Tensor]) -> bool:
        """Go on from ``snapshot``'s ``state``: the episode under way where it was captured (True), or a new
        episode, numbered after the ones collected before (False)."""
        self._restore_rng(state)
        if "traj_pool" in state:
            self._traj_pool.load_state_dict({"traj_id": state["traj_pool"]})
        if not bool(state.get("capturable", False)) or "episode/observation" not in state:
            self._obs, self._step_count, self._episode_reward = None, 0, 0.0
            self._traj_id = int(self._traj_pool.get_traj_and_increment(1)[0])
            return False
        restore(self.gym_env, {k[len("env/0/"):]: v for k, v in state.items() if k.startswith("env/0/")})
        self._obs = state["episode/observation"].numpy().astype(self._obs_dtype, copy=True)
        self._step_count = int(state["episode/step_count"])
        self._episode_reward = float(state["episode/episode_reward"])
        self._traj_id = int(state["episode/traj_id"])
        return True

    # --- stepping -----------------------------------------------------------------------------------

    def _reset(self, seed: int | None = None) -> None:
        obs, _ = self.gym_env.reset(seed=seed) if seed is not None else self.gym_env.reset()
        if self._step_count > 0:  # the trajectory under way had steps: a new one, numbered by TorchRL's pool
            self._traj_id = int(self._traj_pool.get_traj_and_increment(1)[0])
        self._obs = np.asarray(obs, dtype=self._obs_dtype)
        self._step_count, self._episode_reward = 0, 0.0

    def _policy_template(self) -> dict[str, torch.Tensor]:
        """What the policy writes for one step (keys, shapes, dtypes), from one call whose random draws are
        undone (torch's generator forked); cached."""
        if self._template is None:
            observation = torch.zeros(self._obs_shape, dtype=self._obs_torch_dtype, device=self.policy_device)
            with torch.random.fork_rng(devices=[]), torch.no_grad():
                self._template = {k: v.detach() for k, v in self._act(observation).items()}
        return self._template

    def _random_step(self, observation: torch.Tensor) -> dict:
        return {"action": self._action_spec.rand()}

    def _rollout(self, random: bool) -> TensorDict:
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
        device = self.policy_device if self.policy_device is not None and self.policy_device.type != "cpu" else None
        discrete = self._discrete
        if self._obs is None:
            self._reset()
        obs = self._obs
        # rlpipe's own tensor paths make no state: their per-step ops run under inference mode (~12% less a
        # call than no_grad: DQN's epsilon-greedy Q-network 39 -> 35 us); the block is stacked outside it
        fast = act is self._random_step or getattr(act, "inference_safe", False)
        with torch.inference_mode() if fast else contextlib.nullcontext():
            obs = self._steps(n, act, env, device, discrete, obs, obs_buf, next_obs_buf, reward, terminated, truncated,
                              step_count, episode_reward, next_episode_reward, traj_ids, outputs)
        self._obs = np.asarray(obs, dtype=self._obs_dtype)
        return self._block(n, obs_buf, next_obs_buf, reward, terminated, truncated, step_count, episode_reward,
                           next_episode_reward, traj_ids, outputs)

    def _steps(self, n, act, env, device, discrete, obs, obs_buf, next_obs_buf, reward, terminated, truncated,
               step_count, episode_reward, next_episode_reward, traj_ids, outputs):
        """``n`` env steps into the buffers; returns the observation the next block starts from."""
        for i in range(n):
            obs_buf[i] = obs
            observation = torch.from_numpy(obs_buf[i])
            out = act(observation if device is None else observation.to(device))
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
        return obs

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
        }, batch_size=[n], device="cpu")
        storing = self.storing_device
        return td if storing is None or storing.type == "cpu" else td.to(storing)


def _numpy_dtype(dtype: torch.dtype) -> np.dtype:
    return torch.empty((), dtype=dtype).numpy().dtype


class WorkerGymCollector(GymCollector):
    """``GymCollector`` in a worker process of its own: its generators are part of its state, and
    ``set_seed`` seeds them (as ``snapshot.WorkerSnapshotCollector``)."""

    own_rng = True

    def __init__(self, *args, **kwargs):
        prompt_block_hand_over()  # no 1-ms wait after each block in TorchRL's worker loop
        super().__init__(*args, **kwargs)

    def set_seed(self, seed: int, static_seed: bool = False) -> int:
        seed_worker(seed)
        return super().set_seed(seed, static_seed=static_seed)
