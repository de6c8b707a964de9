"""The CrossQ pipeline: its presets, the agent it builds (no target networks, batch-renormalised twin
critics, Adam betas (0.5, 0.999)), the update (critics every time, actor and temperature every
``policy_delay``; batch statistics moved once per update), the batch-renorm statistics in checkpoints,
the faster ``BatchRenorm1d`` against TorchRL's, and learning on Pendulum-v1 and InvertedPendulum-v5."""

from __future__ import annotations

import copy
import json
import subprocess
import sys

import numpy as np
import pytest
import torch
from torchrl.modules import BatchRenorm1d as TorchRLBatchRenorm1d
from torchrl.objectives import CrossQLoss

from rlpipe.modules import TanhNormalMode
from rlpipe.modules.critics import BatchRenorm1d
from rlpipe.modules.fast.crossq_loss import LeanCrossQLoss
from rlpipe.pipelines import crossq, resolve_preset
from rlpipe.pipelines.artifacts.checkpoint import latest_checkpoint, load_checkpoint
from rlpipe.pipelines.config import apply_overrides
from rlpipe.pipelines.errors import InputError
from rlpipe.pipelines.training.triggers import IntervalTrigger

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")

SMALL = ["env=Pendulum-v1", "actor_fc_layer_params=[16]", "critic_fc_layer_params=[32,32]", "batch_size=32",
         "num_threads=1", "eval_in_background=false", "collector.workers=1", "collector.sync=true"]


def small(*overrides: str) -> crossq.CrossQ:
    return crossq.CrossQ(apply_overrides(crossq.preset("crossq-pendulum"), [*SMALL, *overrides]))


def batch_of(pipeline, n: int = 32):
    torch.manual_seed(0)
    return pipeline.env.rollout(n, break_when_any_done=False).select(*pipeline.replay_keys)


def renorm_buffers(pipeline) -> dict[str, torch.Tensor]:
    return {k: v.clone() for k, v in pipeline.loss_module.state_dict().items()
            if k.endswith(("running_mean", "running_var", "num_batches_tracked"))}


# --- presets and what they build ---------------------------------------------------------------------


def test_crossq_presets_are_sb3_contribs_settings_with_cpu_sized_critics():
    cfg = crossq.preset("crossq")
    assert cfg.env == "MinitaurBulletEnv-v0" and resolve_preset("crossq") == ("crossq", cfg)
    assert cfg.actor_learning_rate == cfg.critic_learning_rate == cfg.alpha_learning_rate == 1e-3
    assert (cfg.adam_beta1, cfg.policy_delay, cfg.collect_steps_per_iteration) == (0.5, 3, 1)
    assert cfg.batch_renorm_momentum == 0.01 and cfg.batch_size == 256
    assert cfg.critic_fc_layer_params == [256, 256]  # not the paper's 2048: see the config's docstring
    assert cfg.collector.sync is False and cfg.eval_in_background  # the sac preset's collection path
    assert crossq.preset("crossq-minitaur") == cfg  # the name the time-to-return bench looks for
    assert crossq.preset("crossq-halfcheetah").env == "HalfCheetah-v5"
    for name, env in (("crossq-pendulum", "Pendulum-v1"), ("crossq-invpendulum", "InvertedPendulum-v5")):
        algo, small_cfg = resolve_preset(name)
        assert algo == "crossq" and small_cfg.env == env
        assert small_cfg.collector.workers == 1 and small_cfg.collector.sync  # in-process collection


