"""Tests of rlpipe's gymnasium-native Minitaur environment (real pybullet, no mocks).

The parity tests drive our env and pybullet's own ``MinitaurBulletEnv`` (loaded through
``_reference_minitaur``'s throw-away ``gym`` shim) with the same actions from the same
state and compare observations, rewards and termination step by step.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import warnings

import gymnasium
import numpy as np
import pybullet
import pytest

import rlpipe.envs  # noqa: F401  (registers rlpipe/MinitaurBullet-v0)
from rlpipe.envs.minitaur import (
    BATTERY_VOLTAGE_RANGE,
    FOOT_LINK_ID,
    MINITAUR_LEG_FRICTION,
    MOTOR_VISCOUS_DAMPING_RANGE,
    MinitaurBulletEnv,
    MinitaurEnvRandomizer,
)

sys.path.insert(0, os.path.dirname(__file__))
import _reference_minitaur  # noqa: E402

ENV_ID = "rlpipe/MinitaurBullet-v0"


@pytest.fixture
def make_env():
    """Factory whose envs are closed at teardown."""
    envs = []

    def _make(**kwargs):
        env = MinitaurBulletEnv(**kwargs)
        envs.append(env)
        return env

    yield _make
    for env in envs:
        env.close()


def gait_actions(n: int, seed: int = 0, random_every: int = 7) -> list[np.ndarray]:
    """A smooth 2 Hz trotting-like sinusoid with a uniform random action every few steps.

    The values are float32-representable (as from a float32 policy) but handed over as
    float64, so the reference (which keeps the action's dtype) and ours see the same numbers.
    """
    rng = np.random.default_rng(seed)
    phase_offsets = np.array([0.0, math.pi, math.pi, 0.0])
    actions = []
    for t in range(n):
        phase = 2 * math.pi * 2.0 * t * 0.01 + phase_offsets
        a = np.concatenate([0.3 * np.sin(phase), 0.4 * np.cos(phase)])
        if random_every and t % random_every == 0:
            a = rng.uniform(-1.0, 1.0, 8)
        actions.append(a.astype(np.float32).astype(np.float64))
    return actions


# --------------------------------------------------------------------------- API


def test_spaces(make_env):
    env = make_env()
    assert env.observation_space.shape == (28,)
    assert env.observation_space.dtype == np.float32
    assert env.action_space.shape == (8,)
    assert env.action_space.dtype == np.float32
    np.testing.assert_array_equal(env.action_space.low, -1.0)
    np.testing.assert_array_equal(env.action_space.high, 1.0)
    high = env.observation_space.high
    # angles, velocities (16 V / 0.0954 V s), observed torques, quaternion; +0.01 margin
    np.testing.assert_allclose(high[:8], math.pi + 0.01, rtol=1e-6)
    np.testing.assert_allclose(high[8:16], 16.0 / 0.0954 + 0.01, rtol=1e-6)
    np.testing.assert_allclose(high[16:24], 5.7 + 0.01, rtol=1e-6)
    np.testing.assert_allclose(high[24:], 1.01, rtol=1e-6)
    np.testing.assert_array_equal(env.observation_space.low, -high)
    assert env.time_step == pytest.approx(0.002)
    assert env.action_repeat == 5
    assert env.metadata["render_fps"] == 100


def test_reset_step_signatures(make_env):
    env = make_env()
    out = env.reset(seed=1)
    assert isinstance(out, tuple) and len(out) == 2
    obs, info = out
    assert isinstance(info, dict)
    assert obs.shape == (28,) and obs.dtype == np.float32
    assert env.observation_space.contains(obs)
    # settled in the start pose: motors near pi/2, base upright
    np.testing.assert_allclose(obs[:8], math.pi / 2, atol=0.1)
    np.testing.assert_allclose(obs[24:], [0, 0, 0, 1], atol=0.05)

    out = env.step(env.action_space.sample())
    assert len(out) == 5
    obs, reward, terminated, truncated, info = out
    assert obs.shape == (28,) and obs.dtype == np.float32
    assert type(reward) is float
    assert type(terminated) is bool and type(truncated) is bool
    assert truncated is False
    assert set(info) == {"forward_reward", "energy_reward", "drift_reward", "shake_reward"}
    assert info["energy_reward"] >= 0.0


def test_action_out_of_bounds_raises(make_env):
    env = make_env(env_randomizer=None)
    env.reset(seed=0)
    env.step(np.full(8, 1.005))  # within the reference's 0.01 tolerance
    with pytest.raises(ValueError, match="out of bounds"):
        env.step(np.array([0, 0, 1.5, 0, 0, 0, 0, 0]))
    with pytest.raises(ValueError):
        env.step(np.zeros(7))


def test_check_env_passes():
    from gymnasium.utils.env_checker import check_env

    env = gymnasium.make(ENV_ID, render_mode="rgb_array", render_width=64, render_height=48)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            check_env(env.unwrapped)
        messages = [str(w.message) for w in caught if "WARN" in str(w.message)]  # gymnasium.logger.warn
        assert not messages, messages
    finally:
        env.close()


def test_registration():
    spec = gymnasium.spec(ENV_ID)
    assert spec.max_episode_steps == 1000
    assert spec.reward_threshold == 15.0
    assert spec.entry_point == "rlpipe.envs.minitaur:MinitaurBulletEnv"


def test_close_is_idempotent(make_env):
    env = make_env()
    env.reset(seed=0)
    env.close()
    env.close()
    with pytest.raises(RuntimeError):
        env.reset()


# --------------------------------------------------------------------------- seeding


def _rollout(env, seed, actions):
    obs, _ = env.reset(seed=seed)
    obs_list, rewards = [obs], []
    for a in actions:
        obs, r, term, trunc, _ = env.step(a)
        obs_list.append(obs)
        rewards.append(r)
        if term:
            break
    return np.stack(obs_list), np.array(rewards)


def test_same_seed_same_trajectory_with_randomizer(make_env):
    actions = gait_actions(60, seed=3)
    env_a, env_b = make_env(), make_env()  # randomiser on (the default)
    assert isinstance(env_a.env_randomizer, MinitaurEnvRandomizer)
    global_state = np.random.get_state()
    obs_a, rew_a = _rollout(env_a, 7, actions)
    obs_b, rew_b = _rollout(env_b, 7, actions)
    np.testing.assert_array_equal(obs_a, obs_b)
    np.testing.assert_array_equal(rew_a, rew_b)
    # the env draws from its own generator, never the global one
    after = np.random.get_state()
    np.testing.assert_array_equal(global_state[1], after[1])
    assert global_state[2:] == after[2:]
    # re-seeding the same env replays the episode too
    obs_c, rew_c = _rollout(env_a, 7, actions)
    np.testing.assert_array_equal(obs_a, obs_c)
    np.testing.assert_array_equal(rew_a, rew_c)


def test_different_seeds_differ(make_env):
    actions = gait_actions(30, seed=3)
    env = make_env()
    obs_1, _ = _rollout(env, 1, actions)
    voltage_1 = env.minitaur.motor_model.voltage
    obs_2, _ = _rollout(env, 2, actions)
    voltage_2 = env.minitaur.motor_model.voltage
    assert voltage_1 != voltage_2
    n = min(len(obs_1), len(obs_2))
    assert not np.array_equal(obs_1[:n], obs_2[:n])


def test_randomizer_ranges(make_env):
    env = make_env()
    for seed in range(3):
        env.reset(seed=seed)
        robot, cid = env.minitaur, env._cid
        base_mass = pybullet.getDynamicsInfo(robot.body, -1, physicsClientId=cid)[0]
        assert 0.8 * robot.base_mass_urdf <= base_mass <= 1.2 * robot.base_mass_urdf
        assert base_mass != pytest.approx(robot.base_mass_urdf, rel=1e-9)
        assert BATTERY_VOLTAGE_RANGE[0] <= robot.motor_model.voltage <= BATTERY_VOLTAGE_RANGE[1]
        assert MOTOR_VISCOUS_DAMPING_RANGE[0] <= robot.motor_model.viscous_damping <= MOTOR_VISCOUS_DAMPING_RANGE[1]
        friction = pybullet.getDynamicsInfo(robot.body, FOOT_LINK_ID[0], physicsClientId=cid)[1]
        assert MINITAUR_LEG_FRICTION[0] <= friction <= MINITAUR_LEG_FRICTION[1]


def test_first_reset_deterministic_with_soft_resets(make_env):
    env_a = make_env(hard_reset=False)
    env_b = make_env(hard_reset=False)
    obs_a, _ = env_a.reset(seed=5)
    obs_b, _ = env_b.reset(seed=5)
    np.testing.assert_array_equal(obs_a, obs_b)
    for a in gait_actions(20):
        env_a.step(a)
    obs_soft, _ = env_a.reset()  # soft reset: back to the start pose without reloading
    np.testing.assert_allclose(obs_soft[:8], math.pi / 2, atol=0.1)
    np.testing.assert_allclose(obs_soft[24:], [0, 0, 0, 1], atol=0.05)
    assert np.allclose(env_a.base_position[:2], 0.0, atol=0.02)


def test_observation_noise_is_seeded(make_env):
    env_a = make_env(observation_noise_stdev=0.01, env_randomizer=None)
    env_b = make_env(observation_noise_stdev=0.01, env_randomizer=None)
    env_c = make_env(observation_noise_stdev=0.0, env_randomizer=None)
    obs_a, _ = env_a.reset(seed=11)
    obs_b, _ = env_b.reset(seed=11)
    obs_c, _ = env_c.reset(seed=11)
    np.testing.assert_array_equal(obs_a, obs_b)
    assert not np.array_equal(obs_a, obs_c)
    assert np.abs(obs_a - obs_c).max() < 0.1 * 16.0 / 0.0954  # scaled by the bounds


# --------------------------------------------------------------------------- rendering


def test_render_rgb_array(make_env):
    env = make_env(render_mode="rgb_array", render_width=160, render_height=120)
    env.reset(seed=0)
    for _ in range(3):
        env.step(np.zeros(8))
    frame = env.render()
    assert isinstance(frame, np.ndarray)
    assert frame.shape == (120, 160, 3) and frame.dtype == np.uint8
    assert len(np.unique(frame.reshape(-1, 3), axis=0)) > 10  # not all one colour
    # the robot (dark body) is in the middle of the chase camera's view
    centre = frame[40:80, 50:110].astype(int).sum(axis=2)
    assert centre.min() < 200


def test_render_default_size_and_no_mode(make_env):
    env = make_env(render_mode="rgb_array")
    env.reset(seed=0)
    assert env.render().shape == (720, 960, 3)  # the reference's frame size
    quiet = make_env()
    quiet.reset(seed=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert quiet.render() is None
    with pytest.raises(ValueError):
        MinitaurBulletEnv(render_mode="human")


# --------------------------------------------------------------------------- termination


@pytest.mark.parametrize(
    "action, too_low",
    [
        ([-1, -1, -1, -1, 1, 1, 1, 1], True),  # legs retracted: the base drops below 0.13 m
        ([0, 0, 0, 0, 1, -1, 1, -1], False),  # opposite swings: tilt past up.z < 0.85
    ],
    ids=["height", "tilt"],
)
def test_falling_policy_terminates(make_env, action, too_low):
    env = make_env(env_randomizer=None)
    env.reset(seed=0)
    for t in range(200):  # noqa: B007 - t is read after the loop
        obs, _, terminated, truncated, _ = env.step(np.array(action, dtype=np.float32))
        assert not truncated
        if terminated:
            break
    assert terminated and t < 100
    assert env.is_fallen()
    assert (env.base_position[2] < 0.13) == too_low
    x, y, z, w = obs[24:].astype(np.float64)
    up_z = 1.0 - 2.0 * (x * x + y * y)  # world-z component of the base's z axis
    assert (up_z < 0.85) == (not too_low)


def test_distance_limit_terminates(make_env):
    env = make_env(env_randomizer=None, distance_limit=0.05)
    env.reset(seed=0)
    for a in gait_actions(600, random_every=0):
        _, _, terminated, _, _ = env.step(a)
        if terminated:
            break
    assert terminated
    assert not env.is_fallen()
    x, y, _ = env.base_position
    assert math.hypot(x, y) > 0.05


def test_truncation_at_1000_steps_via_make():
    env = gymnasium.make(ENV_ID, env_randomizer=None)
    try:
        env.reset(seed=0)
        action = np.zeros(8, dtype=np.float32)  # stand still
        for t in range(1, 1001):  # noqa: B007 - t is read after the loop
            _, _, terminated, truncated, _ = env.step(action)
            assert not terminated
            if truncated:
                break
        assert truncated and t == 1000
    finally:
        env.close()


# --------------------------------------------------------------------------- parity


def _parity_run(kwargs: dict, actions, episodes: int = 1, stop_on_termination: bool = True, check=None):
    """Step both envs in lock-step; return (max |obs diff|, max |reward diff|, steps, terminated).

    ``check(ours)``, if given, runs on our env before it is closed.
    """
    ref = _reference_minitaur.make_reference_env(env_randomizer=None, **kwargs)
    ours = MinitaurBulletEnv(env_randomizer=None, **kwargs)
    max_obs = max_rew = 0.0
    steps, terminated = 0, False
    try:
        for episode in range(episodes):
            # the reference's constructor already did the first (hard) reset
            obs_ref = np.asarray(ref.reset() if episode else ref._noisy_observation())
            obs, _ = ours.reset(seed=0) if episode == 0 else ours.reset()
            max_obs = max(max_obs, float(np.abs(obs_ref - obs).max()))
            for a in actions:
                obs_ref, r_ref, done_ref, _ = ref.step(a)
                obs, r, terminated, truncated, _ = ours.step(a)
                steps += 1
                max_obs = max(max_obs, float(np.abs(np.asarray(obs_ref) - obs).max()))
                max_rew = max(max_rew, abs(float(r_ref) - r))
                assert bool(done_ref) == terminated, f"termination differs at step {steps}"
                assert not truncated
                if terminated and stop_on_termination:
                    break
        if check is not None:
            check(ours)
    finally:
        ref._pybullet_client.disconnect()
        ours.close()
    return max_obs, max_rew, steps, terminated


def test_parity_with_reference_full_episode(capsys):
    """Default settings (accurate motor model, overheat protection, leg model), 1000 steps."""
    max_obs, max_rew, steps, terminated = _parity_run({}, gait_actions(1000))
    with capsys.disabled():
        print(f"\n[minitaur parity] steps={steps} terminated={terminated} "
              f"max|obs diff|={max_obs:.3g} max|reward diff|={max_rew:.3g}")
    assert steps == 1000 and not terminated  # the gait walks the whole episode
    assert max_obs < 1e-3
    assert max_rew < 1e-5


@pytest.mark.parametrize(
    "kwargs",
    [
        {"accurate_motor_model_enabled": False},  # pybullet position motors, 0.01 s step
        {"accurate_motor_model_enabled": False, "pd_control_enabled": True},
        {"motor_velocity_limit": 40.0, "drift_weight": 0.5, "shake_weight": 0.5},
        {"leg_model_enabled": False, "torque_control_enabled": True},  # raw PWM commands
    ],
    ids=["position", "pd", "velocity-limit", "torque-control"],
)
def test_parity_with_reference_other_modes(kwargs):
    actions = gait_actions(150, seed=1)
    if kwargs.get("torque_control_enabled"):
        actions = [0.2 * a for a in actions]
    max_obs, max_rew, steps, _ = _parity_run(kwargs, actions)
    assert steps >= 10
    assert max_obs < 1e-3
    assert max_rew < 1e-5


def test_parity_with_reference_soft_resets():
    """``hard_reset=False``: the second and third episodes start from a soft reset on both."""
    max_obs, max_rew, steps, _ = _parity_run({"hard_reset": False}, gait_actions(80, seed=2), episodes=3)
    assert steps > 80
    assert max_obs < 1e-3
    assert max_rew < 1e-5


def test_parity_with_reference_overheat_shutdown():
    """A stalled pose overheats two motors after ~1 s; both envs switch them off alike."""
    action = np.array([1, 1, 1, 1, -1, -1, -1, -1], dtype=np.float64)

    def some_motor_switched_off(env):
        assert not env.minitaur.motor_enabled.all()

    max_obs, max_rew, steps, _ = _parity_run(
        {}, [action] * 160, stop_on_termination=False, check=some_motor_switched_off
    )
    assert steps == 160
    assert max_obs < 1e-3
    assert max_rew < 1e-5


def test_overheat_protection_can_be_disabled(make_env):
    env = make_env(env_randomizer=None, motor_overheat_protection=False)
    env.reset(seed=0)
    for _ in range(160):
        env.step(np.array([1, 1, 1, 1, -1, -1, -1, -1], dtype=np.float32))
    assert env.minitaur.motor_enabled.all()


def test_making_and_stepping_minitaur_prints_nothing():
    # pybullet's C code prints "pybullet build time" at import and "argv[0]=" at each connection;
    # they would interleave with a run's live log (one per env: learner, collectors, evaluator)
    code = ("from rlpipe.envs import make_env\n"
            "for _ in range(2):\n"
            "    env = make_env('MinitaurBulletEnv-v0', seed=0); env.rollout(3); env.close()\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "argv[0]" not in done.stdout and "pybullet build time" not in done.stderr
    assert done.stdout == ""
