"""Evaluations on make_env's one-copy envs are played on the gymnasium env directly (issue 22): the same
episodes and returns, number for number, as TorchRL's ``env.rollout`` path they replace."""

import pytest
import torch

from rlpipe.pipelines.dqn import DQN
from rlpipe.pipelines.sac import SAC
from rlpipe.pipelines.td3 import TD3
from rlpipe.pipelines.workers import evaluation
from rlpipe.pipelines.workers.evaluation import evaluate


def _both_paths(pipeline, episodes: int, seed: int = 7) -> tuple[dict, dict]:
    env, policy = pipeline.eval_env, pipeline.policy
    env.set_seed(seed)
    rollouts = evaluation._evaluate_rollouts(env, policy, episodes, 100_000, None)
    env.set_seed(seed)
    direct = evaluate(env, policy, episodes)
    return rollouts, direct


@pytest.mark.parametrize("make, distinct", [
    (lambda: DQN(DQN.preset("dqn-cartpole-v1-fast")), True),
    (lambda: TD3(TD3.preset("td3-pendulum")), True),
    (lambda: SAC(SAC.preset("sac-pendulum")), True),
    # MuJoCo: float64 observations under DoubleToFloat (an untrained policy drops the pole in 4 steps each time)
    (lambda: SAC(SAC.preset("sac-invpendulum")), False),
], ids=["dqn-cartpole", "td3-pendulum", "sac-pendulum", "sac-invpendulum"])
def test_the_direct_evaluation_plays_what_torchrls_rollouts_play(make, distinct):
    torch.manual_seed(3)
    pipeline = make()
    # a policy that acts: the untrained one's weights moved off their initial values
    with torch.no_grad():
        for p in pipeline.policy.parameters():
            p.add_(torch.randn_like(p) * 0.3)
    assert evaluation.gym_env_of(pipeline.eval_env) is not None  # the direct path is the one taken
    rollouts, direct = _both_paths(pipeline, episodes=5)
    assert direct["returns"] == rollouts["returns"]
    assert direct["average_episode_length"] == rollouts["average_episode_length"]
    if distinct:
        assert len(set(direct["returns"])) > 1  # different episodes, not one replayed


def test_an_interrupt_stops_a_direct_evaluation_within_a_step():
    pipeline = DQN(DQN.preset("dqn-cartpole-v1-fast"))
    calls = 0

    def interrupt():
        nonlocal calls
        calls += 1
        if calls == 5:
            raise KeyboardInterrupt

    pipeline.eval_env.set_seed(0)
    with pytest.raises(KeyboardInterrupt):
        evaluate(pipeline.eval_env, pipeline.policy, 10, interrupt=interrupt)
    assert calls == 5