def test_crossq_builds_batch_renormalised_twin_critics_and_no_target_networks():
    pipeline = crossq.CrossQ(apply_overrides(crossq.preset("crossq"), ["num_threads=1"]))  # Minitaur: 28 obs, 8 actions
    loss = pipeline.loss_module
    assert pipeline.target_updater is None
    assert not any(k.startswith("target_") for k in loss.state_dict())  # (its "_target_entropy" is a number)
    assert float(loss.target_entropy) == -8.0 and float(loss.log_alpha.exp()) == pytest.approx(1.0)
    norms = [m for m in loss.qvalue_network.modules() if isinstance(m, BatchRenorm1d)]
    assert [m.num_features for m in norms] == [36, 256, 256]  # on the input, after each hidden layer
    assert all(m.momentum == 0.01 and m.warmup_steps == 100_000 for m in norms)
    running = loss.qvalue_network_params["module", "2", "running_mean"]  # the first hidden layer's
    assert running.shape == (2, 256)  # one set of statistics per critic
    for name in ("actor", "qvalue", "alpha"):
        group = pipeline.optimizers[name].param_groups[0]
        assert group["lr"] == 1e-3 and group["betas"] == (0.5, 0.999)
    # the optimisers hold parameters only; the statistics are buffers, moved by the forward pass
    assert sum(p.numel() for p in pipeline.optimizers["qvalue"].param_groups[0]["params"]) == sum(
        p.numel() for p in loss.qvalue_network_params.values(True, True) if isinstance(p, torch.nn.Parameter))


@pytest.mark.parametrize("override, words", [("policy_delay=0", "positive"), ("adam_beta1=1.0", "[0, 1)"),
                                             ("batch_renorm_momentum=0", "(0, 1]"),
                                             ("critic_fc_layer_params=[]", "critic_fc_layer_params")])
def test_bad_crossq_keys_are_one_clear_line(override, words):
    with pytest.raises(InputError) as info:
        apply_overrides(crossq.preset("crossq-pendulum"), [override])
    message = str(info.value)
    assert message.startswith(override.split("=")[0]) and words in message and "\n" not in message


def test_a_discrete_env_is_refused_naming_the_algorithms_that_fit():
    with pytest.raises(InputError) as info:
        crossq.CrossQ(apply_overrides(crossq.preset("crossq"), ["env=CartPole-v1"]))
    assert "continuous" in str(info.value) and "CartPole-v1" in str(info.value) and "dqn" in str(info.value)


# --- the update ----------------------------------------------------------------------------------------


def test_critics_update_every_time_and_the_actor_and_temperature_every_policy_delay():
    pipeline = small()
    batch = batch_of(pipeline)
    loss = pipeline.loss_module
    actor = {k: v.clone() for k, v in loss.actor_network_params.items(True, True)}
    for index in (1, 2):
        before = copy.deepcopy(loss.qvalue_network_params.data)
        out = pipeline.update(batch.clone(), index)
        assert set(out) == {"qvalue"} and torch.isfinite(out["qvalue"])
        assert (loss.qvalue_network_params.data != before).any()  # the critics stepped ...
        assert all(torch.equal(v, loss.actor_network_params[k]) for k, v in actor.items())  # ... the actor not
        assert float(loss.log_alpha) == 0.0
        # one training-mode pass per update (the joint (s, a) + (s', a') batch), for each critic
        assert loss.qvalue_network_params["module", "0", "num_batches_tracked"].tolist() == [index, index]
    out = pipeline.update(batch.clone(), 3)
    assert set(out) == set(crossq.CrossQ.loss_names)
    assert any(not torch.equal(v, loss.actor_network_params[k]) for k, v in actor.items())
    assert float(loss.log_alpha) != 0.0
    # the actor's loss reads the critics in eval mode: it moved no statistics
    assert loss.qvalue_network_params["module", "0", "num_batches_tracked"].tolist() == [3, 3]


def stock_twin(pipeline) -> CrossQLoss:
    """TorchRL's own ``CrossQLoss`` over copies of ``pipeline``'s networks, holding its loss's values."""
    lean = pipeline.loss_module
    stock = CrossQLoss(copy.deepcopy(lean.actor_network), copy.deepcopy(lean.qvalue_network), num_qvalue_nets=2,
                       loss_function="l2", alpha_init=1.0, target_entropy=float(lean.target_entropy),
                       action_spec=pipeline.action_spec)
    stock.make_value_estimator(gamma=float(lean.value_estimator.gamma))
    stock.load_state_dict(lean.state_dict())
    return stock


