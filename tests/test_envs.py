"""The env factory: gymnasium ids -> TorchRL envs with the standard transforms, ready for any collector."""

from __future__ import annotations

import gymnasium
import pytest
import torch
from torchrl.collectors import Collector
from torchrl.envs import DoubleToFloat, InitTracker, RewardSum, StepCounter, TransformedEnv

from rlpipe.envs import MINITAUR_ID, EnvError, is_discrete, make_env, resolve_env_id


def _transform_types(env: TransformedEnv) -> list[type]:
    return [type(t) for t in env.transform]


def test_cartpole_has_the_standard_transforms_float_observations_and_integer_actions():
    env = make_env("CartPole-v0", seed=0)
    assert isinstance(env, TransformedEnv)
    types = _transform_types(env)
    for cls in (StepCounter, RewardSum, InitTracker):
        assert cls in types, f"{cls.__name__} missing from {types}"
    assert DoubleToFloat not in types  # nothing of CartPole's is float64: no per-step cost for nothing
    assert env.observation_spec["observation"].dtype == torch.float32
    assert env.observation_spec["observation"].shape == (4,)
    assert is_discrete(env)
    assert env.action_spec.space.n == 2

    rollout = env.rollout(50)  # random actions until done
    assert rollout["observation"].dtype == torch.float32
    actions = rollout["action"]
    assert actions.dtype == torch.int64 and actions.shape == rollout.shape  # indices, not one-hot
    assert set(actions.tolist()) <= {0, 1}
    # the transforms' outputs are there
    steps = rollout["next", "step_count"].squeeze(-1)
    assert steps.tolist() == list(range(1, rollout.shape[0] + 1))
    assert rollout["next", "episode_reward"][-1].item() == pytest.approx(rollout["next", "reward"].sum().item())
    assert rollout["is_init"][0].item() is True
    env.close()


def test_float64_observations_become_float32_through_double_to_float():
    # MuJoCo's observations are float64; the networks read float32
    env = make_env("HalfCheetah-v5", seed=0)
    assert DoubleToFloat in _transform_types(env)
    assert env.observation_spec["observation"].dtype == torch.float32
    assert env.rollout(3)["next", "observation"].dtype == torch.float32
    env.close()


def test_double_observations_become_float32():
    gym_env = gymnasium.make("InvertedPendulum-v5")
    assert gym_env.observation_space.dtype == "float64"
    gym_env.close()
    env = make_env("InvertedPendulum-v5", seed=0)
    assert env.observation_spec["observation"].dtype == torch.float32
    assert env.reset()["observation"].dtype == torch.float32
    assert env.rollout(5)["next", "observation"].dtype == torch.float32
    assert not is_discrete(env)
    env.close()


def test_same_seed_same_episode():
    a, b = make_env("CartPole-v1", seed=3), make_env("CartPole-v1", seed=3)
    torch.testing.assert_close(a.reset()["observation"], b.reset()["observation"])
    c = make_env("CartPole-v1", seed=4)
    assert not torch.equal(make_env("CartPole-v1", seed=3).reset()["observation"], c.reset()["observation"])


@pytest.mark.parametrize("env_id, discrete", [("CartPole-v0", True), ("Acrobot-v1", True), ("Pendulum-v1", False),
                                              ("MountainCarContinuous-v0", False)])
def test_is_discrete(env_id, discrete):
    env = make_env(env_id)
    assert is_discrete(env) is discrete
    env.close()


@pytest.mark.parametrize("env_id, close", [("CartPole-v9", "CartPole-v1"), ("CartPol-v0", "CartPole-v0"),
                                           ("Pendulum-v2", "Pendulum-v1"), ("MinitaurBulletEnv-v1", "MinitaurBulletEnv-v0")])
def test_unknown_id_names_close_matches(env_id, close):
    with pytest.raises(EnvError) as info:
        make_env(env_id)
    message = str(info.value)
    assert env_id in message and close in message
    assert isinstance(info.value, ValueError)


def test_unknown_id_without_close_match_says_what_is_expected():
    with pytest.raises(EnvError, match="gymnasium id"):
        resolve_env_id("zzzzzzzzzzzzzzzzzzzz")


def test_tutorial_minitaur_id_resolves_to_ours():
    assert resolve_env_id("MinitaurBulletEnv-v0") == MINITAUR_ID == "rlpipe/MinitaurBullet-v0"
    assert MINITAUR_ID in gymnasium.registry  # importing rlpipe.envs registers it
    assert resolve_env_id("CartPole-v1") == "CartPole-v1"
    env = make_env("MinitaurBulletEnv-v0", seed=0)
    try:
        assert env.base_env.env_name == MINITAUR_ID
        assert env.observation_spec["observation"].dtype == torch.float32
        assert not is_discrete(env)
    finally:
        env.close()


def test_env_plugs_into_a_torchrl_collector():
    collector = Collector(make_env("CartPole-v0", seed=0), None, frames_per_batch=32, total_frames=64)
    batches = list(collector)
    collector.shutdown()
    assert len(batches) == 2
    for batch in batches:
        assert batch.numel() == 32
        assert batch["action"].dtype == torch.int64
        assert batch["next", "observation"].dtype == torch.float32


