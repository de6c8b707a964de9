"""n-step transitions (``n_step``): each window against a step-by-step reference (episode ends, trajectory
changes without a done, the block's end, envs side by side), and what a short SAC run stores and learns from."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from rlpipe.pipelines import resolve_preset, sac
from rlpipe.pipelines.config import apply_overrides
from rlpipe.pipelines.training.nstep import STEPS_KEY, n_step_transitions

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


def block(shape, seed=0) -> TensorDict:
    """A collected block: observations numbered, episodes ending by termination or truncation, and a
    trajectory id that also changes once without a done (the next env's steps in the same block)."""
    g = torch.Generator().manual_seed(seed)
    n = shape[-1]
    terminated = torch.rand(*shape, 1, generator=g) < 0.1
    truncated = (torch.rand(*shape, 1, generator=g) < 0.06) & ~terminated
    done = terminated | truncated
    ids = torch.cat([torch.zeros(*shape[:-1], 1, dtype=torch.long), done[..., :-1, 0].long().cumsum(-1)], -1)
    ids[..., n // 2:] += 100  # a change of trajectory with no done before it
    obs = torch.arange(torch.Size(shape).numel(), dtype=torch.float32).reshape(*shape, 1).expand(*shape, 2)
    return TensorDict({
        "observation": obs.clone(), "action": torch.randn(*shape, 1, generator=g),
        "collector": {"traj_ids": ids},
        "next": {"observation": obs + 0.5, "reward": torch.randn(*shape, 1, generator=g), "done": done,
                 "terminated": terminated, "truncated": truncated},
    }, list(shape))


def reference(td: TensorDict, n: int, gamma: float, t: int):
    """(discounted sum, index of the window's last step) of the window from step ``t`` of a [T] block."""
    ids, done, reward = td["collector", "traj_ids"], td["next", "done"][:, 0], td["next", "reward"][:, 0]
    total, last = float(reward[t]), t
    for k in range(1, n):
        if done[last] or last + 1 >= td.shape[0] or ids[last + 1] != ids[t]:
            break
        last += 1
        total += gamma ** k * float(reward[last])
    return total, last


@pytest.mark.unit
@pytest.mark.parametrize("shape", [(60,), (3, 40)])
def test_windows_sum_one_trajectorys_rewards_and_take_the_next_entries_and_flags_where_they_end(shape):
    td = block(shape)
    before = td.clone()
    out = n_step_transitions(td, 3, 0.9)
    assert (td == before).all()  # the block itself (what the episode statistics read) is left as taken
    rows = [td] if len(shape) == 1 else list(td.unbind(0))
    outs = [out] if len(shape) == 1 else list(out.unbind(0))
    seen = set()
    for row, got in zip(rows, outs):
        for t in range(row.shape[0]):
            total, last = reference(row, 3, 0.9, t)
            assert float(got["next", "reward"][t]) == pytest.approx(total, abs=1e-5)
            assert int(got[STEPS_KEY][t]) == last - t + 1
            for key in ("observation", "done", "terminated", "truncated"):
                assert torch.equal(got["next", key][t], row["next", key][last]), (t, key)
            assert torch.equal(got["observation"][t], row["observation"][t])
            seen.add((last - t + 1, bool(row["next", "terminated"][last])))
    # every kind of window occurred: whole ones, and shorter ones ending in a termination or otherwise
    assert {(3, False), (1, True), (2, True)} <= seen and {(1, False), (2, False)} & seen
    assert n_step_transitions(td, 1, 0.9) is td


def test_a_run_stores_n_step_transitions_that_the_update_bootstraps_from(tmp_path):
    # Pendulum through sac-pendulum's in-process collector: each stored row's next observation is the
    # observation stored three rows on (one env, blocks stored in order), but at a block's end or an episode's.
    cfg = apply_overrides(resolve_preset("sac-pendulum")[1], [
        "n_step=3", "collect_steps_per_iteration=1", "num_iterations=150", "initial_collect_steps=250", "eval_interval=0", "num_eval_episodes=1",
        "batch_size=32", "actor_fc_layer_params=[16]", "critic_joint_fc_layer_params=[16]"])
    pipeline = sac.SAC(cfg)
    pipeline.train(str(tmp_path / "run"))
    stored = pipeline.replay_buffer[:]
    steps, frames = stored[STEPS_KEY], cfg.collector.frames_per_batch
    assert len(stored) == 400 and set(steps.tolist()) <= {1, 2, 3}
    for i in range(len(stored) - 3):
        if int(steps[i]) == 3 and not stored["next", "done"][i]:  # (an episode's last step: its final observation)
            assert torch.equal(stored["next", "observation"][i], stored["observation"][i + 3])
        else:  # a window cut short: only where its block or its episode (200 steps) ends
            assert (i % frames) + int(steps[i]) == frames or bool(stored["next", "done"][i])
    assert (steps == 3).float().mean() > 0.9
    batch = stored[:32]
    loss = pipeline.loss_module
    one_step = apply_overrides(cfg, ["n_step=1"])
    assert STEPS_KEY in pipeline.replay_keys and STEPS_KEY not in sac.SAC(one_step).replay_keys
    # the lean update's target discounts the bootstrap by gamma ** steps: as TorchRL's own SACLoss does
    obs, action, next_obs, reward, terminated = loss.tensors_from(batch)
    torch.manual_seed(0)
    lean = loss.losses(obs, action, next_obs, reward, terminated, discount=loss.value_estimator.gamma ** steps[:32])
    loss._critic_layers, lean_layers = None, loss._critic_layers
    torch.manual_seed(0)
    stock = loss(batch.clone())
    loss._critic_layers = lean_layers
    torch.testing.assert_close(lean["loss_qvalue"], stock["loss_qvalue"])
