"""Every observation a user's env gives: a goal env (Dict with achieved and desired goals) trained with HER, a
Dict read entry by entry, an image read through a convolutional encoder and kept uint8, and the refusals.

The envs are a user's own, in a module on sys.path, named ``module:Class`` as on the command line.
"""

from __future__ import annotations

import importlib.util
import json
import math
import os
import re
import sys
import textwrap

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from rlpipe.envs import EnvError, gym_env_under, make_env
from rlpipe.envs.observations import EpisodicLife, FireOnLifeStart
from rlpipe.modules.hindsight import STEPS_LEFT, TRAJ_IDS, HindsightReplayBuffer
from rlpipe.pipelines import dqn, sac, td3
from rlpipe.pipelines.artifacts.export import load_policy
from rlpipe.scripts.cli import main

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")

MODULE = "rlpipe_test_observations"
ENVS_PY = '''
import gymnasium
import numpy as np
from gymnasium import spaces


class GoalPoint(gymnasium.Env):
    """A point on a line moved to a goal drawn at reset, in gymnasium-robotics' goal-env form."""

    def __init__(self):
        box = spaces.Box(-1.0, 1.0, (1,), np.float32)
        self.observation_space = spaces.Dict(observation=box, achieved_goal=box, desired_goal=box)
        self.action_space = spaces.Box(-1.0, 1.0, (1,), np.float32)

    def compute_reward(self, achieved_goal, desired_goal, info):
        return -(np.abs(achieved_goal - desired_goal)[..., 0] > 0.1).astype(np.float32)

    def _obs(self):
        return {"observation": self.x.copy(), "achieved_goal": self.x.copy(), "desired_goal": self.g.copy()}

    def reset(self, seed=None, options=None):
        super().reset(seed=seed)
        self.x = self.np_random.uniform(-1, 1, (1,)).astype(np.float32)
        self.g = self.np_random.uniform(-1, 1, (1,)).astype(np.float32)
        self.t = 0
        return self._obs(), {}

    def step(self, action):
        self.x = np.clip(self.x + 0.2 * np.asarray(action, np.float32), -1, 1).astype(np.float32)
        self.t += 1
        obs = self._obs()
        reward = float(self.compute_reward(obs["achieved_goal"], obs["desired_goal"], {}))
        return obs, reward, False, self.t >= 20, {"is_success": float(reward == 0.0)}


class Labelled(gymnasium.Env):
    """A Dict of a vector and a label no network can read."""

    def __init__(self):
        self.observation_space = spaces.Dict(position=spaces.Box(-1, 1, (2,), np.float32), label=spaces.Text(8))
        self.action_space = spaces.Discrete(2)

    def reset(self, seed=None, options=None):
        return {"position": np.zeros(2, np.float32), "label": "a"}, {}

    def step(self, action):
        return {"position": np.zeros(2, np.float32), "label": "a"}, 0.0, False, True, {}


class PixPoint(gymnasium.Env):
    """A 48x48 RGB picture of a column moved left or right; reaching the right edge pays 1."""

    def __init__(self):
        self.observation_space = spaces.Box(0, 255, (48, 48, 3), np.uint8)
        self.action_space = spaces.Discrete(3)

    def _image(self):
        image = np.zeros((48, 48, 3), np.uint8)
        image[:, self.x, 0] = 255
        return image

    def reset(self, seed=None, options=None):
        super().reset(seed=seed)
        self.x, self.t = 24, 0
        return self._image(), {}

    def step(self, action):
        self.x = int(np.clip(self.x + int(action) - 1, 0, 47))
        self.t += 1
        return self._image(), float(self.x > 40), self.x > 40, self.t >= 30, {}


class Beacon(gymnasium.Env):
    """A goal cell on a line of 11, seen only in an 11x11 picture; the walker's own cell only as a number. Reaching
    the goal within 10 steps pays 1: a policy must read both entries."""

    def __init__(self):
        self.observation_space = spaces.Dict(view=spaces.Box(0, 255, (11, 11), np.uint8),
                                             position=spaces.Box(0.0, 1.0, (1,), np.float32))
        self.action_space = spaces.Discrete(2)

    def observe(self, goal, x):
        view = np.zeros((11, 11), np.uint8)
        view[:, goal] = 255
        return {"view": view, "position": np.array([x / 10], np.float32)}

    def reset(self, seed=None, options=None):
        super().reset(seed=seed)
        self.goal = int(self.np_random.integers(11))
        self.x = int(self.np_random.choice([i for i in range(11) if i != self.goal]))
        self.t = 0
        return self.observe(self.goal, self.x), {}

    def step(self, action):
        self.x = int(np.clip(self.x + (1 if int(action) == 1 else -1), 0, 10))
        self.t += 1
        reached = self.x == self.goal
        return self.observe(self.goal, self.x), float(reached), reached, self.t >= 10, {"is_success": float(reached)}


class Camera(gymnasium.Env):
    """A robot's joint angles beside an RGB camera (channels last), continuous actions."""

    def __init__(self):
        self.observation_space = spaces.Dict(joints=spaces.Box(-1.0, 1.0, (3,), np.float32),
                                             camera=spaces.Box(0, 255, (40, 40, 3), np.uint8))
        self.action_space = spaces.Box(-1.0, 1.0, (2,), np.float32)

    def _obs(self):
        return {"joints": self.np_random.uniform(-1, 1, 3).astype(np.float32),
                "camera": self.np_random.integers(0, 256, (40, 40, 3), dtype=np.uint8)}

    def reset(self, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return self._obs(), {}

    def step(self, action):
        self.t += 1
        return self._obs(), 0.0, False, self.t >= 5, {}


class Depth(gymnasium.Env):
    """A uint16 depth camera (millimetres, up to 4,000: past a byte) alone, or beside a joint angle."""

    def __init__(self, beside=False):
        depth = spaces.Box(0, 4000, (6, 6), np.uint16)
        self.observation_space = spaces.Dict(depth=depth, joint=spaces.Box(-1.0, 1.0, (1,), np.float32)) if beside else depth
        self.action_space = spaces.Discrete(2)

    def _obs(self):
        depth = np.full((6, 6), 3000, np.uint16)
        depth[0, 0] = 260
        return {"depth": depth, "joint": np.zeros(1, np.float32)} if isinstance(self.observation_space, spaces.Dict) else depth

    def reset(self, seed=None, options=None):
        super().reset(seed=seed)
        return self._obs(), {}

    def step(self, action):
        return self._obs(), 0.0, False, True, {}


class DepthBeside(Depth):
    def __init__(self):
        super().__init__(beside=True)


class Cells(gymnasium.Env):
    """MinAtar's form: a 10x10 grid of 4 bool channels (channels last), 3 actions."""

    def __init__(self):
        self.observation_space = spaces.Box(0, 1, (10, 10, 4), np.bool_)
        self.action_space = spaces.Discrete(3)

    def reset(self, seed=None, options=None):
        super().reset(seed=seed)
        return self.observation_space.sample(), {}

    def step(self, action):
        return self.observation_space.sample(), 0.0, False, True, {}


class Dot(gymnasium.Env):
    """A 12x12 grey picture of a point to be driven to its centre: continuous actions, the position in the picture
    alone; reward minus the distance to the centre, 30 steps."""

    SIZE = 12

    def __init__(self):
        self.observation_space = spaces.Box(0, 255, (self.SIZE, self.SIZE), np.uint8)
        self.action_space = spaces.Box(-1.0, 1.0, (2,), np.float32)

    def observe(self, position):
        image = np.zeros((self.SIZE, self.SIZE), np.uint8)
        i, j = np.round((np.asarray(position) + 1) / 2 * (self.SIZE - 2)).astype(int)
        image[i:i + 2, j:j + 2] = 255
        return image

    def reset(self, seed=None, options=None):
        super().reset(seed=seed)
        self.position = self.np_random.uniform(-1, 1, 2)
        self.t = 0
        return self.observe(self.position), {}

    def step(self, action):
        self.position = np.clip(self.position + 0.15 * np.clip(action, -1, 1), -1, 1)
        self.t += 1
        return self.observe(self.position), -float(np.linalg.norm(self.position)), False, self.t >= 30, {}


class Counter(gymnasium.Env):
    """A Dict of a vector, a Discrete that starts at 1 and a MultiDiscrete (read one-hot), continuous actions."""

    def __init__(self):
        self.observation_space = spaces.Dict(position=spaces.Box(-1.0, 1.0, (2,), np.float32),
                                             heading=spaces.Discrete(4, start=1), keys=spaces.MultiDiscrete([2, 3]))
        self.action_space = spaces.Box(-1.0, 1.0, (1,), np.float32)

    def reset(self, seed=None, options=None):
        super().reset(seed=seed)
        self.observation_space.seed(seed)
        return self.observation_space.sample(), {}

    def step(self, action):
        return self.observation_space.sample(), 0.0, False, True, {}


class Lives:
    def __init__(self, game):
        self.game = game

    def lives(self):
        return self.game.lives


class Serve(gymnasium.Env):
    """A game of 3 lives in ALE's form (``ale.lives()``, ``get_action_meanings``): the ball is served by FIRE,
    then a life is lost 5 steps later unless the player hits it (action 2), which pays 1."""

    def __init__(self):
        self.observation_space = spaces.Box(-1.0, 100.0, (2,), np.float32)
        self.action_space = spaces.Discrete(3)
        self.ale = Lives(self)

    def get_action_meanings(self):
        return ["NOOP", "FIRE", "HIT"]

    def _obs(self):
        return np.array([self.lives, self.in_play], np.float32)

    def reset(self, seed=None, options=None):
        super().reset(seed=seed)
        self.lives, self.in_play, self.resets = 3, -1, getattr(self, "resets", 0) + 1
        return self._obs(), {}

    def step(self, action):
        reward = 0.0
        if self.in_play < 0 and action == 1:
            self.in_play = 0
        elif self.in_play >= 0:
            self.in_play += 1
            if action == 2:
                reward, self.in_play = 1.0, 0
            elif self.in_play >= 5:
                self.lives, self.in_play = self.lives - 1, -1
        return self._obs(), reward, self.lives == 0, False, {}
'''