def test_the_update_computes_torchrls_crossq_loss():
    pipeline = small("policy_delay=1")
    assert isinstance(pipeline.loss_module, LeanCrossQLoss) and pipeline.loss_module.lean
    batch = batch_of(pipeline)
    reference = stock_twin(pipeline)
    torch.manual_seed(7)
    expected = reference(batch.clone())
    torch.manual_seed(7)
    got = pipeline.update(batch.clone(), 1)
    for name in ("qvalue", "actor", "alpha", "entropy"):
        torch.testing.assert_close(got[name], expected[f"loss_{name}" if name != "entropy" else name].detach())
    # and the statistics moved as the reference's forward moved them
    torch.testing.assert_close(pipeline.loss_module.qvalue_network_params["module", "2", "running_var"],
                               reference.qvalue_network_params["module", "2", "running_var"])


def test_reward_scale_factor_scales_the_rewards_the_critics_learn_from():
    pipeline = small("policy_delay=1", "reward_scale_factor=100")
    batch = batch_of(pipeline)
    reference = stock_twin(pipeline)
    scaled = batch.clone()
    scaled.set(("next", "reward"), scaled.get(("next", "reward")) * 100)
    torch.manual_seed(7)
    expected = reference(scaled)
    torch.manual_seed(7)
    got = pipeline.update(batch.clone(), 1)
    torch.testing.assert_close(got["qvalue"], expected["loss_qvalue"].detach())


def test_the_entropy_target_moves_with_the_frames_collected_as_sacs_does():
    # SAC's schedule (test_sac checks it through a run and a resume): the same keys, the same base code.
    pipeline = small("target_entropy=0", "target_entropy_final=-4", "target_entropy_anneal=[100,500]")
    pipeline.on_frames(300)
    assert float(pipeline.loss_module.target_entropy) == pytest.approx(-2.0)  # (300 - 100) / 400 of the way
    pipeline.on_frames(1000)
    assert float(pipeline.loss_module.target_entropy) == pytest.approx(-4.0)
    assert float(small().loss_module.target_entropy) == -1.0  # no schedule: -|A| as built, untouched


@pytest.mark.parametrize("warmup", [0, 2])
def test_lean_loss_gives_crossqlosss_values_gradients_and_statistics(warmup):
    # 2: the fourth pass is past the warm-up, where the renorm corrections r and d act
    pipeline = small(f"batch_renorm_warmup_steps={warmup}", "critic_fc_layer_params=[32,32]")
    lean = pipeline.loss_module
    stock = stock_twin(pipeline)
    for index in range(4):
        batch = batch_of(pipeline)
        if index >= 2:  # n-step transitions (n_step > 1): the bootstrap discounted by gamma ** steps_to_next_obs
            batch["steps_to_next_obs"] = torch.randint(1, 4, (32,), generator=torch.Generator().manual_seed(index))
        for loss in (lean, stock):
            loss.zero_grad(set_to_none=True)
            torch.manual_seed(index)
            q_loss, q_meta = loss.qvalue_loss(batch.clone())
            a_loss, a_meta = loss.actor_loss(batch.clone())
            alpha_loss = loss.alpha_loss(a_meta["log_prob"], tensordict=batch)
            (q_loss + a_loss + alpha_loss).backward()
            loss.__dict__["_seen"] = (q_loss.detach(), a_loss.detach(), alpha_loss.detach(), q_meta["td_error"])
        for a, b in zip(lean.__dict__["_seen"], stock.__dict__["_seen"], strict=True):
            torch.testing.assert_close(a, b)
        ours, theirs = dict(lean.named_parameters()), dict(stock.named_parameters())
        assert ours.keys() == theirs.keys()
        for name, p in ours.items():
            # A Linear's bias ahead of a batch norm has a zero gradient up to rounding, whose size depends on
            # the CPU's float32 kernels: up to ~1e-7 on the AMD EPYC this was written on, 1.7e-6 on an Intel
            # Xeon (2026-11-29), where the layer's weight gradients are ~1-8. A wrong gradient is ~0.1: atol 1e-5.
            torch.testing.assert_close(p.grad, theirs[name].grad, rtol=1e-5, atol=1e-5, msg=name)
        buffers = dict(stock.named_buffers())
        for name, b in lean.named_buffers():
            torch.testing.assert_close(b, buffers[name], msg=name)
    # four training passes, the count held at the warm-up (at 1 without one), for each critic
    assert lean.qvalue_network_params["module", "0", "num_batches_tracked"].tolist() == [max(warmup, 1)] * 2


