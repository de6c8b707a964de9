"""``rlpipe bench time-to-return``'s Stable-Baselines3 / SBX side: run inside the peer's venv.

    python ttr_sb3.py '{"lib": "sb3", "algo": "sac", "env": "Pendulum-v1", "target": -200, "cap": 30000,
                        "seed": 0, "hyperparams": {...}, "threads": 1, ...}'

``hyperparams`` are RL-Zoo's for the env as the harness read them from the zoo's yml (``n_timesteps`` and
``policy`` dropped; ``policy_kwargs`` a string as in the yml; ``noise_type``/``noise_std`` turned into
the action noise as the zoo does; a ``lin_X`` learning rate into the zoo's linear schedule over its
``n_timesteps``, passed as ``schedule_timesteps``; ``normalize`` into ``VecNormalize`` as the zoo wraps it, the
deterministic evaluation reading its statistics frozen; ``replay_buffer_class``/``replay_buffer_kwargs``, the
zoo's HER settings, into SB3's ``HerReplayBuffer``). A Dict observation takes SB3's ``MultiInputPolicy``. A callback applies the shared rule (``ttr_rule.Rule``) to the
Monitor's episode returns after every env step and stops ``learn`` once the target is confirmed by a
deterministic evaluation (``model.predict(obs, deterministic=True)``) on an env of its own.

With ``marks`` in the spec (``rlpipe bench anytime``), the callback applies ``ttr_rule.Marks`` instead: a greedy
evaluation at each mark of wall-clock time, then the run stops after the last one.
"""

from __future__ import annotations

import json
import os
import sys
import time

import numpy as np
from ttr_rule import Marks, Rule, register_minitaur, versions

EVAL_SEED_OFFSET = 10_000
_ROBOTICS = ("Fetch", "Hand", "PointMaze", "AntMaze", "Adroit", "FrankaKitchen")


def register_robotics(env: str) -> None:
    """gymnasium-robotics' envs, registered, under MuJoCo 4 with the mend rlpipe makes for them
    (``rlpipe/envs/robotics_compat.py``, whose reason holds here too: its joint helpers compare NumPy ints with
    MuJoCo 4's enums, and every Fetch env fails its first reset): rlpipe is not installed in this venv."""
    if not env.startswith(_ROBOTICS):
        return
    import types

    import gymnasium
    import gymnasium_robotics
    import mujoco
    from gymnasium_robotics.utils import mujoco_utils

    class IntJoints(types.ModuleType):
        def __getattr__(self, name):
            return getattr(mujoco, name)

    view = IntJoints("mujoco")
    view.mjtJoint = types.SimpleNamespace(**{n: int(getattr(mujoco.mjtJoint, n)) for n in dir(mujoco.mjtJoint)
                                             if n.startswith("mjJNT_")})
    mujoco_utils.mujoco = view
    gymnasium.register_envs(gymnasium_robotics)


def _policy_kwargs(text):
    if not isinstance(text, str):
        return text
    from torch import nn  # the zoo's strings name torch's activations (nn.ReLU) for SB3

    return eval(text, {"dict": dict, "nn": nn, "__builtins__": {}})  # noqa: S307 - RL-Zoo's own yml strings


def _linear(initial: float, cap: int, total: int):
    """RL-Zoo's ``lin_X``: X falling linearly to 0 over the zoo's ``n_timesteps`` (``total``). SB3 calls it with
    the progress left of this run's ``learn(total_timesteps=cap)``, which is rescaled to the zoo's."""

    def schedule(progress_remaining: float) -> float:
        return initial * max(0.0, 1.0 - (1.0 - progress_remaining) * cap / total)

    return schedule


def env_maker(env: str, kwargs: dict):
    """What ``make_vec_env`` and the evaluation make ``env`` with, in rlpipe's ``env=`` forms: a registered id,
    gymnasium's ``module:Id-v0`` (importing the module registers it), or a user's ``module:Target`` (a
    ``gymnasium.Env`` subclass or a function returning one), constructed with ``kwargs`` (rlpipe's ``env_kwargs``).
    ``rlpipe.envs.user.resolve``'s reading, again: this runs in the peer's venv, where rlpipe is not installed."""
    import importlib

    import gymnasium

    module_name, colon, name = env.partition(":")
    if colon:
        module = importlib.import_module(module_name)
        if name not in gymnasium.registry and callable(getattr(module, name, None)):
            target = getattr(module, name)
            return lambda: target(**kwargs)
        env = name
    return lambda: gymnasium.make(env, **kwargs)