@pytest.fixture(scope="module")
def envs_module(tmp_path_factory):
    folder = tmp_path_factory.mktemp("user_envs")
    (folder / f"{MODULE}.py").write_text(textwrap.dedent(ENVS_PY))
    sys.path.insert(0, str(folder))
    yield MODULE
    sys.path.remove(str(folder))


def test_dict_entries_are_joined_in_the_env_order_and_named_keys_select(envs_module):
    env = make_env(f"{envs_module}:GoalPoint", seed=0)
    assert env.observation_spec["observation"].shape == (3,)  # observation, achieved_goal, desired_goal
    only = make_env(f"{envs_module}:GoalPoint", observation_keys=["observation", "desired_goal"])
    assert only.observation_spec["observation"].shape == (2,)
    with pytest.raises(EnvError, match="'label' as Text"):
        make_env(f"{envs_module}:Labelled")
    with pytest.raises(EnvError, match="does not observe"):
        make_env(f"{envs_module}:GoalPoint", observation_keys=["velocity"])
    assert make_env(f"{envs_module}:Labelled", observation_keys=["position"]).observation_spec["observation"].shape == (2,)


def test_her_relabels_with_a_later_goal_of_the_same_episode():
    """Two episodes interleaved block by block (as two collector workers give them): each relabelled goal is an
    achieved goal of the transition's own episode, at that step or later, and the reward is compute_reward's."""
    def reward(achieved, desired, info):
        return -(np.abs(achieved - desired)[..., 0] > 0.5).astype(np.float32)

    # observation = [achieved, desired]; episode e's achieved goal at step t is 100 * e + t
    def block(episode, steps, last):
        achieved = torch.tensor([100.0 * episode + t for t in steps])
        obs = torch.stack([achieved - 1, torch.full_like(achieved, -7.0)], -1)
        nxt = torch.stack([achieved, torch.full_like(achieved, -7.0)], -1)
        done = torch.tensor([t == last for t in steps]).unsqueeze(-1)
        return TensorDict({"observation": obs, "action": torch.zeros(len(steps), 1), TRAJ_IDS: torch.full((len(steps),), episode),
                           "next": {"observation": nxt, "reward": torch.full((len(steps), 1), -1.0), "done": done,
                                    "terminated": torch.zeros_like(done)}}, batch_size=[len(steps)])

    from torchrl.data import LazyTensorStorage

    from rlpipe.pipelines.artifacts import checkpoint as ckpt

    rb = HindsightReplayBuffer(storage=LazyTensorStorage(100), batch_size=64, compute_reward=reward, achieved=(0, 1),
                               desired=(1, 2), her_ratio=1.0)
    rb.extend(torch.cat([block(1, range(0, 3), 5), block(2, range(0, 3), 5)]))
    assert len(rb) == 0 and len(rb.pending) == 2  # episodes wait for their end
    resumed = HindsightReplayBuffer(storage=LazyTensorStorage(100), batch_size=64, compute_reward=reward,
                                    achieved=(0, 1), desired=(1, 2), her_ratio=1.0)
    ckpt.load_replay_buffer(resumed, ckpt.replay_buffer_state(rb))  # a checkpoint keeps the episodes under way
    assert {k: torch.cat(v)["observation"].tolist() for k, v in resumed.pending.items()} == {
        k: torch.cat(v)["observation"].tolist() for k, v in rb.pending.items()}
    rb.extend(torch.cat([block(1, range(3, 6), 5), block(2, range(3, 6), 5)]))
    assert len(rb) == 12 and not rb.pending
    torch.manual_seed(0)
    batch = rb.sample()
    achieved = batch["next", "observation"][:, 0]
    goal = batch["observation"][:, 1]
    assert torch.equal(goal, batch["next", "observation"][:, 1])
    assert (torch.div(goal, 100, rounding_mode="floor") == torch.div(achieved, 100, rounding_mode="floor")).all()
    assert (goal >= achieved).all() and (goal > achieved).any() and (goal == achieved).any()
    expected = torch.as_tensor(reward(achieved.numpy()[:, None], goal.numpy()[:, None], {})).unsqueeze(-1)
    assert torch.equal(batch["next", "reward"], expected)
    assert STEPS_LEFT not in batch.keys(True)


