"""The SAC pipeline: the actor-learner tutorial's preset (checked on the built loss module too),
discrete envs refused, a short Pendulum-v1 run that learns, and `rlpipe train sac` on Minitaur
through the command line with the preset's own collection path (async collector process,
background evaluator)."""

from __future__ import annotations

import json
import math
import signal
import subprocess
import sys

import gymnasium
import numpy as np
import pytest
import torch

import rlpipe.envs  # noqa: F401  (registers rlpipe/MinitaurBullet-v0)
from rlpipe.pipelines import resolve_preset, sac
from rlpipe.pipelines.config import apply_overrides
from rlpipe.pipelines.errors import InputError

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")

CLI = [sys.executable, "-m", "rlpipe.scripts.cli"]


# --- presets ----------------------------------------------------------------------------------------


def test_sac_preset_is_the_tutorial():
    cfg = sac.preset("sac")
    assert cfg.env == "MinitaurBulletEnv-v0"
    assert cfg.num_iterations == 100_000
    assert cfg.initial_collect_steps == 10_000
    assert cfg.replay_buffer_capacity == 10_000
    assert cfg.batch_size == 256
    assert cfg.actor_learning_rate == cfg.critic_learning_rate == cfg.alpha_learning_rate == 3e-4
    assert cfg.target_update_tau == 0.005 and cfg.target_update_period == 1
    assert cfg.gamma == 0.99
    assert cfg.reward_scale_factor == 1.0
    assert cfg.eval_interval == 10_000 and cfg.num_eval_episodes == 20
    assert cfg.policy_save_interval == 5000
    assert cfg.actor_fc_layer_params == [256, 256] and cfg.critic_joint_fc_layer_params == [256, 256]
    assert cfg.collect_steps_per_iteration == 1  # one env step per update, as the tutorial
    algo, same = resolve_preset("sac")
    assert algo == "sac" and same == cfg


def test_sac_preset_builds_the_tutorials_agent_on_minitaur():
    pipeline = sac.SAC(sac.preset("sac"))
    spec = pipeline.env.action_spec
    assert tuple(spec.shape) == (8,)
    assert pipeline.observation_dim == 28
    loss = pipeline.loss_module
    # SacAgent's defaults: target entropy -|A|/2, initial alpha 1 (log alpha 0)
    assert float(loss.target_entropy) == -4.0
    assert float(loss.log_alpha.exp()) == pytest.approx(1.0)
    assert loss.num_qvalue_nets == 2
    assert 1 - float(pipeline.target_updater.eps) == pytest.approx(0.005)
    assert float(loss.value_estimator.gamma) == pytest.approx(0.99)
    for name, lr in (("actor", 3e-4), ("qvalue", 3e-4), ("alpha", 3e-4)):
        assert pipeline.optimizers[name].param_groups[0]["lr"] == lr
    assert pipeline.replay_buffer._storage.max_size == 10_000 and pipeline.replay_buffer.batch_size == 256


@pytest.mark.parametrize("name, env_id, action_dim", [("sac-halfcheetah", "HalfCheetah-v5", 6),
                                                        ("sac-hopper", "Hopper-v5", 3)])
