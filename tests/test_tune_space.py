"""``rlpipe tune``'s search space: its first trial is the config ``rlpipe train ALGO env=ENV`` trains."""

from __future__ import annotations

import dataclasses

import pytest

from rlpipe.pipelines.config import apply_overrides
from rlpipe.scripts import tune, tune_space


@pytest.mark.parametrize(("algo", "env"), [("dqn", "Acrobot-v1"), ("sac", "Reacher-v5"), ("sac", "Pendulum-v1"),
                                           ("td3", "InvertedDoublePendulum-v5")])
def test_the_first_trial_trains_what_rlpipe_train_would(algo, env):
    cfg = tune.base_config(algo, env, [])
    params = tune_space.params_of(algo, cfg)
    assert {d.name for d in tune_space.dims(algo)} <= set(params)  # every dimension starts from the config's value
    assert _starts_said(apply_overrides(cfg, tune_space.overrides(algo, params))) == _starts_said(cfg)


def _starts_said(cfg):
    """``learning_starts=null`` means ``initial_collect_steps``: the trial names it, the same arithmetic"""
    return dataclasses.replace(cfg, learning_starts=cfg.initial_collect_steps if cfg.learning_starts is None
                               else cfg.learning_starts)


def test_a_value_the_space_does_not_hold_is_left_to_optuna():
    cfg = tune.base_config("sac", "Pendulum-v1", ["actor_fc_layer_params=[32,32]", "critic_joint_fc_layer_params=[32,32]",
                                                  "batch_size=100"])
    params = tune_space.params_of("sac", cfg)
    assert "width" not in params and "batch_size" not in params and params["learning_rate"] == 2e-3
