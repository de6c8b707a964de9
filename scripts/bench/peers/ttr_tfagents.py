"""``rlpipe bench time-to-return``'s TF-Agents side: the DQN tutorial on CartPole-v0 and the SAC actor-learner
tutorial on Minitaur, run inside the TF-Agents peer venv (``peers/tfagents.py``).

    python ttr_tfagents.py '{"tutorial": ".../tfagents_dqn_cartpole.py", "target": 195, "cap": 50000, "seed": 0}'
    python ttr_tfagents.py '{"tutorial": ".../tfagents_sac_minitaur.py", "target": 1.0, "cap": 30000, "seed": 0}'

The tutorial script (``benchmarks/tfagents_tutorials/tfagents_dqn_cartpole.py``: the notebook cell for cell) runs
as it is, with ``--iterations`` set to the step cap; only its ``collect_step`` is replaced by the same
step that also adds the reward to the episode's return and, at each episode's end, applies the shared
rule (``ttr_rule.Rule``). The greedy check is the tutorial's own ``compute_avg_return`` of
``agent.policy`` (greedy) on its ``eval_env``, both found in the running ``main``'s frame.

The Minitaur tutorial (``benchmarks/tfagents_tutorials/tfagents_sac_minitaur.py``, the notebook's actor-learner loop)
runs as it is too, ``--iterations`` the cap less its 10,000 random steps, so that the cap counts env steps
as every other side's does. An observer beside its own (``EXTRA_OBSERVERS``, added to the random and the
collect actor alike, as rlpipe's random steps count too) adds each env step's reward to the episode's
return and applies the rule at each episode's end; the greedy check plays the tutorial's
``GreedyPolicy(tf_agent.policy)`` on its ``eval_env`` (``RUN``), returns and lengths.
"""

from __future__ import annotations

import importlib.util
import json
import os
import sys

from ttr_rule import Rule, versions


def _load_tutorial(path: str):
    module_spec = importlib.util.spec_from_file_location("tfagents_tutorial", path)
    tutorial = importlib.util.module_from_spec(module_spec)
    module_spec.loader.exec_module(tutorial)
    return tutorial


def main(spec: dict) -> None:
    if os.path.basename(spec["tutorial"]) == "tfagents_sac_minitaur.py":
        return minitaur(spec)
    path = spec["tutorial"]
    tutorial = _load_tutorial(path)
    from tf_agents.trajectories import trajectory

    rule = Rule.from_spec(spec)
    names = ("tf-agents", "tensorflow-cpu", "gym", "numpy")
    state = {"steps": 0, "return": 0.0}

    def main_locals() -> dict:
        frame = sys._getframe(1)
        while frame is not None and not (frame.f_code.co_name == "main" and frame.f_globals is vars(tutorial)):
            frame = frame.f_back
        if frame is None:
            raise RuntimeError("ttr_tfagents: the tutorial's main() is not on the stack")
        return frame.f_locals

    def collect_step(environment, policy, buffer) -> None:
        time_step = environment.current_time_step()
        action_step = policy.action(time_step)
        next_time_step = environment.step(action_step.action)
        buffer.add_batch(trajectory.from_transition(time_step, action_step, next_time_step))
        rule.step()
        state["steps"] += 1
        state["return"] += float(next_time_step.reward.numpy()[0])
        if not bool(next_time_step.is_last().numpy()[0]):
            return
        rule.episode(state["return"])
        state["return"] = 0.0
        found = main_locals()
        agent = found.get("agent")
        updates = int(agent.train_step_counter.numpy()) if agent is not None else 0

        def evaluate(n: int) -> list[float]:
            return [tutorial.compute_avg_return(found["eval_env"], agent.policy, n)] * n  # the rule needs the mean

        if agent is not None and rule.check(evaluate, state["steps"], updates):
            rule.emit(state["steps"], updates, versions=versions(*names), threads="default")
            os._exit(0)

    tutorial.collect_step = collect_step
    sys.argv = [path, "--iterations", str(spec["cap"]), "--seed", str(spec["seed"])]
    tutorial.main()
    rule.emit(state["steps"], int(spec["cap"]), versions=versions(*names), threads="default")
    os._exit(0)


def minitaur(spec: dict) -> None:
    path = spec["tutorial"]
    tutorial = _load_tutorial(path)

    rule = Rule.from_spec(spec)
    names = ("tf-agents", "tensorflow-cpu", "dm-reverb", "gym", "pybullet", "numpy")
    state = {"steps": 0, "return": 0.0}

    def updates() -> int:
        return int(tutorial.RUN["train_step"].numpy()) if "train_step" in tutorial.RUN else 0

    def evaluate(n: int) -> tuple[list[float], list[int]]:
        env, policy = tutorial.RUN["eval_env"], tutorial.RUN["eval_policy"]
        returns, lengths = [], []
        for _ in range(n):
            time_step, ret, length = env.reset(), 0.0, 0
            while not time_step.is_last():
                time_step = env.step(policy.action(time_step).action)
                ret += float(time_step.reward)
                length += 1
            returns.append(ret)
            lengths.append(length)
        return returns, lengths

    def observer(traj) -> None:
        if bool(traj.is_boundary()):  # the step after an episode's last: the env's reset, not an env step
            return
        rule.step()
        state["steps"] += 1
        state["return"] += float(traj.reward)
        if not bool(traj.is_last()):
            return
        rule.episode(state["return"])
        state["return"] = 0.0
        if rule.check(evaluate, state["steps"], updates()):
            rule.emit(state["steps"], updates(), versions=versions(*names), threads="default")
            os._exit(0)

    tutorial.EXTRA_OBSERVERS.append(observer)
    iterations = max(1, int(spec["cap"]) - tutorial.INITIAL_COLLECT_STEPS)
    sys.argv = [path, "--iterations", str(iterations), "--seed", str(spec["seed"])]
    tutorial.main()
    rule.emit(state["steps"], updates(), versions=versions(*names), threads="default")
    os._exit(0)


if __name__ == "__main__":
    main(json.loads(sys.argv[1]))