def test_mujoco_presets_exist(name, env_id, action_dim, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # MuJoCo writes MUJOCO_LOG.TXT (deprecation warnings) into the cwd
    algo, cfg = resolve_preset(name)
    assert algo == "sac" and cfg.env == env_id
    small = apply_overrides(cfg, ["actor_fc_layer_params=[8]", "critic_joint_fc_layer_params=[8]"])
    pipeline = sac.SAC(small)
    assert tuple(pipeline.env.action_spec.shape) == (action_dim,)
    # the preset's target entropy: -|A| when it sets one, else the SacAgent default -|A|/2
    expected = cfg.target_entropy if cfg.target_entropy is not None else -action_dim / 2
    assert float(pipeline.loss_module.target_entropy) == expected


def test_the_update_weighs_samples_by_a_prioritized_buffers_weights():
    # The pipeline's update computes SAC on tensors (LeanSACLoss.losses): it must read the batch's
    # importance weights as TorchRL's SACLoss does, not drop them (a trap for prioritized replay).
    cfg = apply_overrides(resolve_preset("sac")[1], [
        "env=Pendulum-v1", "replay_buffer_capacity=1000", "batch_size=32", "actor_fc_layer_params=[16]",
        "critic_joint_fc_layer_params=[16]", "num_threads=0"])
    pipeline = sac.SAC(cfg)
    assert pipeline.loss_module.lean
    batch = pipeline.env.rollout(32, break_when_any_done=False).select(*pipeline.replay_keys)
    batch["priority_weight"] = torch.linspace(0.0, 2.0, 32)
    torch.manual_seed(7)
    expected = pipeline.loss_module(batch.clone())  # SACLoss's TensorDict path, weights applied
    torch.manual_seed(7)
    got = pipeline.update(batch.clone(), 1)
    torch.testing.assert_close(got["qvalue"], expected["loss_qvalue"].detach())
    torch.testing.assert_close(got["actor"], expected["loss_actor"].detach())
    torch.testing.assert_close(got["alpha"], expected["loss_alpha"].detach())


def test_the_greedy_policy_follows_the_actor_as_a_polyak_average_and_checkpoints_hold_it():
    # policy_average_tau: evaluation, export and a target's confirmation act with an average of the
    # actor's weights (avg += tau * (actor - avg) after each actor step); collection samples the actor.
    small = ["env=Pendulum-v1", "replay_buffer_capacity=1000", "batch_size=32", "actor_fc_layer_params=[16]",
             "critic_joint_fc_layer_params=[16]", "num_threads=0"]
    cfg = apply_overrides(resolve_preset("sac")[1], [*small, "policy_average_tau=0.25"])
    pipeline = sac.SAC(cfg)
    assert pipeline.policy is not pipeline.collect_policy
    expected = [p.detach().clone() for p in pipeline.collect_policy.parameters()]  # it starts as the actor
    batch = pipeline.env.rollout(32, break_when_any_done=False).select(*pipeline.replay_keys)
    for index in (1, 2, 3):
        pipeline.update(batch.clone(), index)
        expected = [e + 0.25 * (a.detach() - e) for e, a in zip(expected, pipeline.collect_policy.parameters())]
    for got, want, actor in zip(pipeline.policy.parameters(), expected, pipeline.collect_policy.parameters()):
        torch.testing.assert_close(got.detach(), want)
        assert not torch.equal(got, actor)  # three steps behind by a quarter each: not the actor
    observation = torch.randn(5, pipeline.observation_dim)
    exported = pipeline.export_module()(observation)
    resumed = sac.SAC(cfg)
    resumed.load_state_dict(pipeline.state_dict())
    torch.testing.assert_close(resumed.export_module()(observation), exported)  # the average came back with it
    plain = sac.SAC(apply_overrides(resolve_preset("sac")[1], small))
    with pytest.raises(InputError, match="no averaged policy"):
        resumed.load_state_dict(plain.state_dict())


@pytest.mark.parametrize("lean", [True, False])
def test_a_delayed_policy_update_steps_the_critics_every_time_and_the_actor_and_temperature_every_nth(lean):
    # policy_delay=2: updates 1, 3 move the critics only (and their targets); 2, 4 move all three and
    # the averaged policy. The same on rlpipe's loss on tensors and on a stock TorchRL SACLoss.
    cfg = apply_overrides(resolve_preset("sac")[1], [
        "env=Pendulum-v1", "replay_buffer_capacity=1000", "batch_size=32", "actor_fc_layer_params=[16]",
        "critic_joint_fc_layer_params=[16]", "num_threads=0", "policy_delay=2", "policy_average_tau=0.5"])
    pipeline = sac.SAC(cfg)
    if not lean:
        pipeline.loss_module._critic_layers = None  # the TensorDict path a user's own SACLoss takes
    assert pipeline.loss_module.lean is lean
    loss = pipeline.loss_module
    batch = pipeline.env.rollout(32, break_when_any_done=False).select(*pipeline.replay_keys)

    def snapshot():
        return ([p.detach().clone() for p in pipeline.collect_policy.parameters()],
                [p.detach().clone() for p in pipeline.policy.parameters()],
                float(loss.log_alpha), loss.qvalue_network_params.clone(), loss.target_qvalue_network_params.clone())

    for index in (1, 2, 3, 4):
        actor, average, log_alpha, critics, targets = snapshot()
        out = pipeline.update(batch.clone(), index)
        assert (loss.qvalue_network_params != critics).any() and (loss.target_qvalue_network_params != targets).any()
        moved = [not torch.equal(a, b) for a, b in zip(actor, pipeline.collect_policy.parameters())]
        averaged = [not torch.equal(a, b) for a, b in zip(average, pipeline.policy.parameters())]
        if index % 2:
            assert set(out) == {"qvalue"} and not any(moved) and not any(averaged)
            assert float(loss.log_alpha) == log_alpha
        else:
            assert set(out) == set(sac.SAC.loss_names) and all(moved) and all(averaged)
            assert float(loss.log_alpha) != log_alpha


def test_the_entropy_target_and_learning_rates_move_with_the_frames_collected_and_a_resumed_run_picks_them_up(tmp_path):
    # target_entropy_final: the temperature's target goes linearly from target_entropy to it over
    # target_entropy_anneal's env steps, as a function of the frames collected (random ones included);
    # learning_rate_final_fraction scales every learning rate the same way over learning_rate_anneal.
    cfg = apply_overrides(sac.preset("sac"), [
        "env=Pendulum-v1", "seed=0", "num_iterations=200", "initial_collect_steps=100", "replay_buffer_capacity=1000",
        "batch_size=32", "actor_fc_layer_params=[16]", "critic_joint_fc_layer_params=[16]", "num_threads=1",
        "collector.workers=1", "collector.sync=true", "eval_in_background=false", "eval_interval=0",
        "initial_eval=false", "baseline_episodes=0", "num_eval_episodes=1", "checkpoint_interval=100000",
        "policy_save_interval=100000", "target_entropy=0", "target_entropy_final=-4", "target_entropy_anneal=[100,500]",
        "learning_rate_final_fraction=0.5", "learning_rate_anneal=[100,500]", "critic_learning_rate=1e-3"])
    pipeline = sac.SAC(cfg)
    pipeline.train(tmp_path / "run", progress=False)

    def rates(p):
        return [p.optimizers[name].param_groups[0]["lr"] for name in ("actor", "qvalue", "alpha")]

    assert pipeline.state.frames == 300
    assert float(pipeline.loss_module.target_entropy) == pytest.approx(-2.0)  # (300 - 100) / 400 of the way
    assert rates(pipeline) == pytest.approx([3e-4 * 0.75, 1e-3 * 0.75, 3e-4 * 0.75])  # and to 0.5x: 0.75x
    resumed = sac.SAC(cfg)  # its schedules start from the config's values, not from those it loads
    resumed.load_state_dict(pipeline.state_dict())
    resumed.on_frames(100)
    assert float(resumed.loss_module.target_entropy) == pytest.approx(-3.0)  # from -2 it would be -3.5
    assert rates(resumed) == pytest.approx([3e-4 * 0.625, 1e-3 * 0.625, 3e-4 * 0.625])  # not 0.75 * 0.625
    resumed.on_frames(1000)
    assert float(resumed.loss_module.target_entropy) == pytest.approx(-4.0)  # and they stay at the end
    assert rates(resumed) == pytest.approx([1.5e-4, 5e-4, 1.5e-4])
    with pytest.raises(InputError, match=r"target_entropy_anneal=\[500, 100\].*start < end"):
        sac.SAC(apply_overrides(sac.preset("sac"), ["target_entropy_final=-4", "target_entropy_anneal=[500,100]"]))
    with pytest.raises(InputError, match=r"learning_rate_final_fraction=2.*fraction in \(0, 1\]"):
        sac.SAC(apply_overrides(sac.preset("sac"), ["learning_rate_final_fraction=2"]))
    with pytest.raises(InputError, match=r"learning_rate_final_fraction=0.5 with compile=true.*traced"):
        sac.SAC(apply_overrides(sac.preset("sac"), ["learning_rate_final_fraction=0.5", "compile=true"]))


def test_discrete_env_is_rejected():
    cfg = apply_overrides(sac.preset("sac"), ["env=CartPole-v1"])
    with pytest.raises(InputError) as info:
        sac.SAC(cfg)
    message = str(info.value)
    assert "continuous" in message and "Box" in message and "CartPole-v1" in message


# --- Ctrl-C during an update ------------------------------------------------------------------------


def test_ctrl_c_during_a_sac_update_checkpoints_and_resumes(run_dir, ctrl_c_on_call):
    # A KeyboardInterrupt raised inside the loss's target computation (within tensordict's
    # `to_module` context in the stock SACLoss) would surface as an unrelated RuntimeError, or
    # leave a half-made update; the loop defers Ctrl-C to the end of the update instead.
    cfg = apply_overrides(sac.preset("sac"), [
        "env=Pendulum-v1", "actor_fc_layer_params=[32]", "critic_joint_fc_layer_params=[32]", "batch_size=32",
        "collector.workers=1", "collector.sync=true", "eval_in_background=false", "num_iterations=300",
        "initial_collect_steps=100", "eval_interval=0", "num_eval_episodes=1", "log_interval=100",
        "checkpoint_interval=1000", "policy_save_interval=1000",
    ])
    pipeline = sac.SAC(cfg)
    # where a Ctrl-C lands most of the time in SAC training: inside the loss's target computation
    ctrl_c_inside_the_loss = ctrl_c_on_call("value_target", 120)
    # the actor's NormalParamExtractor, which LeanSACLoss runs as a module
    hook = pipeline.policy.module[0].module[1].register_forward_pre_hook(ctrl_c_inside_the_loss)
    handler = signal.getsignal(signal.SIGINT)
    with pytest.raises(KeyboardInterrupt):
        pipeline.train(run_dir, progress=False)
    hook.remove()
    assert signal.getsignal(signal.SIGINT) is handler  # train put the handler it found back
    c = pipeline.state
    latest = (run_dir / "checkpoints" / "latest").read_text().strip()
    assert latest == f"step_{c.iteration:010d}" and c.iteration > 0
    # stopped within the update it was in: the frames' iteration, all but the unpaid updates made
    assert c.iteration == c.frames - 100 and 100 < c.updates < c.iteration, c
    resumed = sac.SAC(cfg).train(run_dir, resume=True, progress=False)
    assert resumed.summary["iterations"] == 300 and resumed.summary["updates"] == 300


# --- Minitaur through the command line ------------------------------------------------------------


@pytest.mark.slow
def test_cli_trains_sac_on_minitaur_end_to_end(tmp_path):
    run = tmp_path / "run"
    command = [
        *CLI, "train", "sac", "env=rlpipe/MinitaurBullet-v0", "num_iterations=200", "initial_collect_steps=100",
        "actor_fc_layer_params=[64,64]", "critic_joint_fc_layer_params=[64,64]", "batch_size=64",
        "eval_interval=0", "num_eval_episodes=1", "log_interval=100", "checkpoint_interval=100",
        "policy_save_interval=100", "--no-progress", "--out", str(run),
    ]
    out = subprocess.run(command, capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "AverageReturn" in out.stdout
    summary = json.loads((run / "summary.json").read_text())
    assert summary["env"] == "rlpipe/MinitaurBullet-v0"
    assert summary["iterations"] == 200 and summary["frames"] == 300 and summary["updates"] == 200
    assert math.isfinite(summary["final_average_return"])
    config = json.loads((run / "config.json").read_text())["config"]
    # the preset's collection path ran: an async collector process and a background evaluator
    assert config["collector"]["sync"] is False and config["eval_in_background"] is True

    info = json.loads((run / "policy" / "policy.json").read_text())
    assert info["observation_dim"] == 28 and info["action"] == "continuous"
    assert info["low"] == [-1.0] * 8 and info["high"] == [1.0] * 8
    policy = torch.export.load(run / "policy" / "policy.pt2").module()
    env = gymnasium.make("rlpipe/MinitaurBullet-v0")
    obs, _ = env.reset(seed=0)
    observations = [obs]
    for _ in range(20):
        with torch.no_grad():
            action = policy(torch.as_tensor(obs, dtype=torch.float32)[None])[0].numpy()
        assert action.shape == (8,) and np.all(np.abs(action) <= 1.0)
        obs, _, terminated, truncated, _ = env.step(action)  # the env takes it as is
        observations.append(obs)
        if terminated or truncated:
            break
    # and a batch of far-out observations still maps inside the bounds
    batch = torch.as_tensor(np.stack(observations), dtype=torch.float32) * 50
    with torch.no_grad():
        actions = policy(batch)
    assert actions.shape == (len(observations), 8) and actions.abs().max() <= 1.0
    env.close()
