"""Minitaur quadruped locomotion in pybullet, written natively for gymnasium 1.x.

This is rlpipe's own re-implementation of pybullet's ``MinitaurBulletEnv-v0``
(``pybullet_envs/bullet/minitaur_gym_env.py`` with ``minitaur.py``, ``motor.py`` and
``minitaur_env_randomizer.py``), which import the dead ``gym`` package and no longer load
under gymnasium 1.x / numpy 2.  The physics is reproduced call for call, so with the same
actions from the same state the two environments produce the same trajectory
(``tests/test_minitaur.py`` checks this against the reference over a whole episode).

How it maps to the reference
----------------------------
* **Simulation** -- ``plane.urdf`` and ``quadruped/minitaur.urdf`` from ``pybullet_data``
  (loaded with self collision), gravity -10, the four knee point-to-point constraints of the
  closed-chain legs.  Base control step 0.01 s; with the accurate motor model (default) or
  PD control the physics runs at 0.01/5 = 0.002 s with 300/5 = 60 solver iterations and
  each ``step`` applies the action for 5 substeps (``action_repeat * 5``); otherwise one
  0.01 s step with 300 iterations and pybullet's position motors (kp=1, kd=1, 3.5 N m).
* **Action** -- ``Box(-1, 1, (8,))``.  With ``leg_model_enabled`` (default) the 8 values are
  4 leg extensions then 4 leg swings, mapped to the 8 motor angles by the reference's leg
  model; values outside [-1.01, 1.01] raise ``ValueError`` as in the reference.
* **Motor model** (``accurate_motor_model_enabled=True``, default) -- the reference's DC
  motor: PWM = clip(-kp (q - q*) - kd dq, -1, 1) (``motor_kp=1.0``, ``motor_kd=0.02``),
  back-EMF, 50 V voltage clipping, the empirical current->torque table (torque limit
  3.5 N m), an observed torque clipped to 5.7 N m, ``motor_velocity_limit`` clipping of the
  commanded angle and overheat protection (a motor above 2.45 N m for more than 1 s of
  physics time is switched off until the next reset).
* **Observation** -- 28 values: 8 motor angles, 8 motor velocities, 8 (observed) motor
  torques, base orientation quaternion (x, y, z, w); bounds +-(pi, 16/0.0954, 5.7, 1) + 0.01
  exactly as the reference (the joint angles are not wrapped, so a leg driven far can leave
  the box -- also as in the reference).  Optional Gaussian noise scaled by the bounds.
* **Reward** -- ``distance_weight * dx - energy_weight * |tau . dq| * dt`` plus drift
  (-|dy|) and shake (-|dz|) terms whose weights default to 0; ``dt`` is the *physics* step
  and the previous base position starts at the origin after each reset, both as in the
  reference.
* **Termination** -- fallen (base z-axis . world z < 0.85 or base height < 0.13 m) or
  horizontal distance from the origin above ``distance_limit``.  The 1000-step truncation
  comes from the registration (``max_episode_steps=1000``, ``rlpipe/MinitaurBullet-v0``).
* **Reset** -- hard reset (wipe and reload the world) by default, as the reference; the
  robot is settled for 100 physics steps holding all motors at pi/2 before the first
  observation (no settling in torque-control mode, as in the reference).  The
  :class:`MinitaurEnvRandomizer` (on by default, as the reference's) rescales base and leg
  masses by +-20 %, and draws battery voltage, motor damping and foot friction at every
  reset.

Deliberate differences from the reference
-----------------------------------------
* gymnasium API (``reset(seed=, options=) -> (obs, info)``, 5-tuple ``step``), float32
  observations, reward components in ``info``.
* All randomness (randomiser, observation noise) comes from ``self.np_random``, so a seed
  fixes the episode; the reference draws from the global ``random``/``numpy`` RNGs.  The
  randomiser also honours its voltage/damping range arguments (the reference ignores them).
* ``reset(seed=...)`` with an explicit seed always does a hard reset, even with
  ``hard_reset=False``, so reseeding reproduces an episode exactly; the first reset is
  always hard (the reference does it in its constructor).
* A soft reset also zeroes the remembered observed torques (the reference keeps the last
  episode's, visible only in torque-control mode, which skips the settling steps).
* Motor commands are computed in float64 whatever the action dtype (the reference rounds
  them to the action's dtype, i.e. float32 for actions sampled from the space).
* Rendering is headless with pybullet's TinyRenderer in DIRECT mode (``render_mode=
  "rgb_array"``), same chase camera as the reference; ``render_fps`` is 100, the real
  control rate (the reference declared 50).  No GUI mode.
* Per-step Python overhead is cut down: one ``getJointStates`` and one
  ``setJointMotorControlArray`` per physics step, and pybullet's functions are called with
  ``physicsClientId`` directly rather than through ``BulletClient.__getattr__`` (the client
  object still owns the connection).  The physics calls and their order are unchanged, so
  trajectories match the reference to float32 rounding of the observation.
"""