def test_goal_env_trains_with_her_and_reports_success(envs_module, tmp_path):
    cfg = sac.preset("sac-pendulum")
    cfg.env = f"{envs_module}:GoalPoint"
    cfg.num_iterations, cfg.initial_collect_steps, cfg.eval_interval, cfg.num_eval_episodes = 1500, 500, 1500, 10
    cfg.target_return = None
    pipeline = sac.SAC(cfg)
    assert isinstance(pipeline.replay_buffer, HindsightReplayBuffer)
    result = pipeline.train(tmp_path / "run", progress=False)
    assert result.summary["final_success_rate"] >= 0.7  # a random agent: ~0.1
    assert "success_rate" in (tmp_path / "run" / "metrics.csv").read_text().splitlines()[0]
    policy, info = load_policy(tmp_path / "run" / "policy")
    assert info["observation_entries"] == {"observation": [0, 1], "achieved_goal": [1, 2], "desired_goal": [2, 3]}
    assert policy(np.zeros(3, np.float32)).shape == (1,)
    import onnxruntime  # the ONNX file takes the env's own observation: its entries by name

    session = onnxruntime.InferenceSession(str(tmp_path / "run" / "policy" / "policy.onnx"))
    assert [i.name for i in session.get_inputs()] == ["observation", "achieved_goal", "desired_goal"]
    entries = {"observation": np.array([0.1], np.float32), "achieved_goal": np.array([0.1], np.float32),
               "desired_goal": np.array([-0.5], np.float32)}
    np.testing.assert_allclose(policy(entries), policy(np.array([0.1, 0.1, -0.5], np.float32)), rtol=1e-6)
    raw = session.run(None, {k: v[None] for k, v in entries.items()})[0][0]
    np.testing.assert_allclose(raw, policy(entries), rtol=1e-5, atol=1e-6)