# --- BatchRenorm1d ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("smooth", [False, True])
def test_batch_renorm_is_torchrls_faster_and_holds_its_step_count(smooth):
    torch.manual_seed(0)
    ours, theirs = BatchRenorm1d(5, warmup_steps=4, smooth=smooth), TorchRLBatchRenorm1d(5, warmup_steps=4, smooth=smooth)
    with torch.no_grad():
        theirs.weight.uniform_(0.5, 2.0)
        theirs.bias.uniform_(-1.0, 1.0)
    ours.load_state_dict(theirs.state_dict())
    for _ in range(5):  # the warm-up and the first step past it, where r and d take full effect
        x = torch.randn(16, 5) * 3 + 1
        x_ours, x_theirs = x.clone().requires_grad_(), x.clone().requires_grad_()
        grad = torch.randn(16, 5)
        y_ours, y_theirs = ours(x_ours), theirs(x_theirs)
        (y_ours * grad).sum().backward()
        (y_theirs * grad).sum().backward()
        torch.testing.assert_close(y_ours, y_theirs)
        for a, b in ((x_ours.grad, x_theirs.grad), (ours.weight.grad, theirs.weight.grad),
                     (ours.bias.grad, theirs.bias.grad), (ours.running_mean, theirs.running_mean),
                     (ours.running_var, theirs.running_var)):
            torch.testing.assert_close(a, b)
    ours.eval()
    theirs.eval()
    torch.testing.assert_close(ours(x), theirs(x))
    # TorchRL 0.14's count runs past warmup_steps (its clamp is not in place); ours stops there
    assert int(theirs.num_batches_tracked) == 5 and int(ours.num_batches_tracked) == 4
    ours.train()
    for _ in range(10):
        ours(torch.randn(16, 5))
    assert int(ours.num_batches_tracked) == 4


# --- checkpoints, export -----------------------------------------------------------------------------------


SHORT = ["num_iterations=60", "initial_collect_steps=50", "eval_interval=0", "num_eval_episodes=1",
         "log_interval=30", "checkpoint_interval=60", "policy_save_interval=60", "baseline_episodes=0"]


def test_checkpoints_hold_the_batch_statistics_and_a_fresh_pipeline_takes_them_back(tmp_path):
    trained = small(*SHORT)
    result = trained.train(tmp_path / "run", progress=False)
    assert result.summary["updates"] == 60
    state = load_checkpoint(latest_checkpoint(tmp_path / "run" / "checkpoints"), "crossq", "Pendulum-v1")
    saved = renorm_buffers(trained)
    assert saved and all(k in state["loss"] for k in saved)
    counts = [v for k, v in saved.items() if k.endswith("num_batches_tracked")]
    assert all(c.tolist() == [60, 60] for c in counts)  # one per update, each critic
    fresh = small(*SHORT)
    assert any(not torch.equal(v, renorm_buffers(fresh)[k]) for k, v in saved.items())
    fresh.load_state_dict(state)
    assert all(torch.equal(v, renorm_buffers(fresh)[k]) for k, v in saved.items())
    # the exported policy is the actor's deterministic action (TanhNormal's mode), the same every call
    exported = torch.export.load(str(tmp_path / "run" / "policy" / "policy.pt2")).module()
    obs = torch.randn(9, 3)
    expected = TanhNormalMode.from_actor(trained.policy, trained.action_spec)(obs)
    torch.testing.assert_close(exported(obs), expected)
    torch.testing.assert_close(exported(obs), exported(obs))
    assert exported(obs * 100).abs().max() <= 2.0


