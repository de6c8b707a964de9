"""``rlpipe bench time-to-return``'s CleanRL side: run inside the CleanRL peer venv (``peers/cleanrl.py``).

    python ttr_cleanrl.py '{"algo": "sac", "script": ".../sac_continuous_action.py", "env": "Pendulum-v1",
                            "target": -200, "cap": 30000, "seed": 0, ...}'

The script runs unchanged on its defaults (``runpy``, as ``python SCRIPT --seed S --env-id ID
--total-timesteps CAP``). Its env maker wraps each env in ``RecordEpisodeStatistics``; that class is
replaced, before the script imports it, by a subclass that hands each finished episode's return to the
shared rule (``ttr_rule.Rule``). The greedy check plays the script's own networks, found in its globals
(the frames of the running script): SAC's ``actor.get_action`` mean, TD3's ``actor``, DQN's
``q_network`` argmax, on an env of its own. Once the target is confirmed the runner prints its line and
exits there (the script's own end, saving and closing its writer, is not part of the race).
"""

from __future__ import annotations

import json
import os
import runpy
import sys
import time

import numpy as np
from ttr_rule import Rule, versions

EVAL_SEED_OFFSET = 10_000


def main(spec: dict) -> None:
    algo, script = spec["algo"], spec["script"]
    gym = __import__("gymnasium" if algo == "dqn" else "gym")  # dqn.py is on gymnasium 0.28, the others on gym 0.23
    import torch

    rule = Rule.from_spec(spec)
    eval_seed = [int(spec["seed"]) + EVAL_SEED_OFFSET]
    eval_env = []

    def script_globals() -> dict:
        frame = sys._getframe(1)
        while frame is not None and frame.f_globals.get("__file__") != script:
            frame = frame.f_back
        if frame is None:
            raise RuntimeError(f"ttr_cleanrl: no frame of {script} on the stack")
        return frame.f_globals

    def progress(g: dict) -> tuple[int, int]:
        """(env steps, updates made) at the env step ``global_step`` of the script's loop."""
        step, args = int(g["global_step"]), g["args"]
        starts = int(args.learning_starts)
        if algo == "dqn":
            every = int(args.train_frequency)
            return step + 1, max(0, (step - 1) // every - starts // every)
        return step + 1, max(0, step - 1 - starts)

    def evaluate(g: dict, n: int) -> tuple[list[float], list[int]]:
        if not eval_env:
            eval_env.append(gym.make(g["args"].env_id))
        env, device = eval_env[0], g["device"]
        returns, lengths = [], []
        with torch.no_grad():
            for _ in range(n):
                if algo == "dqn":
                    obs, _ = env.reset(seed=eval_seed[0])
                else:
                    env.seed(eval_seed[0])
                    obs = env.reset()
                eval_seed[0] += 1
                total, length, done = 0.0, 0, False
                while not done:
                    x = torch.as_tensor(obs, dtype=torch.float32, device=device).unsqueeze(0)
                    if algo == "sac":
                        action = g["actor"].get_action(x)[2][0].cpu().numpy()
                    elif algo == "td3":
                        action = g["actor"](x)[0].cpu().numpy()
                    else:
                        action = int(g["q_network"](x).argmax(dim=1)[0])
                    out = env.step(action)
                    if len(out) == 5:
                        obs, reward, terminated, truncated, _ = out
                        done = terminated or truncated
                    else:
                        obs, reward, done, _ = out
                    total += float(reward)
                    length += 1
                returns.append(total)
                lengths.append(length)
        return returns, lengths

    names = ("cleanrl", "torch", "gym", "gymnasium", "stable-baselines3", "numpy", "mujoco")

    class RecordEpisodeStatistics(gym.wrappers.RecordEpisodeStatistics):
        def step(self, action):
            out = super().step(action)
            rule.step()
            info = out[-1]
            if isinstance(info, dict) and "episode" in info:
                rule.episode(float(np.ravel(info["episode"]["r"])[0]))  # gymnasium 0.28 keeps an array
                g = script_globals()
                steps, updates = progress(g)
                if rule.check(lambda n: evaluate(g, n), steps, updates):
                    rule.emit(steps, updates, versions=versions(*names), threads=spec.get("threads") or "default")
                    os._exit(0)
            return out

    gym.wrappers.RecordEpisodeStatistics = RecordEpisodeStatistics
    sys.argv = [script, "--seed", str(spec["seed"]), "--env-id", spec["script_env"], "--total-timesteps",
                str(spec["cap"]), "--track", "False", "--capture-video", "False", *spec.get("extra_args", [])]
    start = time.time()
    steps, updates = progress(runpy.run_path(script, run_name="__main__"))  # the cap: not reached
    rule.emit(steps, updates, versions=versions(*names), threads=spec.get("threads") or "default",
              script_s=time.time() - start)
    os._exit(0)


if __name__ == "__main__":
    main(json.loads(sys.argv[1]))
