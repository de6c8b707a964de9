"""Evaluation's two paths on the same policy and env, in one process (``python -m``): TorchRL's ``env.rollout``
and the direct one (``pipelines/workers/evaluation._evaluate_directly``), 10 episodes of each preset's untrained
policy on its eval env, twice each, one torch thread. Figures: BENCHMARKS.md ("Evaluations on the same path").
"""

from __future__ import annotations

import time


def main() -> None:
    import torch

    from rlpipe.pipelines.dqn import DQN
    from rlpipe.pipelines.sac import SAC
    from rlpipe.pipelines.td3 import TD3
    from rlpipe.pipelines.workers import evaluation

    torch.set_num_threads(1)
    cases = [("sac-pendulum", SAC(SAC.preset("sac-pendulum"))), ("td3-pendulum", TD3(TD3.preset("td3-pendulum"))),
             ("dqn (CartPole-v0)", DQN(DQN.preset("dqn")))]
    for name, p in cases:
        paths = [("TorchRL rollouts", lambda p=p: evaluation._evaluate_rollouts(p.eval_env, p.policy, 10, 100_000, None)),
                 ("direct", lambda p=p: evaluation.evaluate(p.eval_env, p.policy, 10))]
        for _ in range(2):
            for label, play in paths:
                p.eval_env.set_seed(1)
                t0 = time.perf_counter()
                result = play()
                seconds = time.perf_counter() - t0
                steps = result["average_episode_length"] * 10
                print(f"{name} {label}: {seconds:.3f} s for {steps:.0f} steps = {seconds / steps * 1e6:.0f} us a step "
                      f"(average return {result['average_return']:.2f})", flush=True)


if __name__ == "__main__":
    main()
