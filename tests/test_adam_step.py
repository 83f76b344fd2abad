"""fast.adam_step: the fused Adam step called directly gives what Adam.step gives, and falls back where it must."""

from __future__ import annotations

import copy

import pytest
import torch
from torch import nn

from gchgg.fast.adam_step import adam_step, plain_fused_adam


def _net(generator: torch.Generator) -> nn.Sequential:
    net = nn.Sequential(nn.Linear(7, 16), nn.ReLU(), nn.Linear(16, 3))
    with torch.no_grad():
        for p in net.parameters():
            p.copy_(torch.randn(p.shape, generator=generator))
    return net


def _twins(**adam):
    g = torch.Generator().manual_seed(0)
    a = _net(g)
    b = copy.deepcopy(a)
    return (a, torch.optim.Adam(a.parameters(), **adam)), (b, torch.optim.Adam(b.parameters(), **adam))


def _set_grads(net: nn.Module, generator: torch.Generator) -> None:
    for p in net.parameters():
        p.grad = torch.randn(p.shape, generator=generator) * 1e-2


@pytest.mark.parametrize("lr_change", [False, True])
def test_equals_adam_step_bit_for_bit_over_many_steps(lr_change):
    """Parameters and the optimiser's state after 30 steps (a learning-rate change half-way) are
    Adam.step's exactly; the state dict round-trips between the two."""
    (a, opt_a), (b, opt_b) = _twins(lr=1e-3, fused=True)
    assert plain_fused_adam(opt_b)
    ga, gb = torch.Generator().manual_seed(1), torch.Generator().manual_seed(1)
    for step in range(30):
        if lr_change and step == 15:
            opt_a.param_groups[0]["lr"] = opt_b.param_groups[0]["lr"] = 3e-4
        _set_grads(a, ga), _set_grads(b, gb)
        opt_a.step()
        adam_step(opt_b)
    for pa, pb in zip(a.parameters(), b.parameters(), strict=True):
        assert torch.equal(pa, pb)
        for key in ("step", "exp_avg", "exp_avg_sq"):
            assert torch.equal(opt_a.state[pa][key], opt_b.state[pb][key])
    opt_b.load_state_dict(copy.deepcopy(opt_a.state_dict()))  # the state is the optimiser's own: it loads, steps on
    _set_grads(a, ga), _set_grads(b, gb)
    opt_a.step()
    adam_step(opt_b)
    assert all(torch.equal(pa, pb) for pa, pb in zip(a.parameters(), b.parameters(), strict=True))


@pytest.mark.parametrize(
    "adam", [dict(fused=False), dict(fused=True, amsgrad=True), dict(fused=True, weight_decay=0.1),
             dict(fused=True, maximize=True)],  # fmt: skip
)
def test_other_adams_take_their_own_step(adam):
    """Any setting the plain fused step does not compute goes through optimizer.step(): same values."""
    (a, opt_a), (b, opt_b) = _twins(lr=1e-3, **adam)
    assert not plain_fused_adam(opt_b)
    ga, gb = torch.Generator().manual_seed(2), torch.Generator().manual_seed(2)
    for _ in range(5):
        _set_grads(a, ga), _set_grads(b, gb)
        opt_a.step()
        adam_step(opt_b)
    assert all(torch.equal(pa, pb) for pa, pb in zip(a.parameters(), b.parameters(), strict=True))


def test_hooks_and_missing_gradients_fall_back_to_step():
    """A registered step hook runs (the optimiser's own step is taken); a parameter without a gradient
    is left alone, as Adam.step leaves it."""
    (a, opt_a), (b, opt_b) = _twins(lr=1e-3, fused=True)
    calls = []
    handle = opt_b.register_step_post_hook(lambda *args: calls.append(1))
    assert not plain_fused_adam(opt_b)
    g = torch.Generator().manual_seed(3)
    _set_grads(b, g)
    adam_step(opt_b)
    assert calls == [1]
    handle.remove()
    assert plain_fused_adam(opt_b)
    _set_grads(a, torch.Generator().manual_seed(3))
    opt_a.step()
    _set_grads(a, g), _set_grads(b, torch.Generator().manual_seed(4))
    last = list(b.parameters())[-1]
    last.grad, before = None, last.detach().clone()
    adam_step(opt_b)
    assert torch.equal(last, before)
