"""LeanAdam is torch's fused Adam, step for step: same parameters, same state, same checkpoints."""

from __future__ import annotations

import copy

import pytest
import torch
from torch import nn

from rlpipe.modules.fast.optim import LeanAdam


def twin_models(seed: int = 0):
    torch.manual_seed(seed)
    model = nn.Sequential(nn.Linear(4, 32), nn.ReLU(), nn.Linear(32, 2))
    return model, copy.deepcopy(model)


def train(model, opt, steps: int, seed: int = 1, scheduler=None):
    gen = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        x = torch.randn(16, 4, generator=gen)
        opt.zero_grad()
        model(x).pow(2).mean().backward()
        opt.step()
        if scheduler is not None:
            scheduler.step()


def trained_pair(steps: int):
    """The same model trained ``steps`` steps by Adam(fused=True) and by LeanAdam."""
    ref, lean = twin_models()
    opt_ref = torch.optim.Adam(ref.parameters(), lr=1e-2, fused=True)
    opt_lean = LeanAdam(lean.parameters(), lr=1e-2)
    train(ref, opt_ref, steps)
    train(lean, opt_lean, steps)
    return ref, lean, opt_ref, opt_lean


def assert_same(a: nn.Module, b: nn.Module, opt_a, opt_b):
    for pa, pb in zip(a.parameters(), b.parameters()):
        assert torch.equal(pa, pb)
    sa, sb = opt_a.state_dict(), opt_b.state_dict()
    assert sa["param_groups"] == sb["param_groups"]
    for i, state in sa["state"].items():
        for key, value in state.items():
            assert torch.equal(value, sb["state"][i][key]), (i, key)


def test_steps_are_bitwise_those_of_fused_adam_with_a_schedule_and_weight_decay():
    ref, lean = twin_models()
    kwargs = dict(lr=1e-2, betas=(0.8, 0.99), eps=1e-6, weight_decay=1e-3)
    opt_ref = torch.optim.Adam(ref.parameters(), fused=True, **kwargs)
    opt_lean = LeanAdam(lean.parameters(), **kwargs)
    sched_ref = torch.optim.lr_scheduler.StepLR(opt_ref, step_size=3, gamma=0.5)
    sched_lean = torch.optim.lr_scheduler.StepLR(opt_lean, step_size=3, gamma=0.5)
    train(ref, opt_ref, 10, scheduler=sched_ref)
    train(lean, opt_lean, 10, scheduler=sched_lean)
    assert_same(ref, lean, opt_ref, opt_lean)
    assert float(opt_lean.state[next(lean.parameters())]["step"]) == 10
    # and those steps took the lean path (Adam's own step only made the state, on the first)
    lean(torch.ones(2, 4)).sum().backward()
    assert opt_lean._lean_groups() is not None


def test_a_parameter_without_gradient_is_left_alone_as_adam_does():
    ref, lean, opt_ref, opt_lean = trained_pair(2)
    for model, opt in ((ref, opt_ref), (lean, opt_lean)):  # only the last layer gets a gradient
        opt.zero_grad()
        model[2](torch.ones(3, 32)).sum().backward()
        opt.step()
    assert_same(ref, lean, opt_ref, opt_lean)


def test_state_dict_round_trip_continues_identically():
    ref, lean, opt_ref, _ = trained_pair(5)
    # a fresh LeanAdam loaded from the stock optimiser's checkpoint
    resumed_model = copy.deepcopy(lean)
    resumed = LeanAdam(resumed_model.parameters(), lr=1.0)
    resumed.load_state_dict(copy.deepcopy(opt_ref.state_dict()))  # as from a file: no shared tensors
    train(ref, opt_ref, 5, seed=2)
    train(resumed_model, resumed, 5, seed=2)
    assert_same(ref, resumed_model, opt_ref, resumed)


@pytest.mark.parametrize("plain_adam_first", [False, True])
def test_closures_and_hooks_get_adams_own_step(plain_adam_first, monkeypatch):
    # torch wraps Adam.step in its hook runner when the first plain Adam is made: with and without
    step = torch.optim.Adam.step
    if getattr(step, "hooked", False) and not plain_adam_first:
        monkeypatch.setattr(torch.optim.Adam, "step", step.__wrapped__)
    ref, lean = twin_models()
    if not plain_adam_first:
        opt_lean = LeanAdam(lean.parameters(), lr=1e-2)
        assert not getattr(torch.optim.Adam.step, "hooked", False)
    opt_ref = torch.optim.Adam(ref.parameters(), lr=1e-2, fused=True)
    if plain_adam_first:
        opt_lean = LeanAdam(lean.parameters(), lr=1e-2)
    calls = []
    opt_lean.register_step_pre_hook(lambda opt, args, kwargs: calls.append("pre"))
    opt_lean.register_step_post_hook(lambda opt, args, kwargs: calls.append("post"))
    x = torch.randn(8, 4)
    for model, opt in ((ref, opt_ref), (lean, opt_lean)):
        for _ in range(3):
            def closure(model=model, opt=opt):
                opt.zero_grad()
                loss = model(x).pow(2).mean()
                loss.backward()
                return loss
            loss = opt.step(closure)
            assert torch.is_tensor(loss)
    assert calls == ["pre", "post"] * 3
    assert_same(ref, lean, opt_ref, opt_lean)
