"""``rlpipe bench time-to-return``'s TorchRL side: one of TorchRL's sota-implementations scripts, run in rlpipe's
own venv with Hydra first on ``PYTHONPATH`` (``peers/torchrl_sota.py`` says which scripts, and why so).

    python ttr_torchrl.py '{"algo": "sac", "script": ".../sota-implementations/sac/sac.py", "env": "Pendulum-v1",
                            "overrides": ["env.name=Pendulum-v1", ...], "target": -200, "cap": 30000, "seed": 0, ...}'

The script runs unchanged (``runpy``, as ``python SCRIPT OVERRIDE ...``, its Hydra config beside it). Two of
TorchRL's methods are wrapped before it starts, each doing what it did: the collector's iteration
(``BaseCollector.__iter__``) hands each batch's finished training episodes (``("next", "episode_reward")`` where
``("next", "done")``), in the order they ended, to the shared rule (``ttr_rule.Rule``) as the script receives
the batch; and ``ReplayBuffer.sample`` counts the updates (each of the three scripts samples once per update).
The greedy check plays the script's own policy, found in the frame of its ``main`` (SAC's and TD3's ``model[0]``,
the actor the scripts evaluate; DQN's ``model``, its Q-value actor), under ``ExplorationType.DETERMINISTIC``,
on an env of its own made by the script's own env factory (``utils.env_maker`` with ``apply_env_transforms``;
``utils_cartpole.make_env``). Once the target is confirmed the runner prints its line, ends the script's env
worker processes and exits there (the script's own end is not part of the race).

The DQN script sets no seed: the runner seeds torch's and numpy's generators with the run's seed before it
starts (SAC's and TD3's scripts seed them themselves, from the ``env.seed`` they are given).
"""

from __future__ import annotations

import json
import os
import runpy
import sys
import time

from ttr_rule import Rule, versions

EVAL_SEED_OFFSET = 10_000
NAMES = ("torchrl", "torch", "tensordict", "gymnasium", "mujoco", "hydra-core", "omegaconf", "numpy")


def main(spec: dict) -> None:
    import numpy as np
    import torch
    from torchrl.collectors import BaseCollector
    from torchrl.data import ReplayBuffer
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    algo, script = spec["algo"], os.path.abspath(spec["script"])
    threads = spec.get("threads")
    if threads:
        torch.set_num_threads(int(threads))
    torch.manual_seed(int(spec["seed"]))
    np.random.seed(int(spec["seed"]))
    rule = Rule.from_spec(spec)
    counts = {"frames": 0, "updates": 0, "eval_seed": int(spec["seed"]) + EVAL_SEED_OFFSET}
    eval_env = []

    def script_main_locals() -> dict:
        frame = sys._getframe(1)
        while frame is not None and not (frame.f_code.co_filename == script and frame.f_code.co_name == "main"):
            frame = frame.f_back
        if frame is None:
            raise RuntimeError(f"ttr_torchrl: no frame of {script}'s main on the stack")
        return frame.f_locals

    def evaluate(n: int) -> tuple[list[float], list[int]]:
        found = script_main_locals()
        cfg = found["cfg"]
        policy = found["model"] if algo == "dqn" else found["model"][0]
        if not eval_env:
            if algo == "dqn":
                eval_env.append(sys.modules["utils_cartpole"].make_env(cfg.env.env_name, "cpu"))
            else:
                utils = sys.modules["utils"]
                eval_env.append(utils.apply_env_transforms(utils.env_maker(cfg), cfg.env.max_episode_steps))
        env = eval_env[0]
        max_steps = 10_000_000 if algo == "dqn" else int(cfg.env.max_episode_steps)  # dqn: as its eval_model
        returns, lengths = [], []
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            for _ in range(n):
                env.set_seed(counts["eval_seed"])
                counts["eval_seed"] += 1
                rollout = env.rollout(max_steps, policy, auto_cast_to_device=True, break_when_any_done=True)
                returns.append(float(rollout["next", "reward"].sum()))
                lengths.append(int(rollout.numel()))
        return returns, lengths

    def finished(batch) -> list[tuple[int, float]]:
        """(env steps at its end, return) of each episode that ended in ``batch`` (``[*envs, time]``), by time."""
        done = batch["next", "done"]
        returns = batch["next", "episode_reward"]
        steps = batch.shape[-1]
        envs = batch.numel() // steps
        done = done.reshape(envs, steps).T  # [time, envs]: row-major order is the order they ended
        returns = returns.reshape(envs, steps).T
        at = (torch.arange(steps).unsqueeze(-1).expand(steps, envs) + 1) * envs
        return list(zip(at[done].tolist(), returns[done].tolist()))

    def end(reached: bool) -> None:
        sys.stderr.flush()
        print(flush=True)  # the line starts a line of its own, after the script's progress bar
        rule.emit(counts["frames"], counts["updates"], versions=versions(*NAMES), threads=threads or "default",
                  **({} if reached else {"script_s": time.time() - start}))
        if reached:  # the script's env workers would outlive an os._exit
            import psutil

            for child in psutil.Process().children(recursive=True):
                child.kill()
            os._exit(0)

    iterate = BaseCollector.__iter__

    def timed_iter(self):
        batches = iterate(self)
        while True:
            rule.step()  # the first: the script asks for its first batch, its first env step follows
            try:
                batch = next(batches)
            except StopIteration:
                return
            rule.step()
            before = counts["frames"]
            counts["frames"] += batch.numel()
            for at, ret in finished(batch):
                rule.episode(ret)
                if rule.check(evaluate, before + at, counts["updates"]):
                    end(reached=True)
            yield batch

    sample = ReplayBuffer.sample

    def counted_sample(self, *args, **kwargs):
        counts["updates"] += 1
        return sample(self, *args, **kwargs)

    BaseCollector.__iter__ = timed_iter
    ReplayBuffer.sample = counted_sample
    sys.path.insert(0, os.path.dirname(script))  # its helpers (utils.py, utils_cartpole.py), as `python SCRIPT` has
    sys.argv = [script, *spec["overrides"]]
    start = time.time()
    try:
        runpy.run_path(script, run_name="__main__")
    except SystemExit as exc:  # Hydra ends a failed run so; a finished one returns
        if exc.code not in (0, None):
            raise
    end(reached=False)  # the cap: not reached
    os._exit(0)


if __name__ == "__main__":
    main(json.loads(sys.argv[1]))