def test_cli_trains_crossq_and_lists_its_keys(tmp_path):
    cli = [sys.executable, "-m", "rlpipe.scripts.cli"]
    keys = subprocess.run([*cli, "train", "crossq", "--keys"], capture_output=True, text=True, timeout=120)
    assert keys.returncode == 0, keys.stderr[-2000:]
    for line in ("policy_delay=3", "adam_beta1=0.5", "critic_fc_layer_params=[256, 256]", "batch_renorm_momentum=0.01"):
        assert line in keys.stdout
    run = tmp_path / "run"
    proc = subprocess.run([*cli, "train", "crossq-pendulum", *SHORT, "critic_fc_layer_params=[32,32]",
                           "--no-progress", "--out", str(run)], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads((run / "summary.json").read_text())
    assert summary["algo"] == "crossq" and summary["updates"] == 60
    header = (run / "metrics.csv").read_text().splitlines()[0].split(",")
    assert {"loss_qvalue", "loss_actor", "loss_alpha", "loss_alpha_value", "loss_entropy"} <= set(header)
    assert (run / "report.html").exists()


# --- it learns ---------------------------------------------------------------------------------------------


LEARN = ["initial_eval=true", "eval_interval=500", "num_eval_episodes=5", "log_interval=500", "checkpoint_interval=100000",
         "policy_save_interval=100000", "num_threads=1"]


def stop_past(bar: float) -> IntervalTrigger:
    """A trigger that ends the run (as its last iteration would) once an evaluation has reached ``bar``: what the
    learning checks ask is reached, no more updates after it."""

    def stop(loop) -> None:
        if any(e["step"] > 0 and e["average_return"] >= bar for e in loop.evaluations):
            loop.finish_early(f"an evaluation reached {bar}")

    return IntervalTrigger(500, stop, name="stop-past")


@pytest.mark.slow
def test_crossq_learns_pendulum(run_dir, play):
    # Its evaluations swing between updates (as SAC's do on Pendulum): the check is that it got well past
    # random (-1200 to -1600) and that the policy it ends with is too. Tried with the preset's 64x64 networks
    # and LeanCrossQLoss (evaluations every 500, 2026-11-27): the best evaluation by 5000 updates on seeds
    # 0-4, 6, 7, 9: -258 (seed 0, the test's), -123, -150, -129, -520, -226, -700, -101; by 3000 only half
    # of seeds 0-11 were past -400, with the stock CrossQLoss as with the lean one (the old check, 3000
    # updates and -400, held on seed 0 by luck: the lean loss's rounding moved it to -595).
    # (The run stops at the first evaluation past -600: the bar is what is checked, not the updates after it.)
    cfg = apply_overrides(crossq.preset("crossq-pendulum"), [*LEARN, "num_iterations=5000"])
    result = crossq.CrossQ(cfg).train(run_dir, progress=False, triggers=[stop_past(-600)])
    returns = [e["average_return"] for e in result.evaluations]
    assert result.evaluations[0]["step"] == 0 and returns[0] < -900, returns
    assert max(returns[1:]) >= -600, f"CrossQ did not learn Pendulum-v1 by 5,000 updates: {returns}"
    assert np.mean(play(run_dir / "policy" / "policy.pt2", "Pendulum-v1", 3, seed=300)) > -1100
