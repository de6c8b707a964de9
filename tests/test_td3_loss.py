"""TD3AblationLoss, td3_update and make_target_updater: each switch changes exactly what it names.

Small networks and hand-made TensorDicts with non-unit, asymmetric action bounds (so that noise
scaling by the action range is visible), plus one short Pendulum-v1 rollout.
"""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.objectives import TD3Loss

from rlpipe.modules.actors import (
    make_deterministic_actor,
    make_exploration_policy,
    make_gaussian_actor,
)
from rlpipe.modules.critics import make_qvalue_critic
from rlpipe.modules.fast.target_updates import make_target_updater
from rlpipe.modules.td3_loss import TD3AblationLoss, td3_update

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")

OBS, ACT, HIDDEN = 3, 2, (8,)
LOW, HIGH = torch.tensor([-2.0, 0.0]), torch.tensor([2.0, 1.0])
CENTER, RADIUS = (HIGH + LOW) / 2, (HIGH - LOW) / 2
SPEC = Bounded(LOW, HIGH, (ACT,))


def make_loss(actor=None, **switches) -> TD3AblationLoss:
    actor = make_deterministic_actor(OBS, SPEC, HIDDEN) if actor is None else actor
    critic = make_qvalue_critic(OBS, ACT, HIDDEN)
    loss = TD3AblationLoss(actor, critic, action_spec=SPEC, **switches)
    # Targets that differ from the online networks, so that using the wrong set shows.
    with torch.no_grad():
        for name in ("target_actor_network_params", "target_qvalue_network_params"):
            for key, value in getattr(loss, name).items(True, True):
                if key[-1] in ("weight", "bias"):
                    value.add_(0.3 * torch.randn_like(value))
    return loss


def make_batch(batch_size: int = 6) -> TensorDict:
    terminated = torch.zeros(batch_size, 1, dtype=torch.bool)
    terminated[0] = batch_size > 1  # one terminal transition, when there is room for others
    return TensorDict(
        {
            "observation": torch.randn(batch_size, OBS),
            "action": LOW + (HIGH - LOW) * torch.rand(batch_size, ACT),
            ("next", "observation"): torch.randn(batch_size, OBS),
            ("next", "reward"): torch.randn(batch_size, 1),
            ("next", "done"): terminated.clone(),
            ("next", "terminated"): terminated,
        },
        [batch_size],
    )


def mlp(x, params, prefix):
    """Hand-written 1-hidden-layer ReLU MLP from a flat {name: tensor} dict."""
    hidden = torch.relu(x @ params[f"{prefix}0.weight"].T + params[f"{prefix}0.bias"])
    return hidden @ params[f"{prefix}2.weight"].T + params[f"{prefix}2.bias"]


def flat(params, index=None):
    return {
        ".".join(k): (v if index is None else v[index]).detach()
        for k, v in params.items(True, True)
    }


def target_actor_action(loss, next_observation):
    """The target actor's action, through TorchRL's own TensorDict machinery."""
    with loss.target_actor_network_params.to_module(loss.actor_network):
        td = TensorDict(observation=next_observation, batch_size=[len(next_observation)])
        td = loss.actor_network(td)
    return td["action"].detach()


def target_critic(loss, index, observation, action):
    """Target critic ``index`` at (observation, action), through TorchRL's machinery."""
    td = TensorDict(observation=observation, action=action, batch_size=[len(observation)])
    with loss.target_qvalue_network_params[index].to_module(loss.qvalue_network):
        return loss.qvalue_network(td)["state_action_value"].detach()


def optimizers(loss):
    critic = torch.optim.Adam(loss.qvalue_network_params.parameters(), lr=1e-2)
    actor = torch.optim.Adam(loss.actor_network_params.parameters(), lr=1e-2)
    return critic, actor


def snapshot(params):
    return [p.detach().clone() for p in params.parameters()]


def changed(before, params):
    return any(not torch.equal(b, p) for b, p in zip(before, params.parameters()))


