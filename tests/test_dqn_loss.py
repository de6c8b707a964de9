"""LeanDQNLoss gives TorchRL's DQNLoss numbers: same loss, same gradients, same priorities."""

from __future__ import annotations

import copy

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Categorical
from torchrl.objectives import DQNLoss

from rlpipe.modules import make_qvalue_actor
from rlpipe.modules.fast.dqn_loss import LeanDQNLoss

pytestmark = pytest.mark.unit


@pytest.mark.parametrize("double_dqn, delay_value", [(False, False), (False, True), (True, True)])
@pytest.mark.parametrize("loss_function", ["l2", "smooth_l1"])
@pytest.mark.parametrize("n_step", [False, True])
def test_lean_loss_matches_dqnloss(double_dqn, delay_value, loss_function, n_step):
    # n_step: transitions that look 1-3 steps ahead (steps_to_next_obs), bootstrapped with gamma ** steps
    spec = Categorical(3)
    torch.manual_seed(0)
    actor = make_qvalue_actor(4, spec, [16, 8])
    kwargs = dict(loss_function=loss_function, delay_value=delay_value, double_dqn=double_dqn, action_space=spec)
    stock, lean = DQNLoss(actor, **kwargs), LeanDQNLoss(copy.deepcopy(actor), **kwargs)
    for loss in (stock, lean):
        loss.make_value_estimator(gamma=0.9)
    lean.load_state_dict(stock.state_dict())
    if delay_value:  # targets apart from the online network, so a mix-up would show
        with torch.no_grad():
            for loss in (stock, lean):
                for value in loss.target_value_network_params.values(True, True):
                    value.mul_(0.5)
    assert lean.lean
    g = torch.Generator().manual_seed(1)
    batch = TensorDict({
        "observation": torch.randn(32, 4, generator=g), "action": torch.randint(0, 3, (32,), generator=g),
        "next": {"observation": torch.randn(32, 4, generator=g), "reward": torch.randn(32, 1, generator=g),
                 "terminated": torch.rand(32, 1, generator=g) < 0.3, "done": torch.zeros(32, 1, dtype=torch.bool)},
    }, [32])
    if n_step:
        batch["steps_to_next_obs"] = torch.randint(1, 4, (32,), generator=g)
    grads = []
    for loss, data in ((stock, batch.clone()), (lean, batch.clone())):
        out = loss(data)
        out["loss"].backward()
        grads.append(({n: p.grad.clone() for n, p in loss.named_parameters() if p.grad is not None}, out["loss"], data["td_error"]))
    (g_stock, l_stock, p_stock), (g_lean, l_lean, p_lean) = grads
    torch.testing.assert_close(l_lean, l_stock)
    torch.testing.assert_close(p_lean, p_stock)
    assert g_lean.keys() == g_stock.keys() and g_lean
    for name in g_stock:
        torch.testing.assert_close(g_lean[name], g_stock[name], msg=name)