from __future__ import annotations

import contextlib
import math
import os
import sys
from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces


@contextlib.contextmanager
def _c_output_silenced(*fds: int):
    """File descriptors ``fds`` pointed at /dev/null for the block.

    pybullet's C code prints "pybullet build time: ..." to stderr when imported and "argv[0]=" to
    stdout at each connection, which interleaves with the run's live log (one per env: the
    learner's, each collector's, the evaluator's). Python's ``redirect_stdout`` cannot reach C's
    writes, so the descriptors themselves are swapped; Python's own streams are flushed first.
    """
    sys.stdout.flush()
    sys.stderr.flush()
    saved = []
    try:
        with open(os.devnull, "wb") as null:
            for fd in fds:
                try:
                    saved.append((fd, os.dup(fd)))
                except OSError:  # a closed descriptor (a daemon's): nothing to quiet
                    continue
                os.dup2(null.fileno(), fd)
        yield
    finally:
        for fd, copy in saved:
            os.dup2(copy, fd)
            os.close(copy)


with _c_output_silenced(2):
    import pybullet  # noqa: E402  (after the helper that quiets its import)
import pybullet_data  # noqa: E402
from pybullet_utils.bullet_client import BulletClient  # noqa: E402

__all__ = [
    "MinitaurBulletEnv",
    "Minitaur",
    "MotorModel",
    "EnvRandomizerBase",
    "MinitaurEnvRandomizer",
]

# ---------------------------------------------------------------------------------------
# Constants (values from pybullet_envs/bullet/{motor,minitaur,minitaur_gym_env}.py)
# ---------------------------------------------------------------------------------------
NUM_MOTORS = 8
NUM_LEGS = 4
NUM_SUBSTEPS = 5
BASE_TIME_STEP = 0.01
BASE_SOLVER_ITERATIONS = 300
SETTLE_STEPS = 100

ACTION_EPS = 0.01
OBSERVATION_EPS = 0.01

# DC motor model
VOLTAGE_CLIPPING = 50.0
OBSERVED_TORQUE_LIMIT = 5.7
MOTOR_VOLTAGE = 16.0
MOTOR_RESISTANCE = 0.186
MOTOR_TORQUE_CONSTANT = 0.0954
MOTOR_VISCOUS_DAMPING = 0.0
MOTOR_SPEED_LIMIT = MOTOR_VOLTAGE / (MOTOR_VISCOUS_DAMPING + MOTOR_TORQUE_CONSTANT)
_CURRENT_TABLE = np.array([0.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0])
_TORQUE_TABLE = np.array([0.0, 1.0, 1.9, 2.45, 3.0, 3.25, 3.5])

# Robot
INIT_POSITION = (0.0, 0.0, 0.2)
INIT_ORIENTATION = (0.0, 0.0, 0.0, 1.0)
KNEE_CONSTRAINT_POINT_RIGHT = (0.0, 0.005, 0.2)
KNEE_CONSTRAINT_POINT_LEFT = (0.0, 0.01, 0.2)
KNEE_ANGLE = -2.1834
OVERHEAT_SHUTDOWN_TORQUE = 2.45
OVERHEAT_SHUTDOWN_TIME = 1.0
POSITION_CONTROL_MAX_FORCE = 3.5
LEG_POSITION = ("front_left", "back_left", "front_right", "back_right")
MOTOR_NAMES = tuple(f"motor_{leg}{side}_joint" for leg in LEG_POSITION for side in "LR")
LEG_LINK_ID = (2, 3, 5, 6, 8, 9, 11, 12, 15, 16, 18, 19, 21, 22, 24, 25)
MOTOR_LINK_ID = (1, 4, 7, 10, 14, 17, 20, 23)
FOOT_LINK_ID = (3, 6, 9, 12, 16, 19, 22, 25)
BASE_LINK_ID = -1
MOTOR_DIRECTION = np.array([-1.0, -1.0, -1.0, -1.0, 1.0, 1.0, 1.0, 1.0])

# Leg model: motor i takes extension action i//2 and swing action i//2 + 4.
_QUARTER_PI = math.pi / 4
_LEG_EXTENSION_IDX = np.array([0, 0, 1, 1, 2, 2, 3, 3])
_LEG_SWING_IDX = _LEG_EXTENSION_IDX + NUM_LEGS
_LEG_EXTENSION_COEF = np.array([1.0, -1.0, 1.0, -1.0, -1.0, 1.0, -1.0, 1.0]) * _QUARTER_PI
_LEG_SWING_COEF = -1 * _QUARTER_PI  # -scale_for_singularity * pi/4
_LEG_SWING_OFFSET = 1.5  # offset_for_singularity

# Randomiser ranges
MINITAUR_BASE_MASS_ERROR_RANGE = (-0.2, 0.2)  # relative
MINITAUR_LEG_MASS_ERROR_RANGE = (-0.2, 0.2)  # relative
BATTERY_VOLTAGE_RANGE = (14.8, 16.8)  # V
MOTOR_VISCOUS_DAMPING_RANGE = (0.0, 0.01)  # N m s / rad
MINITAUR_LEG_FRICTION = (0.8, 1.5)