def test_default_matches_hand_computed_td3():
    """All switches on: the tutorial's target, critic loss and actor loss, computed by hand."""
    torch.manual_seed(0)
    loss = make_loss()
    loss.make_value_estimator(gamma=0.9)
    td = make_batch()
    s, a, s2 = td["observation"], td["action"], td["next", "observation"]
    r, term = td["next", "reward"], td["next", "terminated"].float()

    actor_t = flat(loss.target_actor_network_params)
    a2 = CENTER + RADIUS * torch.tanh(mlp(s2, actor_t, "module.mlp."))
    torch.manual_seed(123)
    noise = (torch.randn_like(a2) * 0.2).clamp(-0.5, 0.5)
    # The tutorial's normalise / add noise / clamp to [-1, 1] / rescale.
    a2 = (((a2 - CENTER) / RADIUS) + noise).clamp(-1.0, 1.0) * RADIUS + CENTER
    q_t = [
        mlp(torch.cat([s2, a2], -1), flat(loss.target_qvalue_network_params, i), "module.")
        for i in (0, 1)
    ]
    target = r + 0.9 * (1 - term) * torch.min(q_t[0], q_t[1])

    q = [mlp(torch.cat([s, a], -1), flat(loss.qvalue_network_params, i), "module.") for i in (0, 1)]
    critic_loss = ((q[0] - target) ** 2).mean() + ((q[1] - target) ** 2).mean()
    actor = flat(loss.actor_network_params)
    pi = CENTER + RADIUS * torch.tanh(mlp(s, actor, "module.mlp."))
    actor_loss = -mlp(torch.cat([s, pi], -1), flat(loss.qvalue_network_params, 0), "module.").mean()

    torch.manual_seed(123)  # the loss draws the same noise: actor loss first draws nothing
    out = loss(td)
    torch.testing.assert_close(out["target_value"], target.squeeze(-1))
    torch.testing.assert_close(out["loss_qvalue"], critic_loss)
    torch.testing.assert_close(out["loss_actor"], actor_loss)
    assert out["pred_value"].shape == (2, 6)


def test_matches_torchrl_td3loss_without_noise():
    """Smoothing off vs stock TD3Loss with policy_noise=0, same parameters: same losses."""
    torch.manual_seed(1)
    actor = make_deterministic_actor(OBS, SPEC, HIDDEN)
    critic = make_qvalue_critic(OBS, ACT, HIDDEN)
    ours = TD3AblationLoss(actor, critic, action_spec=SPEC, target_policy_smoothing=False)
    stock = TD3Loss(actor, critic, action_spec=SPEC, policy_noise=0.0, loss_function="l2")
    with torch.no_grad():  # the actor is shared; the twin critics are drawn per loss
        stock.qvalue_network_params.data.copy_(ours.qvalue_network_params.data)
        stock.target_qvalue_network_params.data.copy_(ours.target_qvalue_network_params.data)
    td = make_batch()
    mine, theirs = ours(td.clone()), stock(td.clone())
    for key in ("loss_qvalue", "loss_actor", "target_value", "pred_value", "next_state_value"):
        torch.testing.assert_close(mine[key], theirs[key])


def without_smoothing_and_stock() -> tuple[TD3AblationLoss, TD3Loss]:
    """Ours with smoothing off and the stock TD3Loss without noise, same actor and critics' parameters."""
    torch.manual_seed(1)
    actor = make_deterministic_actor(OBS, SPEC, HIDDEN)
    critic = make_qvalue_critic(OBS, ACT, HIDDEN)
    ours = TD3AblationLoss(actor, critic, action_spec=SPEC, target_policy_smoothing=False)
    stock = TD3Loss(actor, critic, action_spec=SPEC, policy_noise=0.0, loss_function="l2")
    with torch.no_grad():
        stock.qvalue_network_params.data.copy_(ours.qvalue_network_params.data)
        stock.target_qvalue_network_params.data.copy_(ours.target_qvalue_network_params.data)
    return ours, stock


def test_importance_weights_weigh_the_losses_as_td3loss_does():
    """A prioritized buffer's weights ("priority_weight", TorchRL 0.14's key) give TD3Loss's weighted
    means, through the TensorDict interface and through td3_update's tensor path alike."""
    ours, stock = without_smoothing_and_stock()
    td = make_batch()
    td["priority_weight"] = torch.tensor([0.1, 1.0, 0.5, 2.0, 0.0, 1.5])
    mine, theirs, unweighted = ours(td.clone()), stock(td.clone()), ours(td.exclude("priority_weight"))
    for key in ("loss_qvalue", "loss_actor"):
        torch.testing.assert_close(mine[key], theirs[key], msg=key)
        assert not torch.allclose(mine[key], unweighted[key]), key  # the weights do change the loss
    critic_opt, actor_opt = optimizers(ours)
    out = td3_update(ours, td.clone(), critic_opt, actor_opt, make_target_updater(ours, 0.005), update_index=2)
    torch.testing.assert_close(out["loss_qvalue"], theirs["loss_qvalue"])


def test_clipped_double_q_switch():
    torch.manual_seed(2)
    td = make_batch(32)
    s2, r = td["next", "observation"], td["next", "reward"]
    not_term = 1 - td["next", "terminated"].float()
    for clipped in (True, False):
        loss = make_loss(clipped_double_q=clipped, target_policy_smoothing=False)
        a2 = target_actor_action(loss, s2)
        q1, q2 = target_critic(loss, 0, s2, a2), target_critic(loss, 1, s2, a2)
        assert not torch.allclose(q1, torch.min(q1, q2))  # the test can tell them apart
        expected = r + 0.99 * not_term * (torch.min(q1, q2) if clipped else q1)
        target, next_q = loss.value_target(s2, r, td["next", "terminated"])
        torch.testing.assert_close(target, expected)
        # Both critics are still trained toward the target.
        critic_loss, predictions, _, _ = loss.qvalue_loss_from_tensors(*loss.tensors_from(td))
        critic_loss.backward()
        assert predictions.shape == (2, 32, 1)
        grad = loss.qvalue_network_params["module", "0", "weight"].grad
        assert grad[0].abs().sum() > 0 and grad[1].abs().sum() > 0