def test_vector_env_steps_copies_as_one_batch_and_resets_each_on_its_own():
    env = make_env("CartPole-v1", num_envs=4, seed=0)
    assert env.batch_size == (4,) and env.action_spec_unbatched.space.n == 2
    rollout = env.rollout(60, break_when_any_done=False)
    done = rollout["next", "done"].squeeze(-1)
    assert rollout.shape == (4, 60) and done.any()
    # an episode's return is its length on CartPole, and each copy restarts after its own end
    lengths = rollout["next", "step_count"].squeeze(-1)[done]
    torch.testing.assert_close(rollout["next", "episode_reward"].squeeze(-1)[done], lengths.float())
    first_end = int(done[0].nonzero()[0])
    assert rollout["step_count"][0, first_end + 1].item() == 0
    collector = Collector(env, None, frames_per_batch=40, total_frames=80)
    assert [b.numel() for b in collector] == [40, 40]
    collector.shutdown()


# --- spaces beyond a flat Box: flattened where that means something, refused where not ----------------


@pytest.mark.parametrize("env_id, size", [("FrozenLake-v1", 16), ("Blackjack-v1", 32 + 11 + 2), ("Taxi-v4", 500)])
def test_discrete_and_tuple_observations_become_one_hot_float_vectors(env_id, size):
    env = make_env(env_id, seed=0)
    spec = env.observation_spec["observation"]
    assert spec.shape == (size,) and spec.dtype == torch.float32
    rollout = env.rollout(5)
    obs = rollout["observation"]
    assert obs.dtype == torch.float32 and set(obs.unique().tolist()) <= {0.0, 1.0}
    assert is_discrete(env)
    from rlpipe.envs import env_label

    assert env_label(env) == env_id
    env.close()


def test_dqn_trains_on_frozenlake_and_blackjack(tmp_path):
    from rlpipe.pipelines import dqn

    for env_id in ("FrozenLake-v1", "Blackjack-v1"):
        cfg = dqn.DQNConfig(env=env_id, num_iterations=100, initial_collect_steps=50, batch_size=16, eval_interval=0,
                            num_eval_episodes=2, log_interval=50, num_threads=1)
        result = dqn.DQN(cfg).train(tmp_path / env_id, progress=False)
        assert result.summary["updates"] == 100 and result.summary["env"] == env_id
        assert result.summary["final_average_return"] is not None


@pytest.mark.parametrize("env_id, obs, act", [("LunarLanderContinuous-v3", 8, 2), ("BipedalWalker-v3", 24, 4)])
def test_box2d_envs_of_the_td3_tutorial_work(env_id, obs, act):
    env = make_env(env_id, seed=0)
    assert env.observation_spec["observation"].shape == (obs,) and env.action_spec.shape[-1] == act
    assert not is_discrete(env)
    assert env.rollout(20)["next", "observation"].shape == (20, obs)
    env.close()


def test_td3_trains_on_lunar_lander_continuous(tmp_path):
    from rlpipe.pipelines import td3

    cfg = td3.TD3Config(env="LunarLanderContinuous-v3", num_iterations=100, initial_collect_steps=50, learning_starts=50,
                        batch_size=16, eval_interval=0, num_eval_episodes=1, log_interval=50, num_threads=1,
                        actor_fc_layer_params=[32], critic_fc_layer_params=[32])
    assert td3.TD3(cfg).train(tmp_path / "run", progress=False).summary["updates"] == 100


def test_atari_ids_name_the_extra_they_need():
    import importlib.util

    if importlib.util.find_spec("ale_py") is not None:
        pytest.skip("ale-py is installed here (rlpipe[atari]): ALE ids resolve")
    with pytest.raises(EnvError) as info:
        make_env("ALE/Breakout-v5")
    assert 'pip install "rlpipe[atari]"' in str(info.value) and "ALE/Breakout-v5" in str(info.value)


# --- what a run takes, from the env's specs ------------------------------------------------------------


def test_transition_bytes_come_from_the_specs():
    from rlpipe.pipelines.system.memory import transition_bytes

    env = make_env("Pendulum-v1")
    stored = ["observation", "action", ("next", "observation"), ("next", "reward"), ("next", "done"),
              ("next", "terminated")]
    # two 3-float observations, one float action, one float reward, two bools
    assert transition_bytes(env, stored) == 2 * 3 * 4 + 4 + 4 + 2
    assert transition_bytes(env) > transition_bytes(env, stored)
    assert transition_bytes(make_env("Pendulum-v1", num_envs=4), stored) == transition_bytes(env, stored)


def test_a_replay_that_does_not_fit_is_refused_before_anything_is_built(tmp_path):
    from rlpipe.pipelines import InputError, td3
    from rlpipe.pipelines.system.memory import available_bytes

    available = available_bytes("cpu")
    assert available is not None and available > 0
    capacity = available // 10  # > available at ~40 bytes a transition
    with pytest.raises(InputError) as info:
        td3.TD3(td3.TD3Config(replay_buffer_capacity=capacity))
    message = str(info.value)
    assert message.startswith(f"replay_buffer_capacity={capacity}: the replay buffer") and "available" in message
    fits = int(message.rsplit("at most about ", 1)[1])
    assert 0 < fits < capacity
    td3.TD3(td3.TD3Config(replay_buffer_capacity=min(fits // 2, 1_000_000)))  # what the line says fits, fits