# Rendering (chase camera of the reference)
RENDER_WIDTH = 960
RENDER_HEIGHT = 720
CAMERA_DISTANCE = 1.0
CAMERA_YAW = 0.0
CAMERA_PITCH = -30.0


def observation_upper_bound() -> np.ndarray:
    """Upper bound of an observation without the 0.01 margin (also the noise scale)."""
    upper = np.empty(3 * NUM_MOTORS + 4)
    upper[0:NUM_MOTORS] = math.pi
    upper[NUM_MOTORS : 2 * NUM_MOTORS] = MOTOR_SPEED_LIMIT
    upper[2 * NUM_MOTORS : 3 * NUM_MOTORS] = OBSERVED_TORQUE_LIMIT
    upper[3 * NUM_MOTORS :] = 1.0
    return upper


def convert_from_leg_model(action: np.ndarray) -> np.ndarray:
    """Map (4 extensions, 4 swings) in [-1, 1] to the 8 desired motor angles (float64)."""
    swing = _LEG_SWING_COEF * (action[_LEG_SWING_IDX] + _LEG_SWING_OFFSET)
    extension = _LEG_EXTENSION_COEF * action[_LEG_EXTENSION_IDX]
    return (math.pi + swing) + extension


def _clip(x: np.ndarray, low, high) -> np.ndarray:
    """Same values as ``np.clip(x, low, high)`` (NaN included), a few microseconds cheaper."""
    return np.minimum(np.maximum(x, low), high)


