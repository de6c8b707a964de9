"""LeanSACLoss gives TorchRL's SACLoss numbers: same losses, same gradients, same random draws."""

from __future__ import annotations

import copy

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded
from torchrl.modules import TanhNormal, ValueOperator
from torchrl.objectives import SACLoss

from rlpipe.modules.actors import make_tanh_normal_actor
from rlpipe.modules.critics import make_qvalue_critic
from rlpipe.modules.fast.sac_loss import LeanSACLoss, tanh_normal_rsample
from rlpipe.modules.normalization import RunningObservationNorm

pytestmark = pytest.mark.unit

OBS, ACT, B = 5, 3, 64


def losses_pair(low=-2.0, high=1.5, layer_norm=False, normalized=False):
    spec = Bounded(torch.full((ACT,), low), torch.full((ACT,), high), (ACT,))
    torch.manual_seed(0)
    norm = None
    if normalized:  # normalize_observations: one running normaliser in front of the actor and the critics
        norm = RunningObservationNorm(OBS)
        norm.update(torch.randn(100, OBS) * 3 + 2)
    actor = make_tanh_normal_actor(OBS, spec, [32, 32], encoder=norm)
    critic = make_qvalue_critic(OBS, ACT, [32, 32], layer_norm=layer_norm, encoder=norm)
    kwargs = dict(num_qvalue_nets=2, loss_function="l2", alpha_init=0.5, target_entropy=-1.5, delay_qvalue=True)
    stock = SACLoss(actor, critic, **kwargs)
    lean = LeanSACLoss(copy.deepcopy(actor), copy.deepcopy(critic), **kwargs)
    for loss in (stock, lean):
        loss.make_value_estimator(gamma=0.97)
    lean.load_state_dict(stock.state_dict())
    with torch.no_grad():  # targets apart from the online critics, so a mix-up would show (the normaliser's
        # statistics are the learner's, the same in every copy: RunningObservationNorm.update writes them all)
        for params in (lean.target_qvalue_network_params, stock.target_qvalue_network_params):
            for key, value in params.items(True, True):
                if not key[-1].startswith("observation_"):
                    value.add_(0.1)
    return stock, lean


def batch():
    g = torch.Generator().manual_seed(1)
    return TensorDict({
        "observation": torch.randn(B, OBS, generator=g), "action": torch.rand(B, ACT, generator=g) * 3 - 2,
        "next": {"observation": torch.randn(B, OBS, generator=g), "reward": torch.randn(B, 1, generator=g),
                 "terminated": torch.rand(B, 1, generator=g) < 0.3, "done": torch.zeros(B, 1, dtype=torch.bool)},
    }, [B])


def backward_and_grads(loss, out):
    (out["loss_actor"] + out["loss_qvalue"] + out["loss_alpha"]).backward()
    return {name: p.grad.clone() for name, p in loss.named_parameters() if p.grad is not None}


@pytest.mark.parametrize("bounds, layer_norm, normalized", [((-2.0, 1.5), False, False), ((-1.0, 1.0), False, False),
                                                            ((-1.0, 1.0), True, False), ((-2.0, 1.5), False, True)])
def test_lean_loss_matches_sacloss_values_and_gradients(bounds, layer_norm, normalized):
    # layer_norm: the critics' LayerNorm acts on each row's features; the lean loss keeps the twin
    # critics' activations as columns, where a layout mistake normalises across the batch instead
    stock, lean = losses_pair(*bounds, layer_norm=layer_norm, normalized=normalized)
    assert lean.lean
    data = batch()
    torch.manual_seed(5)
    expected = stock(data.clone())
    expected_grads = backward_and_grads(stock, expected)
    for through_forward in (True, False):
        lean.zero_grad(set_to_none=True)
        torch.manual_seed(5)
        got = lean(data.clone()) if through_forward else lean.losses(*lean.tensors_from(data))
        grads = backward_and_grads(lean, got)
        for key in ("loss_actor", "loss_qvalue", "loss_alpha", "alpha", "entropy"):
            torch.testing.assert_close(got[key], expected[key], rtol=1e-6, atol=1e-6, msg=key)
        assert grads.keys() == expected_grads.keys() and len(grads) == 13  # actor 6, critics 6, log_alpha
        for name in grads:
            torch.testing.assert_close(grads[name], expected_grads[name], rtol=1e-5, atol=1e-6, msg=name)