def test_her_refused_for_an_env_without_goals(tmp_path, capsys):
    code = main(["train", "sac-pendulum", "her=true", "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "her=true" in err[0] and "not a goal env" in err[0]
    assert not (tmp_path / "run").exists()


def test_image_env_trains_dqn_through_a_cnn_with_uint8_frames(envs_module, tmp_path):
    cfg = dqn.preset("dqn")
    cfg.env = f"{envs_module}:PixPoint"
    cfg.frame_stack = 2
    cfg.num_iterations, cfg.initial_collect_steps, cfg.eval_interval, cfg.num_eval_episodes = 200, 100, 200, 2
    pipeline = dqn.DQN(cfg)
    assert pipeline.image_shape == (6, 48, 48) and pipeline.observation_dim == 256  # the Nature network from 36 px
    assert not pipeline.loss_module.lean  # the stock TorchRL loss runs the encoder
    pipeline.train(tmp_path / "run", progress=False)
    rb = pipeline.replay_buffer  # each frame once, uint8 (modules/frames.py)
    assert rb.frames.dtype == torch.uint8 and rb.frames.shape[1:] == (3, 48, 48)
    assert "observation" not in rb.storage._storage.keys() and rb.sample()["observation"].dtype == torch.uint8
    info = json.loads((tmp_path / "run" / "policy" / "policy.json").read_text())
    assert info["observation_shape"] == [6, 48, 48] and info["observation_dtype"] == "uint8"
    policy, _ = load_policy(tmp_path / "run" / "policy")  # ONNX, checked against torch when written
    frames = make_env(f"{envs_module}:PixPoint", frame_stack=2).reset()["observation"]
    assert policy(frames.numpy()).shape == ()


def test_atari_lives_end_training_episodes_and_fire_serves_every_life(envs_module):
    """A game that waits for FIRE: each life starts served, so a policy that never fires still ends its game;
    in training each lost life ends the episode and the next reset carries on with the same game."""
    game = importlib.import_module(envs_module).Serve()
    whole = FireOnLifeStart(game)  # evaluation
    obs, _ = whole.reset(seed=0)
    assert obs[1] == 0  # served
    steps, done = 0, False
    while not done:
        obs, reward, done, _, _ = whole.step(0)
        steps += 1
    assert steps == 15 and game.lives == 0  # three lives, each served by the env, lost 5 steps later

    lives = FireOnLifeStart(EpisodicLife(game))  # training
    lives.reset(seed=0)
    resets, lengths = game.resets, []
    for _ in range(4):
        n, done = 0, False
        while not done:
            _, _, done, _, _ = lives.step(0)
            n += 1
        lengths.append((n, game.lives))
        lives.reset()
    assert lengths[:3] == [(5, 2), (5, 1), (5, 0)]  # one life an episode
    assert game.resets == resets + 1  # the game went on across the first two resets, restarted after the last life


@pytest.mark.skipif(importlib.util.find_spec("ale_py") is None, reason="needs rlpipe[atari] (ale-py)")
def test_atari_trains_on_lives_and_evaluates_whole_games(tmp_path):
    cfg = dqn.preset("dqn-atari")
    cfg.replay_buffer_capacity = 1000
    pipeline = dqn.DQN(cfg)
    train_env, eval_env = (gym_env_under(e) for e in (pipeline.env, pipeline.eval_env))
    assert any(isinstance(layer, EpisodicLife) for layer in _layers(train_env))
    assert not any(isinstance(layer, EpisodicLife) for layer in _layers(eval_env))
    assert any(isinstance(layer, FireOnLifeStart) for layer in _layers(eval_env))


def _layers(env):
    while env is not None:
        yield env
        env = getattr(env, "env", None)


def test_a_box_whose_values_do_not_fit_in_a_byte_is_read_as_a_matrix_not_wrapped_into_an_image(envs_module, tmp_path):
    """An image is stored and exported as uint8; a uint16 depth camera's 3,000 mm would wrap to 184. It is read
    as SB3 reads it (every Box but a uint8 one): flattened into the float vector, its values as the env gives them."""
    from gymnasium import spaces

    from rlpipe.envs.observations import is_image, observation_images
    from rlpipe.pipelines.artifacts.export import export_policy

    alone = make_env(f"{envs_module}:Depth", seed=0)
    assert alone.observation_spec["observation"].dtype == torch.float32
    values = alone.reset()["observation"]
    assert values.shape == (36,) and values[0] == 260 and values[1] == 3000
    beside = make_env(f"{envs_module}:DepthBeside", seed=0)
    values = beside.reset()["observation"]
    assert values.shape == (37,) and values[0] == 260 and values[35] == 3000
    assert observation_images(gym_env_under(beside)) == {}  # no CNN span: the depth is a vector entry
    cfg = dqn.preset("dqn")
    cfg.env = f"{envs_module}:DepthBeside"
    pipeline = dqn.DQN(cfg)
    export_policy(pipeline.exported_policy(), pipeline.observation_shape, tmp_path, pipeline.export_info(),
                  entries=pipeline.observation_entries(), images=pipeline.observation_entry_images())
    policy, _ = load_policy(tmp_path)  # takes the env's own Dict, the matrix entry as the env gives it
    raw = gym_env_under(beside).unwrapped._obs()
    with torch.no_grad():
        expected = pipeline.exported_policy()(values.unsqueeze(0))[0]
    assert json.loads((tmp_path / "policy.json").read_text())["inputs"] == {"depth": [36], "joint": [1]}
    assert policy(raw) == expected.item() and policy({k: np.stack([v, v]) for k, v in raw.items()}).shape == (2,)
    assert is_image(spaces.Box(0, 255, (6, 6), np.uint8)) and is_image(spaces.Box(0, 1, (6, 6, 4), bool))
    assert is_image(spaces.Box(0, 9, (6, 6), np.int64)) and not is_image(spaces.Box(-1, 9, (6, 6), np.int64))


def test_small_images_get_the_small_encoder():
    from rlpipe.modules.encoders import make_image_encoder

    encoder = make_image_encoder((4, 10, 10), 1.0)
    assert len(list(encoder.convolutions)) == 2 and encoder(torch.zeros(3, 4, 10, 10, dtype=torch.uint8)).shape == (3, 1024)


def _image_steps(envs_module, seed: int, traj_offset: int, steps: int = 120) -> TensorDict:
    env = make_env(f"{envs_module}:PixPoint", frame_stack=3, seed=seed)
    rollout = env.rollout(steps, break_when_any_done=False)
    starts = rollout["is_init"].reshape(-1).long()
    rollout.set(TRAJ_IDS, traj_offset + starts.cumsum(0))
    return rollout


def test_frame_buffer_stores_each_frame_once_and_gives_back_the_stacks(envs_module):
    """Two envs' steps interleaved block by block, as two collector workers give them: every transition comes
    back with the observation and next observation it was stored with; one frame per step is stored; a
    checkpoint's state refills a fresh buffer that gives the same stacks."""
    from torchrl.data import LazyTensorStorage

    from rlpipe.modules.frames import FrameReplayBuffer
    from rlpipe.pipelines.artifacts import checkpoint as ckpt

    a, b = _image_steps(envs_module, 0, 0), _image_steps(envs_module, 1, 1000)
    blocks = [part for i in range(0, 120, 40) for part in (a[i:i + 40], b[i:i + 40])]

    def buffer(memmap=False):
        return FrameReplayBuffer(storage=LazyTensorStorage(500), batch_size=32, capacity=500, frame_stack=3,
                                 channels=3, memmap=memmap)

    rb = buffer(memmap=True)  # replay_buffer_storage=memmap: the ring in a file, unlinked once mapped
    for block in blocks[:1]:
        rb.extend(block)
    assert rb.frames.untyped_storage().filename is not None and not os.path.exists(rb.frames.untyped_storage().filename)
    rb = buffer()
    for block in blocks:
        rb.extend(block)
    episodes = int(a["is_init"].sum() + b["is_init"].sum())
    assert rb.written <= 240 + 3 * episodes  # a frame a step, and at most a stack where an episode starts
    expected = torch.cat(blocks)
    got = rb._stacked(rb.storage.get(torch.arange(len(rb))))
    assert torch.equal(got["observation"], expected["observation"])
    assert torch.equal(got["next", "observation"], expected["next", "observation"])
    again = buffer()
    ckpt.load_replay_buffer(again, ckpt.replay_buffer_state(rb))
    assert torch.equal(again._stacked(again.storage.get(torch.arange(len(again))))["observation"], got["observation"])


def test_frame_buffer_never_returns_a_transition_whose_frames_were_overwritten(envs_module):
    from torchrl.data import LazyTensorStorage

    from rlpipe.modules.frames import FrameReplayBuffer

    rb = FrameReplayBuffer(storage=LazyTensorStorage(100), batch_size=64, capacity=100, frame_stack=3, channels=3,
                           frame_headroom=2)
    steps = _image_steps(envs_module, 0, 0, steps=300)
    steps.set("row", torch.arange(300))
    for i in range(0, 300, 10):
        rb.extend(steps[i:i + 10])
    assert rb.written > rb.frame_capacity  # the ring went round: some stored transitions lost frames
    torch.manual_seed(0)
    for _ in range(20):
        batch = rb.sample()
        assert torch.equal(batch["observation"], steps["observation"][batch["row"]])
        assert torch.equal(batch["next", "observation"], steps["next", "observation"][batch["row"]])


def test_running_normalisation_is_shared_by_every_network_and_exported(envs_module, tmp_path):
    """normalize_observations=true: the statistics are the blocks' running mean and variance, every critic copy
    inside TorchRL's loss reads the same ones, and the exported policy normalises the env's own observation."""
    from rlpipe.modules.normalization import RunningObservationNorm

    norm = RunningObservationNorm(2)
    data = torch.randn(300, 2) * torch.tensor([3.0, 0.1]) + torch.tensor([5.0, -1.0])
    for part in data.split(70):
        norm.update(part)
    torch.testing.assert_close(norm.observation_mean, data.mean(0), rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(norm.observation_var, data.var(0, unbiased=False), rtol=1e-3, atol=1e-4)

    cfg = sac.preset("sac-pendulum")
    cfg.num_iterations, cfg.initial_collect_steps, cfg.eval_interval, cfg.num_eval_episodes = 300, 200, 300, 2
    cfg.target_return, cfg.normalize_observations = None, True
    pipeline = sac.SAC(cfg)
    assert len(pipeline.normalizer.mirrors) >= 6  # twin critics and their targets: mean, var and count each
    pipeline.train(tmp_path / "run", progress=False)
    mean = pipeline.normalizer.observation_mean
    assert mean.abs().sum() > 0
    for name, mirror in pipeline.normalizer.mirrors:
        assert torch.equal(mirror, getattr(pipeline.normalizer, name).expand_as(mirror)), name
    exported = pipeline.exported_policy()
    assert any(key.endswith("observation_mean") for key in exported.state_dict())  # the statistics travel with it
    policy, _ = load_policy(tmp_path / "run" / "policy")
    observation = torch.tensor([0.5, -0.5, 1.0])
    expected = pipeline.exported_policy()(observation.unsqueeze(0))[0]
    torch.testing.assert_close(policy(observation), expected, rtol=1e-4, atol=1e-5)



def test_an_image_beside_vectors_is_read_by_a_cnn_and_exported_as_the_env_gives_it(envs_module, tmp_path):
    """A Dict with an image among its entries: the image joins the vector channels first, each network reads its
    span through a CNN and the vectors as they are, and the exported policy takes the entries by name, the image as
    uint8 in the env's own layout (channels last here)."""
    from rlpipe.modules.encoders import DictEncoder
    from rlpipe.pipelines.artifacts.export import export_policy

    env = make_env(f"{envs_module}:Camera", seed=0)
    assert env.observation_spec["observation"].shape == (3 + 3 * 40 * 40,)
    cfg = sac.preset("sac-pendulum")
    cfg.env = f"{envs_module}:Camera"
    pipeline = sac.SAC(cfg)
    assert pipeline.observation_dim == 3 + 64 * 1 * 1  # joints, then the Nature convolutions' maps (40 px: 1x1)
    assert any(isinstance(m, DictEncoder) for m in pipeline.policy.modules())
    assert pipeline.shared_encoder is not None  # actor and critics read one (test_sac_from_pixels_shares_...)
    raw, _ = gym_env_under(env).unwrapped.reset(seed=1)
    joined = torch.as_tensor(gym_env_under(env).observation(raw))
    torch.testing.assert_close(joined[3:].reshape(3, 40, 40), torch.as_tensor(raw["camera"]).permute(2, 0, 1).float())
    export_policy(pipeline.exported_policy(), pipeline.observation_shape, tmp_path, pipeline.export_info(),
                  entries=pipeline.observation_entries(), images=pipeline.observation_entry_images())
    info = json.loads((tmp_path / "policy.json").read_text())
    assert info["inputs"] == {"joints": [3], "camera": [40, 40, 3]}
    assert info["image_inputs"] == {"camera": {"shape": [40, 40, 3], "channels_last": True}}
    policy, _ = load_policy(tmp_path)  # ONNX, checked against torch on random inputs when written
    with torch.no_grad():
        expected = pipeline.exported_policy()(joined.unsqueeze(0))[0]
    torch.testing.assert_close(policy(raw), expected.numpy(), rtol=1e-4, atol=1e-5, check_dtype=False)
    torch.testing.assert_close(policy(joined), expected, rtol=1e-4, atol=1e-5)
    import onnxruntime

    session = onnxruntime.InferenceSession(str(tmp_path / "policy.onnx"))
    assert [(i.name, i.type) for i in session.get_inputs()] == [("joints", "tensor(float)"), ("camera", "tensor(uint8)")]
    action = session.run(None, {k: v[None] for k, v in raw.items()})[0][0]
    np.testing.assert_allclose(action, expected.numpy(), rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("algo", ["sac", "td3"])
def test_from_pixels_actor_and_critics_share_one_encoder_that_the_critics_loss_alone_trains(envs_module, algo):
    """SAC and TD3 on an image (a Dict with a camera among its entries): one encoder in front of the actor and both
    critics, run once per update on the observations (DrQ's choice). The gradient it steps on is the critics' loss's
    alone (the actor's loss reads its features detached); the stock TorchRL path (fast=false) gives the lean path's
    numbers; a checkpoint carries it. share_encoder=false: each network an encoder of its own."""
    module = {"sac": sac, "td3": td3}[algo]

    def pipeline(**keys):
        cfg = module.preset(f"{algo}-pendulum")
        cfg.env = f"{envs_module}:Camera"
        for key, value in keys.items():
            setattr(cfg, key, value)
        return module.SAC(cfg) if algo == "sac" else module.TD3(cfg)

    lean, stock = pipeline(), pipeline(fast=False)
    encoder = lean.shared_encoder
    assert encoder is not None and getattr(lean.loss_module, "lean", True)
    assert any(m is encoder for m in lean.collect_policy.modules()) and any(m is encoder for m in lean.policy.modules())
    critic = [".".join(k) for k in lean.loss_module.qvalue_network_params.keys(True, True)]
    assert not any("encoder" in k for k in critic) and "encoder" in lean.optimizers
    assert set(lean.replay_keys) >= {"observation", ("next", "observation")}  # features are never stored
    torch.manual_seed(0)
    batch = lean.env.rollout(32, break_when_any_done=False)
    cfg = lean.config
    actor_step = cfg.policy_delay * getattr(cfg, "target_update_period", 1)  # the actor and the critics step
    outs = []
    for pipe in (lean, stock):
        torch.manual_seed(1)
        outs.append(pipe.update(batch.clone(), actor_step))
    assert set(outs[0]) == ({"actor", "qvalue", "alpha", "alpha_value", "entropy"} if algo == "sac" else {"actor", "qvalue"})
    for key in outs[0]:
        torch.testing.assert_close(outs[0][key], outs[1][key], rtol=1e-4, atol=1e-5)
    # Adam's first step moves a weight by about the learning rate whatever its gradient's size: a gradient within
    # float noise of zero may move it by less on one side, so the weights agree to a tenth of a step
    step = cfg.critic_learning_rate if algo == "sac" else cfg.learning_rate
    for mine, theirs in zip(lean.shared_encoder.parameters(), stock.shared_encoder.parameters(), strict=True):
        torch.testing.assert_close(mine, theirs, rtol=0, atol=0.1 * step)

    torch.manual_seed(2)
    features_batch, _ = lean.encode(batch.clone())
    critics_loss = (lean.loss_module.qvalue_v2_loss if algo == "sac" else lean.loss_module.value_loss)(features_batch)[0]
    params = list(encoder.parameters())
    expected = torch.autograd.grad(critics_loss, params)
    seen = {}
    hooks = [p.register_hook(lambda grad, i=i: seen.__setitem__(i, seen.get(i, 0) + grad)) for i, p in enumerate(params)]
    torch.manual_seed(2)
    lean.update(batch.clone(), actor_step)
    for hook in hooks:
        hook.remove()
    for i, grad in enumerate(expected):
        torch.testing.assert_close(seen[i], grad, rtol=1e-4, atol=1e-7)

    resumed = pipeline()  # a checkpoint carries the encoder (in the policy's state) and its optimiser
    resumed.load_state_dict(lean.state_dict())
    for mine, theirs in zip(lean.shared_encoder.parameters(), resumed.shared_encoder.parameters(), strict=True):
        assert torch.equal(mine, theirs)
    moments = [state["exp_avg"] for state in resumed.optimizers["encoder"].state_dict()["state"].values()]
    assert moments and all(torch.equal(a, b["exp_avg"]) for a, b in
                           zip(moments, lean.optimizers["encoder"].state_dict()["state"].values(), strict=True))

    own = pipeline(share_encoder=False)
    assert own.shared_encoder is None and "encoder" not in own.optimizers
    assert algo != "sac" or not own.loss_module.lean  # TorchRL's own loss code runs networks with encoders
    critic = [".".join(k) for k in own.loss_module.qvalue_network_params.keys(True, True)]
    assert any("encoder" in k for k in critic)


@pytest.mark.parametrize("algo,keys", [("sac", {}), ("td3", {}), ("td3", {"deterministic_policy": False})])
def test_a_picture_alone_updates_with_a_shared_encoder_and_with_one_per_network(envs_module, algo, keys):
    """A picture not joined into a vector (Dot, 12x12): the update runs on it with the shared encoder and with an
    encoder in each network (the loss then calls the networks on the picture itself), fast path or TorchRL's."""
    module = {"sac": sac, "td3": td3}[algo]
    for share, fast in [(True, True), (False, True), (False, False)]:
        cfg = module.preset(f"{algo}-pendulum")
        cfg.env = f"{envs_module}:Dot"
        for key, value in {**keys, "share_encoder": share, "fast": fast}.items():
            setattr(cfg, key, value)
        pipeline = module.SAC(cfg) if algo == "sac" else module.TD3(cfg)
        assert (pipeline.shared_encoder is not None) == share
        torch.manual_seed(0)
        batch = pipeline.env.rollout(16, break_when_any_done=False)
        out = pipeline.update(batch, cfg.policy_delay * getattr(cfg, "target_update_period", 1))
        assert "actor" in out and all(torch.isfinite(value).all() for value in out.values()), (share, fast, out)


@pytest.mark.slow
def test_sac_learns_from_pixels_through_the_shared_encoder(envs_module, tmp_path):
    """The sized default on Dot (a picture of a point, continuous actions; SAC, one encoder shared by the actor and
    the critics): the exported policy, given the env's own pictures, drives the point from each corner to the
    centre."""
    assert main(["train", f"env={envs_module}:Dot", "num_iterations=1500", "batch_size=64",
                 "--out", str(tmp_path / "run")]) == 0
    config = json.loads((tmp_path / "run" / "config.json").read_text())["config"]
    assert config["share_encoder"] is True
    policy, _ = load_policy(tmp_path / "run" / "policy")
    dot = sys.modules[envs_module].Dot()
    for corner in [(-0.9, -0.9), (-0.9, 0.9), (0.9, -0.9), (0.9, 0.9)]:
        position = np.array(corner)
        for _ in range(15):
            position = np.clip(position + 0.15 * np.clip(policy(dot.observe(position)), -1, 1), -1, 1)
        assert np.linalg.norm(position) < 0.3, f"from {corner} the policy left the point at {position}"


def test_the_exported_policy_takes_the_envs_own_frame_and_discrete_values(envs_module, tmp_path):
    """An image of one frame: the exported policy takes it as the env gives it (HxWxC uint8, MinAtar's bool grid), and
    rlpipe's channels-first stack too; a Dict's Discrete and MultiDiscrete entries go in as the env's integers. A
    wrong shape is one line naming the one expected."""
    import onnxruntime

    from rlpipe.pipelines.artifacts.export import export_policy

    class Probe(torch.nn.Module):  # a linear map of every pixel: a channel put in the wrong place changes its output
        def __init__(self, size):
            super().__init__()
            self.linear = torch.nn.Linear(size, 4)

        def forward(self, stacks):
            return self.linear(stacks.flatten(1).to(torch.float32) / 255)

    for name, shape in (("PixPoint", [48, 48, 3]), ("Cells", [10, 10, 4])):
        cfg = dqn.preset("dqn")
        cfg.env = f"{envs_module}:{name}"
        pipeline = dqn.DQN(cfg)
        assert pipeline.export_inputs() == {"frame": (tuple(shape), True)}
        env = getattr(sys.modules[envs_module], name)()
        env.observation_space.seed(0)  # the env's own frames, each drawn from its space
        frames = np.stack([env.observation_space.sample() for _ in range(6)])
        stacks = torch.as_tensor(frames).permute(0, 3, 1, 2).to(torch.uint8)  # channels first, as rlpipe's env gives
        torch.manual_seed(0)
        probe = Probe(math.prod(shape))
        with torch.no_grad():
            expected = probe(stacks)
        export_policy(probe, pipeline.observation_shape, tmp_path / name, pipeline.export_info(),
                      dtype=pipeline.observation_dtype, **pipeline.export_inputs())
        policy, info = load_policy(tmp_path / name)
        assert info["inputs"] == {"observation": shape} and info["image_input"]["channels_last"]
        torch.testing.assert_close(policy(frames), expected.numpy(), rtol=1e-4, atol=1e-5, check_dtype=False)
        torch.testing.assert_close(policy(frames[3]), expected[3].numpy(), rtol=1e-4, atol=1e-5, check_dtype=False)
        torch.testing.assert_close(policy(stacks), expected, rtol=1e-4, atol=1e-5)
        session = onnxruntime.InferenceSession(str(tmp_path / name / "policy.onnx"))
        np.testing.assert_allclose(session.run(None, {"observation": frames.astype(np.uint8)})[0], expected.numpy(),
                                   rtol=1e-4, atol=1e-5)
        with pytest.raises(ValueError, match=re.escape(f"takes {shape}")):
            policy(frames[:, :5])
        export_policy(pipeline.exported_policy(), pipeline.observation_shape, tmp_path / name, pipeline.export_info(),
                      dtype=pipeline.observation_dtype, **pipeline.export_inputs())  # the DQN's own: its greedy action
        assert load_policy(tmp_path / name)[0](frames[0]).shape == ()

    cfg = sac.preset("sac-pendulum")
    cfg.env = f"{envs_module}:Counter"
    pipeline = sac.SAC(cfg)
    export_policy(pipeline.exported_policy(), pipeline.observation_shape, tmp_path / "counter", pipeline.export_info(),
                  **pipeline.export_inputs())
    policy, info = load_policy(tmp_path / "counter")
    assert info["inputs"] == {"position": [2], "heading": [], "keys": [2]}
    env = make_env(f"{envs_module}:Counter", seed=0)
    own = [gym_env_under(env).unwrapped.reset(seed=seed)[0] for seed in range(8)]
    joined = torch.as_tensor(np.stack([gym_env_under(env).observation(o) for o in own]))
    with torch.no_grad():
        expected = pipeline.exported_policy()(joined)
    for o, action in zip(own, expected):
        torch.testing.assert_close(policy(o), action.numpy(), rtol=1e-4, atol=1e-5, check_dtype=False)
    torch.testing.assert_close(policy(joined), expected, rtol=1e-4, atol=1e-5)
    session = onnxruntime.InferenceSession(str(tmp_path / "counter" / "policy.onnx"))
    raw = session.run(None, {k: np.asarray(v, np.float32 if k == "position" else np.int64)[None] for k, v in own[0].items()})
    np.testing.assert_allclose(raw[0][0], expected[0].numpy(), rtol=1e-4, atol=1e-5)
    with pytest.raises(ValueError, match="without 'keys'"):
        policy({"position": own[0]["position"], "heading": 1})
    with pytest.raises(ValueError, match=r"entry 'heading' of shape \[4\]: a batch of \[4\]"):  # one-hot, not its value
        policy({**own[0], "heading": np.eye(4)[0]})


@pytest.mark.parametrize("override, expected", [
    ("frame_stack=2", "frame_stack=2: env .* observes a Dict of 2 entries"),
    ("normalize_observations=true", "normalize_observations=true: .* observes an image"),
])
def test_what_an_image_in_a_dict_cannot_have_is_one_line(envs_module, tmp_path, capsys, override, expected):
    code = main(["train", "sac-pendulum", f"env={envs_module}:Camera", override, "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and re.search(expected, err[0]), err
    assert not (tmp_path / "run").exists()


@pytest.mark.slow
def test_a_dict_of_an_image_and_a_vector_trains_on_both(envs_module, tmp_path):
    """The sized default on Beacon (the goal only in the picture, the walker only in the number): the greedy policy
    walks toward the goal from every cell two or more away, which neither entry alone tells it."""
    assert main(["train", f"env={envs_module}:Beacon", "num_iterations=4000", "--out", str(tmp_path / "run")]) == 0
    policy, _ = load_policy(tmp_path / "run" / "policy")
    beacon = sys.modules[envs_module].Beacon()
    pairs = [(goal, x) for goal in range(11) for x in range(11) if abs(goal - x) >= 2]
    toward = [int(policy(beacon.observe(goal, x))) == int(goal > x) for goal, x in pairs]
    assert sum(toward) >= 0.9 * len(pairs), f"{sum(toward)} of {len(pairs)} toward the goal"