class MotorModel:
    """DC motor model of the reference ``motor.py``, vectorised over the 8 motors.

    In position control the PWM is ``-kp (q - q*) - kd dq``; in torque control the command
    is the PWM itself.  The PWM (clipped to [-1, 1]) gives the net voltage after back-EMF
    and viscous damping, clipped at 50 V; the current gives the torque through an empirical
    saturating table.  Returns ``(actual_torque, observed_torque)``.
    """

    def __init__(self, torque_control_enabled: bool = False, kp: float = 1.2, kd: float = 0.0):
        self.torque_control_enabled = torque_control_enabled
        self.kp = kp
        self.kd = kd
        self.resistance = MOTOR_RESISTANCE
        self.voltage = MOTOR_VOLTAGE
        self.torque_constant = MOTOR_TORQUE_CONSTANT
        self.viscous_damping = MOTOR_VISCOUS_DAMPING

    def convert_to_torque(
        self, motor_commands: np.ndarray, motor_angle: np.ndarray, motor_velocity: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        # _clip(x, lo, hi) == np.clip(x, lo, hi), without np.clip's Python-level overhead.
        if self.torque_control_enabled:
            pwm = np.asarray(motor_commands, dtype=np.float64)
        else:
            pwm = -self.kp * (motor_angle - motor_commands) - self.kd * motor_velocity
        pwm = _clip(pwm, -1.0, 1.0)
        observed = _clip(
            self.torque_constant * (pwm * self.voltage / self.resistance),
            -OBSERVED_TORQUE_LIMIT,
            OBSERVED_TORQUE_LIMIT,
        )
        voltage_net = _clip(
            pwm * self.voltage - (self.torque_constant + self.viscous_damping) * motor_velocity,
            -VOLTAGE_CLIPPING,
            VOLTAGE_CLIPPING,
        )
        current = voltage_net / self.resistance
        actual = np.sign(current) * np.interp(np.abs(current), _CURRENT_TABLE, _TORQUE_TABLE)
        return actual, observed


class Minitaur:
    """The simulated robot: loading, pose reset, motor control and state queries.

    Motor-space quantities (angles, velocities, torques, commands) are the joint ones
    multiplied by :data:`MOTOR_DIRECTION`.  All pybullet calls go to ``client_id``.
    """

    def __init__(
        self,
        client_id: int,
        urdf_root: str,
        time_step: float,
        self_collision_enabled: bool,
        motor_velocity_limit: float,
        pd_control_enabled: bool,
        accurate_motor_model_enabled: bool,
        motor_kp: float,
        motor_kd: float,
        torque_control_enabled: bool,
        motor_overheat_protection: bool,
        on_rack: bool,
        kd_for_pd_controllers: float,
    ):
        self._cid = client_id
        self._urdf_root = urdf_root
        self.time_step = time_step
        self._self_collision_enabled = self_collision_enabled
        self._motor_velocity_limit = float(motor_velocity_limit)
        self._accurate = bool(accurate_motor_model_enabled)
        self._pd = bool(pd_control_enabled)
        self._torque_control_enabled = torque_control_enabled
        self._overheat_protection = bool(motor_overheat_protection)
        self._on_rack = on_rack
        self.motor_model: MotorModel | None = None
        if self._accurate:
            self._kp, self._kd = motor_kp, motor_kd
            self.motor_model = MotorModel(torque_control_enabled, kp=motor_kp, kd=motor_kd)
        elif self._pd:
            self._kp, self._kd = 8.0, kd_for_pd_controllers
        else:
            self._kp, self._kd = 1.0, 1.0
        self._overheat_limit = OVERHEAT_SHUTDOWN_TIME / self.time_step
        self.observed_motor_torques = np.zeros(NUM_MOTORS)
        self.load()

    # -- construction / reset ----------------------------------------------------------
    def load(self) -> None:
        """Load the URDF into the (freshly reset) world and put the legs in the start pose."""
        cid = self._cid
        flags = pybullet.URDF_USE_SELF_COLLISION if self._self_collision_enabled else 0
        self.body = pybullet.loadURDF(
            f"{self._urdf_root}/quadruped/minitaur.urdf", INIT_POSITION, flags=flags,
            physicsClientId=cid,
        )
        self.joint_name_to_id = {}
        for j in range(pybullet.getNumJoints(self.body, physicsClientId=cid)):
            info = pybullet.getJointInfo(self.body, j, physicsClientId=cid)
            self.joint_name_to_id[info[1].decode("UTF-8")] = info[0]
        self.motor_ids = [self.joint_name_to_id[name] for name in MOTOR_NAMES]
        self.base_mass_urdf = pybullet.getDynamicsInfo(self.body, BASE_LINK_ID, physicsClientId=cid)[0]
        self.leg_masses_urdf = [
            pybullet.getDynamicsInfo(self.body, LEG_LINK_ID[0], physicsClientId=cid)[0],
            pybullet.getDynamicsInfo(self.body, MOTOR_LINK_ID[0], physicsClientId=cid)[0],
        ]
        self._reset_pose(add_constraint=True)
        if self._on_rack:
            pybullet.createConstraint(
                self.body, -1, -1, -1, pybullet.JOINT_FIXED, [0, 0, 0], [0, 0, 0], [0, 0, 1],
                physicsClientId=cid,
            )
        self._reset_motor_bookkeeping()

    def soft_reset(self) -> None:
        """Put the robot back at the start pose without reloading the world."""
        cid = self._cid
        pybullet.resetBasePositionAndOrientation(self.body, INIT_POSITION, INIT_ORIENTATION, physicsClientId=cid)
        pybullet.resetBaseVelocity(self.body, [0, 0, 0], [0, 0, 0], physicsClientId=cid)
        self._reset_pose(add_constraint=False)
        self._reset_motor_bookkeeping()

    def _reset_motor_bookkeeping(self) -> None:
        self._overheat_counter = np.zeros(NUM_MOTORS, dtype=np.int64)
        self._motor_enabled = np.ones(NUM_MOTORS, dtype=bool)
        self._all_motors_enabled = True
        self.observed_motor_torques = np.zeros(NUM_MOTORS)

    def _reset_pose(self, add_constraint: bool) -> None:
        cid, body, ids = self._cid, self.body, self.joint_name_to_id
        half_pi = math.pi / 2.0
        for leg_id, leg in enumerate(LEG_POSITION):
            dir_l = MOTOR_DIRECTION[2 * leg_id]
            dir_r = MOTOR_DIRECTION[2 * leg_id + 1]
            motor_l, knee_l = ids[f"motor_{leg}L_joint"], ids[f"knee_{leg}L_link"]
            motor_r, knee_r = ids[f"motor_{leg}R_joint"], ids[f"knee_{leg}R_link"]
            pybullet.resetJointState(body, motor_l, dir_l * half_pi, targetVelocity=0, physicsClientId=cid)
            pybullet.resetJointState(body, knee_l, dir_l * KNEE_ANGLE, targetVelocity=0, physicsClientId=cid)
            pybullet.resetJointState(body, motor_r, dir_r * half_pi, targetVelocity=0, physicsClientId=cid)
            pybullet.resetJointState(body, knee_r, dir_r * KNEE_ANGLE, targetVelocity=0, physicsClientId=cid)
            if add_constraint:
                pybullet.createConstraint(
                    body, knee_r, body, knee_l, pybullet.JOINT_POINT2POINT, [0, 0, 0],
                    KNEE_CONSTRAINT_POINT_RIGHT, KNEE_CONSTRAINT_POINT_LEFT, physicsClientId=cid,
                )
            if self._accurate or self._pd:
                # Torque-driven motors: switch off pybullet's default velocity motor.
                for motor in (motor_l, motor_r):
                    pybullet.setJointMotorControl2(
                        body, motor, pybullet.VELOCITY_CONTROL, targetVelocity=0, force=0,
                        physicsClientId=cid,
                    )
            else:
                for motor, direction in ((motor_l, dir_l), (motor_r, dir_r)):
                    pybullet.setJointMotorControl2(
                        body, motor, pybullet.POSITION_CONTROL,
                        targetPosition=direction * half_pi, positionGain=self._kp,
                        velocityGain=self._kd, force=POSITION_CONTROL_MAX_FORCE,
                        physicsClientId=cid,
                    )
            for knee in (knee_l, knee_r):  # passive knees, no friction
                pybullet.setJointMotorControl2(
                    body, knee, pybullet.VELOCITY_CONTROL, targetVelocity=0, force=0,
                    physicsClientId=cid,
                )

    # -- state -------------------------------------------------------------------------
    def motor_state(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Motor angles, velocities and torques (the observed ones, see the reference)."""
        states = pybullet.getJointStates(self.body, self.motor_ids, physicsClientId=self._cid)
        q = np.array([s[0] for s in states]) * MOTOR_DIRECTION
        dq = np.array([s[1] for s in states]) * MOTOR_DIRECTION
        if self._accurate or self._pd:
            tau = self.observed_motor_torques
        else:
            tau = np.array([s[3] for s in states]) * MOTOR_DIRECTION
        return q, dq, tau

    def base_pose(self) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
        return pybullet.getBasePositionAndOrientation(self.body, physicsClientId=self._cid)

    @property
    def motor_enabled(self) -> np.ndarray:
        return self._motor_enabled.copy()

    # -- control -----------------------------------------------------------------------
    def apply_action(self, motor_commands: np.ndarray) -> None:
        """Send one physics step's worth of motor commands (desired angles, or PWM)."""
        cid, body = self._cid, self.body
        if not (self._accurate or self._pd):
            if self._motor_velocity_limit < np.inf:
                q = self.motor_state()[0]
                step = self.time_step * self._motor_velocity_limit
                motor_commands = np.clip(motor_commands, q - step, q + step)
            n = NUM_MOTORS
            pybullet.setJointMotorControlArray(
                body, self.motor_ids, pybullet.POSITION_CONTROL,
                targetPositions=(motor_commands * MOTOR_DIRECTION).tolist(),
                positionGains=[self._kp] * n, velocityGains=[self._kd] * n,
                forces=[POSITION_CONTROL_MAX_FORCE] * n, physicsClientId=cid,
            )
            return

        states = pybullet.getJointStates(body, self.motor_ids, physicsClientId=cid)
        q = np.array([s[0] for s in states]) * MOTOR_DIRECTION
        dq = np.array([s[1] for s in states]) * MOTOR_DIRECTION
        if self._motor_velocity_limit < np.inf:
            step = self.time_step * self._motor_velocity_limit
            motor_commands = _clip(motor_commands, q - step, q + step)

        if self._accurate:
            actual, observed = self.motor_model.convert_to_torque(motor_commands, q, dq)
            if self._overheat_protection:
                hot = np.abs(actual) > OVERHEAT_SHUTDOWN_TORQUE
                self._overheat_counter = (self._overheat_counter + 1) * hot
                overheated = self._overheat_counter > self._overheat_limit
                if overheated.any():
                    self._motor_enabled &= ~overheated
                    self._all_motors_enabled = False
            self.observed_motor_torques = observed
            applied = actual * MOTOR_DIRECTION
            if not self._all_motors_enabled:
                applied = np.where(self._motor_enabled, applied, 0.0)
        else:  # plain PD torque control
            torque = -self._kp * (q - motor_commands) - self._kd * dq
            self.observed_motor_torques = torque
            applied = torque * MOTOR_DIRECTION
        pybullet.setJointMotorControlArray(
            body, self.motor_ids, pybullet.TORQUE_CONTROL, forces=applied.tolist(),
            physicsClientId=cid,
        )

    # -- physical parameters (randomiser) ----------------------------------------------
    def set_base_mass(self, mass: float) -> None:
        pybullet.changeDynamics(self.body, BASE_LINK_ID, mass=mass, physicsClientId=self._cid)

    def set_leg_masses(self, leg_masses) -> None:
        """``leg_masses[0]`` for every leg link, ``leg_masses[1]`` for every motor link."""
        for link in LEG_LINK_ID:
            pybullet.changeDynamics(self.body, link, mass=leg_masses[0], physicsClientId=self._cid)
        for link in MOTOR_LINK_ID:
            pybullet.changeDynamics(self.body, link, mass=leg_masses[1], physicsClientId=self._cid)

    def set_foot_friction(self, friction: float) -> None:
        for link in FOOT_LINK_ID:
            pybullet.changeDynamics(self.body, link, lateralFriction=friction, physicsClientId=self._cid)

    def set_battery_voltage(self, voltage: float) -> None:
        if self.motor_model is not None:
            self.motor_model.voltage = voltage

    def set_motor_viscous_damping(self, damping: float) -> None:
        if self.motor_model is not None:
            self.motor_model.viscous_damping = damping


class EnvRandomizerBase:
    """Called by ``reset()`` after the robot is placed; randomises physical parameters.

    Implementations must draw from ``env.np_random`` so that seeding fixes the episode.
    """

    def randomize_env(self, env: MinitaurBulletEnv) -> None:  # pragma: no cover - interface
        raise NotImplementedError


class MinitaurEnvRandomizer(EnvRandomizerBase):
    """The reference's randomiser, drawing from the env's own generator.

    At each reset: base mass and leg (link, motor) masses scaled by a uniform factor in
    1 + ``*_mass_err_range``, battery voltage, motor viscous damping and foot friction drawn
    uniformly from their ranges (same order of draws as the reference).
    """

    def __init__(
        self,
        minitaur_base_mass_err_range=MINITAUR_BASE_MASS_ERROR_RANGE,
        minitaur_leg_mass_err_range=MINITAUR_LEG_MASS_ERROR_RANGE,
        battery_voltage_range=BATTERY_VOLTAGE_RANGE,
        motor_viscous_damping_range=MOTOR_VISCOUS_DAMPING_RANGE,
        foot_friction_range=MINITAUR_LEG_FRICTION,
    ):
        self.minitaur_base_mass_err_range = tuple(minitaur_base_mass_err_range)
        self.minitaur_leg_mass_err_range = tuple(minitaur_leg_mass_err_range)
        self.battery_voltage_range = tuple(battery_voltage_range)
        self.motor_viscous_damping_range = tuple(motor_viscous_damping_range)
        self.foot_friction_range = tuple(foot_friction_range)

    def randomize_env(self, env: MinitaurBulletEnv) -> None:
        rng: np.random.Generator = env.np_random
        robot = env.minitaur
        lo, hi = self.minitaur_base_mass_err_range
        base = robot.base_mass_urdf
        robot.set_base_mass(rng.uniform(base * (1.0 + lo), base * (1.0 + hi)))
        lo, hi = self.minitaur_leg_mass_err_range
        robot.set_leg_masses([rng.uniform(m * (1.0 + lo), m * (1.0 + hi)) for m in robot.leg_masses_urdf])
        robot.set_battery_voltage(rng.uniform(*self.battery_voltage_range))
        robot.set_motor_viscous_damping(rng.uniform(*self.motor_viscous_damping_range))
        robot.set_foot_friction(rng.uniform(*self.foot_friction_range))


_DEFAULT_RANDOMIZER = MinitaurEnvRandomizer()  # stateless: safe to share between envs


class MinitaurBulletEnv(gymnasium.Env):
    """Minitaur walking forward (+x) on a plane; see the module docstring for details.

    Register/make it as ``gymnasium.make("rlpipe/MinitaurBullet-v0")`` (1000-step limit).
    Several instances can live in one process: each owns a DIRECT pybullet client.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 100}

    def __init__(
        self,
        urdf_root: str = pybullet_data.getDataPath(),
        action_repeat: int = 1,
        distance_weight: float = 1.0,
        energy_weight: float = 0.005,
        shake_weight: float = 0.0,
        drift_weight: float = 0.0,
        distance_limit: float = float("inf"),
        observation_noise_stdev: float = 0.0,
        self_collision_enabled: bool = True,
        motor_velocity_limit: float = np.inf,
        pd_control_enabled: bool = False,
        leg_model_enabled: bool = True,
        accurate_motor_model_enabled: bool = True,
        motor_kp: float = 1.0,
        motor_kd: float = 0.02,
        torque_control_enabled: bool = False,
        motor_overheat_protection: bool = True,
        hard_reset: bool = True,
        on_rack: bool = False,
        kd_for_pd_controllers: float = 0.3,
        env_randomizer: EnvRandomizerBase | None = _DEFAULT_RANDOMIZER,
        render_mode: str | None = None,
        render_width: int = RENDER_WIDTH,
        render_height: int = RENDER_HEIGHT,
    ):
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.render_mode = render_mode
        self._render_width = int(render_width)
        self._render_height = int(render_height)

        self._urdf_root = urdf_root
        self._distance_weight = distance_weight
        self._energy_weight = energy_weight
        self._shake_weight = shake_weight
        self._drift_weight = drift_weight
        self._distance_limit = distance_limit
        self._observation_noise_stdev = observation_noise_stdev
        self._self_collision_enabled = self_collision_enabled
        self._motor_velocity_limit = motor_velocity_limit
        self._pd_control_enabled = pd_control_enabled
        self._leg_model_enabled = leg_model_enabled
        self._accurate_motor_model_enabled = accurate_motor_model_enabled
        self._motor_kp = motor_kp
        self._motor_kd = motor_kd
        self._torque_control_enabled = torque_control_enabled
        self._motor_overheat_protection = motor_overheat_protection
        self._hard_reset = hard_reset
        self._on_rack = on_rack
        self._kd_for_pd_controllers = kd_for_pd_controllers
        self.env_randomizer = env_randomizer

        # Torque-driven motors need the smaller physics step for stability.
        self._time_step = BASE_TIME_STEP
        self._num_solver_iterations = BASE_SOLVER_ITERATIONS
        self._action_repeat = int(action_repeat)
        if pd_control_enabled or accurate_motor_model_enabled:
            self._time_step /= NUM_SUBSTEPS
            self._num_solver_iterations /= NUM_SUBSTEPS
            self._action_repeat *= NUM_SUBSTEPS
        control_dt = self._time_step * self._action_repeat
        if round(1.0 / control_dt) != self.metadata["render_fps"]:
            self.metadata = {**self.metadata, "render_fps": int(round(1.0 / control_dt))}

        self._upper_bound = observation_upper_bound()
        high = (self._upper_bound + OBSERVATION_EPS).astype(np.float32)
        self.observation_space = spaces.Box(-high, high, dtype=np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, (NUM_MOTORS,), dtype=np.float32)
        self._action_low = -1 - ACTION_EPS
        self._action_high = 1 + ACTION_EPS

        with _c_output_silenced(1):
            self._client: BulletClient | None = BulletClient(connection_mode=pybullet.DIRECT)
        self._cid = self._client._client
        self.minitaur: Minitaur | None = None
        self._env_step_counter = 0
        self._last_base_position = (0.0, 0.0, 0.0)
        self._settle_commands = np.full(NUM_MOTORS, math.pi / 2)

    # -- gymnasium API -----------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        if self._client is None:
            raise RuntimeError("reset() on a closed MinitaurBulletEnv")
        # what `replay` needs to play this episode again (envs.snapshot: pybullet's saveState is in-process only),
        # kept as numpy's own dict: this module imports neither torch nor rlpipe (the peers' venvs load it as a file)
        self._episode_rng = self.np_random.bit_generator.state
        self._episode_actions: list[np.ndarray] = []
        return self._start_episode(seed)

    def _start_episode(self, seed: int | None = None):
        if self._hard_reset or self.minitaur is None or seed is not None:
            self._build_world()
        else:
            self.minitaur.soft_reset()
        if self.env_randomizer is not None:
            self.env_randomizer.randomize_env(self)
        self._env_step_counter = 0
        self._last_base_position = (0.0, 0.0, 0.0)
        if not self._torque_control_enabled:
            torque_driven = self._pd_control_enabled or self._accurate_motor_model_enabled
            for _ in range(SETTLE_STEPS):
                if torque_driven:
                    self.minitaur.apply_action(self._settle_commands)
                pybullet.stepSimulation(physicsClientId=self._cid)
        q, dq, tau = self.minitaur.motor_state()
        _, orientation = self.minitaur.base_pose()
        return self._observation(q, dq, tau, orientation), {}

    def step(self, action):
        if self.minitaur is None:
            raise RuntimeError("call reset() before step()")
        action = np.asarray(action, dtype=np.float64)
        if action.shape != (NUM_MOTORS,):
            raise ValueError(f"action must have shape ({NUM_MOTORS},), got {action.shape}")
        self._episode_actions.append(action.copy())
        if self._leg_model_enabled:
            in_bounds = (action >= self._action_low) & (action <= self._action_high)
            if not in_bounds.all():
                i = int(np.flatnonzero(~in_bounds)[0])
                raise ValueError(f"{i}th action {action[i]} out of bounds.")
            motor_commands = convert_from_leg_model(action)
        else:
            motor_commands = action

        robot, cid = self.minitaur, self._cid
        for _ in range(self._action_repeat):
            robot.apply_action(motor_commands)
            pybullet.stepSimulation(physicsClientId=cid)
        self._env_step_counter += 1

        q, dq, tau = robot.motor_state()
        position, orientation = robot.base_pose()
        last = self._last_base_position
        forward_reward = position[0] - last[0]
        drift_reward = -abs(position[1] - last[1])
        shake_reward = -abs(position[2] - last[2])
        self._last_base_position = position
        energy_reward = float(np.abs(np.dot(tau, dq)) * self._time_step)
        reward = (
            self._distance_weight * forward_reward
            - self._energy_weight * energy_reward
            + self._drift_weight * drift_reward
            + self._shake_weight * shake_reward
        )
        terminated = self._is_fallen(position, orientation) or (
            math.sqrt(position[0] ** 2 + position[1] ** 2) > self._distance_limit
        )
        info = {
            "forward_reward": forward_reward,
            "energy_reward": energy_reward,
            "drift_reward": drift_reward,
            "shake_reward": shake_reward,
        }
        return self._observation(q, dq, tau, orientation), float(reward), bool(terminated), False, info

    # -- the episode as data (envs.snapshot) ----------------------------------------------
    def why_not_replayable(self) -> str | None:
        """None when ``replay`` rebuilds the episode exactly: a hard reset builds the world anew each
        episode, so the episode is a function of the generator at its reset and the actions since."""
        return None if self._hard_reset else "a soft-reset Minitaur (hard_reset=False) keeps the last episode's world"

    def replay_state(self) -> dict[str, Any]:
        """The generator's state at the episode's reset and the actions since (``replay`` plays them again),
        as tensors (``dict[str, torch.Tensor]``)."""
        import torch

        from rlpipe.envs.snapshot import generator_state

        actions = getattr(self, "_episode_actions", None)
        if actions is None:
            return {}
        stacked = np.stack(actions) if actions else np.zeros((0, NUM_MOTORS))
        rng = np.random.Generator(np.random.PCG64())
        rng.bit_generator.state = self._episode_rng
        return {**{f"rng/{k}": v for k, v in generator_state(rng).items()}, "actions": torch.from_numpy(stacked)}

    def replay(self, state: dict[str, Any]) -> None:
        """Play the captured episode again in this env: the state it ends in is the captured one."""
        if not state:
            return
        from rlpipe.envs.snapshot import set_generator_state

        set_generator_state(self.np_random, {k[len("rng/"):]: v for k, v in state.items() if k.startswith("rng/")})
        self._episode_rng = self.np_random.bit_generator.state
        self._episode_actions = []
        self._start_episode(seed=None)
        for action in state["actions"].numpy():
            self.step(action)

    def render(self):
        if self.render_mode is None:
            gymnasium.logger.warn(
                "render() called without a render_mode; create the env with render_mode='rgb_array'."
            )
            return None
        if self.minitaur is None:
            raise RuntimeError("call reset() before render()")
        cid, w, h = self._cid, self._render_width, self._render_height
        base_position, _ = self.minitaur.base_pose()
        view = pybullet.computeViewMatrixFromYawPitchRoll(
            cameraTargetPosition=base_position, distance=CAMERA_DISTANCE, yaw=CAMERA_YAW,
            pitch=CAMERA_PITCH, roll=0, upAxisIndex=2, physicsClientId=cid,
        )
        projection = pybullet.computeProjectionMatrixFOV(
            fov=60, aspect=w / h, nearVal=0.1, farVal=100.0, physicsClientId=cid
        )
        _, _, rgba, _, _ = pybullet.getCameraImage(
            w, h, viewMatrix=view, projectionMatrix=projection,
            renderer=pybullet.ER_TINY_RENDERER, flags=pybullet.ER_NO_SEGMENTATION_MASK,
            physicsClientId=cid,
        )
        rgba = np.asarray(rgba, dtype=np.uint8).reshape(h, w, 4)
        return np.ascontiguousarray(rgba[:, :, :3])

    def close(self):
        if self._client is not None:
            try:
                self._client.disconnect()
            except pybullet.error:
                pass
            self._client = None
            self.minitaur = None

    # -- helpers -----------------------------------------------------------------------
    def _build_world(self) -> None:
        cid = self._cid
        pybullet.resetSimulation(physicsClientId=cid)
        pybullet.setPhysicsEngineParameter(
            numSolverIterations=int(self._num_solver_iterations), physicsClientId=cid
        )
        pybullet.setTimeStep(self._time_step, physicsClientId=cid)
        plane = pybullet.loadURDF(f"{self._urdf_root}/plane.urdf", physicsClientId=cid)
        pybullet.changeVisualShape(plane, -1, rgbaColor=[1, 1, 1, 0.9], physicsClientId=cid)
        pybullet.setGravity(0, 0, -10, physicsClientId=cid)
        self.minitaur = Minitaur(
            cid,
            urdf_root=self._urdf_root,
            time_step=self._time_step,
            self_collision_enabled=self._self_collision_enabled,
            motor_velocity_limit=self._motor_velocity_limit,
            pd_control_enabled=self._pd_control_enabled,
            accurate_motor_model_enabled=self._accurate_motor_model_enabled,
            motor_kp=self._motor_kp,
            motor_kd=self._motor_kd,
            torque_control_enabled=self._torque_control_enabled,
            motor_overheat_protection=self._motor_overheat_protection,
            on_rack=self._on_rack,
            kd_for_pd_controllers=self._kd_for_pd_controllers,
        )

    def _observation(self, q, dq, tau, orientation) -> np.ndarray:
        obs = np.empty(3 * NUM_MOTORS + 4)
        obs[0:8] = q
        obs[8:16] = dq
        obs[16:24] = tau
        obs[24:28] = orientation
        if self._observation_noise_stdev > 0:
            obs += self.np_random.normal(scale=self._observation_noise_stdev, size=obs.shape) * self._upper_bound
        return obs.astype(np.float32)

    def _is_fallen(self, position, orientation) -> bool:
        # Third row of the rotation matrix dotted with world z == its (2, 2) entry.
        up_z = pybullet.getMatrixFromQuaternion(orientation, physicsClientId=self._cid)[8]
        return up_z < 0.85 or position[2] < 0.13

    def is_fallen(self) -> bool:
        """Whether the robot is tilted by more than ~32 degrees or its base is below 0.13 m."""
        position, orientation = self.minitaur.base_pose()
        return self._is_fallen(position, orientation)

    @property
    def base_position(self) -> tuple[float, float, float]:
        return self.minitaur.base_pose()[0]

    @property
    def time_step(self) -> float:
        """Physics time step (s); one ``step`` advances ``time_step * action_repeat``."""
        return self._time_step

    @property
    def action_repeat(self) -> int:
        return self._action_repeat