def test_target_policy_smoothing_switch():
    torch.manual_seed(3)
    next_observation = torch.randn(4000, OBS)
    off = make_loss(target_policy_smoothing=False)
    clean = target_actor_action(off, next_observation)
    assert torch.equal(off.target_action(next_observation), clean)

    on = make_loss(target_policy_smoothing=True, policy_noise=0.2, noise_clip=0.5)
    clean = target_actor_action(on, next_observation)
    smoothed = on.target_action(next_observation)
    normalised_noise = (smoothed - clean) / RADIUS
    assert not torch.equal(smoothed, clean)
    assert normalised_noise.abs().max() <= 0.5 + 1e-5  # noise_clip, in normalised units
    assert ((smoothed >= LOW) & (smoothed <= HIGH)).all()
    # The noise is scaled per dimension by the half range (radius 2 and 0.5 here): in normalised
    # units both dimensions have the std of N(0, 0.2) clamped at +-0.5 (2.5 sigma), ~0.197.
    margin = 1.1 * 0.5 * RADIUS  # farther than the largest noise from both bounds: no clamping
    inside = (clean - LOW > margin) & (HIGH - clean > margin)
    for dim in range(ACT):
        std = normalised_noise[inside[:, dim], dim].std()
        assert abs(std - 0.197) < 0.02, (dim, std)


def test_delayed_policy_updates_switch():
    torch.manual_seed(4)
    td = make_batch(16)
    for delayed in (True, False):
        loss = make_loss()
        critic_opt, actor_opt = optimizers(loss)
        updater = make_target_updater(loss, tau=0.005)
        for index in range(1, 5):
            actor_before = snapshot(loss.actor_network_params)
            critic_before = snapshot(loss.qvalue_network_params)
            target_before = loss.target_qvalue_network_params.data.clone()
            out = td3_update(
                loss, td, critic_opt, actor_opt, updater, index,
                policy_delay=2, delayed_policy_updates=delayed,
            )
            actor_step = not delayed or index % 2 == 0
            assert changed(critic_before, loss.qvalue_network_params)
            assert changed(actor_before, loss.actor_network_params) == actor_step
            assert ("loss_actor" in out) == actor_step
            target_moved = not (loss.target_qvalue_network_params == target_before).all()
            assert target_moved == actor_step
            assert all(not v.requires_grad for v in out.values())


def test_target_networks_switch():
    torch.manual_seed(5)
    td = make_batch(16)
    for target_networks in (False, True):
        loss = make_loss()
        critic_opt, actor_opt = optimizers(loss)
        updater = make_target_updater(loss, tau=0.005, target_networks=target_networks)
        td3_update(loss, td, critic_opt, actor_opt, updater, 2, policy_delay=2)
        same_actor = (loss.target_actor_network_params == loss.actor_network_params.data).all()
        same_critic = (loss.target_qvalue_network_params == loss.qvalue_network_params.data).all()
        assert bool(same_actor) == bool(same_critic) == (not target_networks)