def main(spec: dict) -> None:
    launch_import = time.time()
    lib, algo = spec["lib"], spec["algo"]
    threads = spec.get("threads")
    if lib == "sb3":
        import torch

        if threads:
            torch.set_num_threads(int(threads))
        from stable_baselines3 import DQN, SAC, TD3
        from stable_baselines3.common.callbacks import BaseCallback
        from stable_baselines3.common.noise import NormalActionNoise
        classes = {"sac": SAC, "td3": TD3, "dqn": DQN}
        names = ("stable-baselines3", "rl-zoo3", "torch", "gymnasium", "numpy", "mujoco", "pybullet")
    else:
        from sbx import DQN, SAC, TD3
        from stable_baselines3.common.callbacks import BaseCallback
        from stable_baselines3.common.noise import NormalActionNoise
        classes = {"sac": SAC, "td3": TD3, "dqn": DQN}
        names = ("sbx-rl", "stable-baselines3", "rl-zoo3", "jax", "jaxlib", "flax", "gymnasium", "numpy", "mujoco",
                 "pybullet")
    from stable_baselines3.common.env_util import make_vec_env

    register_minitaur(spec.get("minitaur_module"))
    env_id, seed = spec["env"], int(spec["seed"])
    hp = dict(spec.get("hyperparams") or {})
    n_envs = int(hp.pop("n_envs", 1))
    normalize = hp.pop("normalize", False)
    for unsupported in ("env_wrapper", "frame_stack", "callback", "vec_env_wrapper"):
        if hp.get(unsupported):
            raise SystemExit(f"ttr_sb3: hyperparameter {unsupported} is not supported by this runner")
        hp.pop(unsupported, None)
    if "policy_kwargs" in hp:
        hp["policy_kwargs"] = _policy_kwargs(hp["policy_kwargs"])
    if "replay_buffer_kwargs" in hp:
        hp["replay_buffer_kwargs"] = _policy_kwargs(hp["replay_buffer_kwargs"])
    if isinstance(hp.get("replay_buffer_class"), str):  # the zoo names SB3's buffers by class name
        import stable_baselines3

        hp["replay_buffer_class"] = getattr(stable_baselines3, hp["replay_buffer_class"])
    schedule_steps = int(hp.pop("schedule_timesteps", None) or spec["cap"])
    for key in ("learning_rate",):  # the zoo's schedules (exp_manager._preprocess_schedules) of the off-policy algos
        if isinstance(hp.get(key), str) and hp[key].startswith("lin_"):
            hp[key] = _linear(float(hp[key][4:]), int(spec["cap"]), schedule_steps)
    noise_type, noise_std = hp.pop("noise_type", None), hp.pop("noise_std", None)
    register_robotics(env_id)
    make = env_maker(env_id, dict(spec.get("env_kwargs") or {}))
    env = make_vec_env(make, n_envs=n_envs, seed=seed)
    if normalize:  # the zoo's VecNormalize: observations and rewards, its gamma
        from stable_baselines3.common.vec_env import VecNormalize

        options = normalize if isinstance(normalize, dict) else {}
        if isinstance(normalize, str):
            options = _policy_kwargs(normalize)
        env = VecNormalize(env, gamma=float(hp.get("gamma", 0.99)), **options)
    if noise_type == "normal":
        dim = env.action_space.shape[0]
        hp["action_noise"] = NormalActionNoise(mean=np.zeros(dim), sigma=float(noise_std) * np.ones(dim))
    elif noise_type is not None:
        raise SystemExit(f"ttr_sb3: noise_type={noise_type} is not supported by this runner")
    eval_env = make()
    eval_seed = [seed + EVAL_SEED_OFFSET]

    rule = Rule.from_spec(spec)

    def evaluate(n: int, seeds=None) -> tuple[list[float], list[int]]:
        returns, lengths = [], []
        for k in range(n):
            obs, _ = eval_env.reset(seed=eval_seed[0] if seeds is None else seeds(k))
            eval_seed[0] += 1
            total, length, done = 0.0, 0, False
            while not done:
                seen = env.normalize_obs(obs) if normalize else obs  # the training statistics, frozen
                action, _ = model.predict(seen, deterministic=True)
                obs, reward, terminated, truncated, _ = eval_env.step(action)
                total += float(reward)
                length += 1
                done = terminated or truncated
            returns.append(total)
            lengths.append(length)
        return returns, lengths

    class Target(BaseCallback):
        def _on_step(self) -> bool:
            rule.step()
            ended = False
            for info in self.locals.get("infos", ()):
                if "episode" in info:
                    rule.episode(info["episode"]["r"])
                    ended = True
            if not ended:
                return True
            return not rule.check(evaluate, self.num_timesteps, getattr(self.model, "_n_updates", 0))

    marks = Marks.from_spec(spec)

    class Anytime(BaseCallback):
        def _on_step(self) -> bool:
            rule.step()
            if marks.due():
                marks.record(lambda: {"last": evaluate(marks.eval_episodes, marks.episode_seed)}, self.num_timesteps,
                             getattr(self.model, "_n_updates", 0))
            return not marks.done()

    import gymnasium

    policy = "MultiInputPolicy" if isinstance(env.observation_space, gymnasium.spaces.Dict) else "MlpPolicy"
    model = classes[algo](policy, env, seed=seed, verbose=0, **{k: v for k, v in hp.items() if k != "policy"})
    imported = time.time() - launch_import
    model.learn(total_timesteps=int(spec["cap"]), callback=Target() if marks is None else Anytime())
    if marks is not None:
        marks.emit(versions=versions(*names), lib=lib, hyperparams=spec.get("hyperparams"),
                   hyperparams_source=spec.get("hyperparams_source"), threads=threads or "default", setup_s=imported,
                   first_step_unix=rule.first_step_unix)
        os._exit(0)
    rule.emit(model.num_timesteps, getattr(model, "_n_updates", 0), versions=versions(*names), lib=lib,
              hyperparams=spec.get("hyperparams"), hyperparams_source=spec.get("hyperparams_source"),
              threads=threads or "default", setup_s=imported)
    os._exit(0)  # nothing left to save: the benchmark times to here


if __name__ == "__main__":
    main(json.loads(sys.argv[1]))