def test_importance_weights_weigh_the_losses_as_sacloss_does():
    # A prioritized buffer's weights ("priority_weight", TorchRL 0.14's key): SACLoss's weighted means.
    stock, lean = losses_pair()
    data = batch()
    data["priority_weight"] = torch.rand(B, generator=torch.Generator().manual_seed(3)) * 2
    torch.manual_seed(5)
    expected = stock(data.clone())
    for through_forward in (True, False):
        torch.manual_seed(5)
        got = lean(data.clone()) if through_forward else lean.losses(
            *lean.tensors_from(data), weights=data["priority_weight"])
        for key in ("loss_actor", "loss_qvalue", "loss_alpha"):
            torch.testing.assert_close(got[key], expected[key], rtol=1e-6, atol=1e-6, msg=key)
    torch.manual_seed(5)
    unweighted = lean(data.exclude("priority_weight"))
    assert not torch.allclose(unweighted["loss_qvalue"], expected["loss_qvalue"])  # the weights do count


def test_tanh_normal_rsample_is_torchrls_tanh_normal():
    loc, scale = torch.randn(100, 2) * 3, torch.rand(100, 2) + 0.05
    low, high = torch.tensor([-2.0, 0.0]), torch.tensor([1.0, 4.0])
    torch.manual_seed(3)
    action, log_prob = TanhNormal(loc, scale, low=low, high=high).rsample_and_log_prob()
    torch.manual_seed(3)
    got_action, got_log_prob = tanh_normal_rsample(loc, scale, (high + low) / 2, (high - low) / 2)
    torch.testing.assert_close(got_action, action)
    torch.testing.assert_close(got_log_prob, log_prob)


class Critic(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.net = torch.nn.Linear(OBS + ACT, 1)

    def forward(self, observation, action):
        return self.net(torch.cat([observation, action], -1))


def test_other_structures_go_through_sacloss():
    spec = Bounded(-torch.ones(ACT), torch.ones(ACT), (ACT,))
    actor = make_tanh_normal_actor(OBS, spec, [16])
    critic = ValueOperator(Critic(), in_keys=["observation", "action"])  # not a TorchRL MLP: no tensor path
    lean = LeanSACLoss(actor, critic, num_qvalue_nets=2)
    assert not lean.lean
    out = lean(batch())
    assert torch.isfinite(out["loss_qvalue"]) and torch.isfinite(out["loss_actor"])


def test_n_step_transitions_bootstrap_with_gamma_to_their_steps_as_sacloss_does():
    # steps_to_next_obs (n_step > 1): TorchRL's TD0 discounts each bootstrap by gamma ** steps; so must the lean loss
    stock, lean = losses_pair()
    data = batch()
    data["steps_to_next_obs"] = torch.randint(1, 4, (B,), generator=torch.Generator().manual_seed(3))
    torch.manual_seed(5)
    expected = stock(data.clone())
    for through_forward in (True, False):
        torch.manual_seed(5)
        obs, action, next_obs, reward, terminated = lean.tensors_from(data)
        got = lean(data.clone()) if through_forward else lean.losses(
            obs, action, next_obs, reward, terminated, discount=0.97 ** data["steps_to_next_obs"])
        torch.testing.assert_close(got["loss_qvalue"], expected["loss_qvalue"], rtol=1e-6, atol=1e-6)
    torch.manual_seed(5)
    assert not torch.allclose(lean(data.exclude("steps_to_next_obs"))["loss_qvalue"], expected["loss_qvalue"])