def test_stochastic_policy_end_to_end():
    torch.manual_seed(6)
    with pytest.raises(ValueError):
        make_loss(deterministic_policy=False)  # a deterministic actor cannot be sampled
    actor = make_gaussian_actor(OBS, SPEC, HIDDEN)
    loss = make_loss(actor=actor, deterministic_policy=False, target_policy_smoothing=False)
    td = make_batch(16)
    out = loss(td)
    assert torch.isfinite(out["loss_actor"]) and torch.isfinite(out["loss_qvalue"])
    out["loss_actor"].backward()
    grads = [p.grad for p in loss.actor_network_params.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    assert any(g.abs().sum() > 0 for g in grads)
    # Exploration by sampling: same observation, different actions; deterministic at evaluation.
    obs = TensorDict(observation=torch.zeros(8, OBS), batch_size=[8])
    actions = actor(obs.clone())["action"]
    assert actions.std(0).min() > 0 and ((actions >= LOW) & (actions <= HIGH)).all()
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        assert actor(obs.clone())["action"].std(0).max() == 0
    # The target action is a sample of the target policy.
    s2 = td["next", "observation"]
    assert not torch.equal(loss.target_action(s2), loss.target_action(s2))
    critic_opt, actor_opt = optimizers(loss)
    updater = make_target_updater(loss)
    for index in (1, 2):
        out = td3_update(loss, td, critic_opt, actor_opt, updater, index)
    assert torch.isfinite(out["loss_actor"]) and torch.isfinite(out["loss_qvalue"])


def test_batch_of_one():
    """experience_replay=False is a buffer and batch of 1: the loss and update must take it."""
    torch.manual_seed(7)
    loss = make_loss()
    td = make_batch(1)
    out = loss(td)
    assert out["pred_value"].shape == (2, 1) and torch.isfinite(out["loss_qvalue"])
    critic_opt, actor_opt = optimizers(loss)
    updater = make_target_updater(loss)
    for index in (1, 2):
        out = td3_update(loss, td, critic_opt, actor_opt, updater, index)
    assert torch.isfinite(out["loss_qvalue"]) and torch.isfinite(out["loss_actor"])


@pytest.mark.parametrize("path", ["functional_call", "tensordict"])
def test_every_network_path_agrees_with_the_tensor_path(path):
    """Actors other than a TanhBoundedMLP are called through functional_call (plain modules) or
    TensorDicts, critics that are not a TorchRL MLP through TensorDicts: all paths agree."""
    torch.manual_seed(8)
    fast = make_loss()
    # the fast path is taken for rlpipe's own networks: the comparison below is against it
    assert fast._actor_layers is not None and fast._critic_layers is not None and fast._actor_on_tensors
    slow = make_loss()
    slow._actor_layers = None  # as for a plain actor module that is not a TanhBoundedMLP
    if path == "tensordict":
        slow._actor_on_tensors = False  # as for any other actor
        slow._critic_layers = None  # as for any critic that is not a plain MLP
    with torch.no_grad():
        names = ("qvalue_network_params", "target_qvalue_network_params")
        names += ("target_actor_network_params",)
        for name in names:
            getattr(slow, name).data.copy_(getattr(fast, name).data)
        slow_actor, fast_actor = slow.actor_network_params, fast.actor_network_params
        for p_slow, p_fast in zip(slow_actor.parameters(), fast_actor.parameters()):
            p_slow.copy_(p_fast)
    td = make_batch()
    torch.manual_seed(0)
    a = fast(td.clone())
    torch.manual_seed(0)
    b = slow(td.clone())
    for key in ("loss_qvalue", "loss_actor", "target_value", "pred_value"):
        torch.testing.assert_close(a[key], b[key])


def test_pendulum_rollout_and_exploration_noise():
    from torchrl.envs import GymEnv

    torch.manual_seed(9)
    env = GymEnv("Pendulum-v1")
    spec = env.action_spec
    actor = make_deterministic_actor(3, spec)
    policy = make_exploration_policy(actor, spec, sigma=0.1)
    # The tutorial's noise: randn * (expl_noise / 2) * (max - min) = std 0.2 on Pendulum's [-2, 2].
    obs = TensorDict(observation=torch.zeros(4000, 3), batch_size=[4000])
    with torch.no_grad():
        noise = policy(obs.clone())["action"] - actor(obs.clone())["action"]
        assert abs(noise.std() - 0.2) < 0.02
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            assert torch.equal(policy(obs.clone())["action"], actor(obs.clone())["action"])
        data = env.rollout(32, policy)
    loss = TD3AblationLoss(actor, make_qvalue_critic(3, 1), action_spec=spec)
    critic_opt, actor_opt = optimizers(loss)
    updater = make_target_updater(loss)
    for index in (1, 2):
        out = td3_update(loss, data, critic_opt, actor_opt, updater, index)
    assert torch.isfinite(out["loss_qvalue"]) and torch.isfinite(out["loss_actor"])


def test_n_step_transitions_bootstrap_with_gamma_to_their_steps_as_td3loss_does():
    """steps_to_next_obs (n_step > 1): TD3Loss's TD0 discounts each bootstrap by gamma ** steps; so do the
    TensorDict interface and td3_update's tensor path."""
    ours, stock = without_smoothing_and_stock()
    td = make_batch()
    td["steps_to_next_obs"] = torch.tensor([1, 3, 2, 3, 1, 2])
    mine, theirs, one_step = ours(td.clone()), stock(td.clone()), ours(td.exclude("steps_to_next_obs"))
    torch.testing.assert_close(mine["target_value"], theirs["target_value"])
    torch.testing.assert_close(mine["loss_qvalue"], theirs["loss_qvalue"])
    assert not torch.allclose(mine["target_value"], one_step["target_value"])
    critic_opt, actor_opt = optimizers(ours)
    out = td3_update(ours, td.clone(), critic_opt, actor_opt, make_target_updater(ours, 0.005), update_index=1)
    torch.testing.assert_close(out["loss_qvalue"], theirs["loss_qvalue"])
