"""Subnormals flushed to zero in the update (fast.subnormal): the mode is scoped; the networks come out the same."""

from __future__ import annotations

import copy

import pytest
import torch
from tensordict import TensorDict

from gchgg.ddpg.agent import DDPGAgent
from gchgg.fast.subnormal import flush_subnormals, flushing

OBS, GOAL, ACT, HIDDEN = 10, 3, 4, (32, 32)
SUBNORMAL = 1e-39  # below float32's smallest normal number, 1.18e-38


def test_the_mode_holds_inside_the_block_only_and_a_mode_already_on_stays_on():
    tiny = torch.tensor([SUBNORMAL])
    assert not flushing() and float(tiny * 1.0) > 0
    with flush_subnormals():
        assert flushing() and float(tiny * 1.0) == 0.0
        with flush_subnormals():  # nested: leaving the inner block keeps the outer one's mode
            pass
        assert flushing()
    assert not flushing()
    with flush_subnormals(False):
        assert not flushing()
    torch.set_flush_denormal(True)
    try:
        with flush_subnormals():
            pass
        assert flushing(), "a block must leave a mode the caller had set on"
    finally:
        torch.set_flush_denormal(False)


def test_an_error_in_the_block_still_restores_the_mode():
    with pytest.raises(RuntimeError, match="inside"), flush_subnormals():
        raise RuntimeError("inside")
    assert not flushing()


def _batches(n: int, generator: torch.Generator) -> list[TensorDict]:
    def batch():
        obs = torch.randn(64, OBS, generator=generator)
        return TensorDict({
            "observation": obs, "desired_goal": torch.randn(64, GOAL, generator=generator),
            "action": torch.rand(64, ACT, generator=generator) * 2 - 1,
            "next": {"observation": obs + 0.1 * torch.randn(64, OBS, generator=generator),
                     "reward": -(torch.rand(64, 1, generator=generator) < 0.7).float()},
        }, [64])  # fmt: skip

    return [batch() for _ in range(n)]


def _agent_with_dead_units() -> DDPGAgent:
    """An agent after 5 updates whose first hidden layer has 8 units that never fire (bias -1000) in both
    networks, their weights' Adam moments set into the subnormal range: as a long run leaves them."""
    g = torch.Generator().manual_seed(0)
    agent = DDPGAgent(OBS, GOAL, ACT, hidden=HIDDEN, generator=g, matmul="default", subnormals="keep")
    for batch in _batches(5, g):
        agent.update(batch)
    for network, optimizer in ((agent.actor, agent.actor_optimizer), (agent.critic, agent.critic_optimizer)):
        first = next(m for m in network.modules() if isinstance(m, torch.nn.Linear))
        with torch.no_grad():
            first.bias[:8] = -1000.0
        for parameter in (first.weight, first.bias):
            state = optimizer.state[parameter]
            state["exp_avg"][:8] = SUBNORMAL
            state["exp_avg_sq"][:8] = SUBNORMAL
    return agent


def test_updates_with_subnormals_flushed_give_the_same_networks_bit_for_bit():
    """The dead units' weights get zero gradients, so their moments only decay: flushed they are 0 at once,
    kept they stay subnormal; every weight, target weight and loss comes out the same either way."""
    start = _agent_with_dead_units()
    batches = _batches(40, torch.Generator().manual_seed(1))
    runs = {}
    for mode in ("keep", "flush"):
        agent = copy.deepcopy(start)
        agent.subnormals = mode
        losses = [agent.update(batch) for batch in batches]
        runs[mode] = agent, losses
    (kept, kept_losses), (flushed, flushed_losses) = runs["keep"], runs["flush"]
    assert kept_losses == flushed_losses
    for a, b in zip(kept.loss_module.parameters(), flushed.loss_module.parameters(), strict=True):
        assert torch.equal(a, b)
    first = next(m for m in kept.actor.modules() if isinstance(m, torch.nn.Linear))
    flushed_first = next(m for m in flushed.actor.modules() if isinstance(m, torch.nn.Linear))
    kept_moment = kept.actor_optimizer.state[first.weight]["exp_avg"][:8]
    flushed_moment = flushed.actor_optimizer.state[flushed_first.weight]["exp_avg"][:8]
    assert bool(((kept_moment != 0) & (kept_moment.abs() < torch.finfo(torch.float32).tiny)).any())
    assert bool((flushed_moment == 0).all())
    assert not flushing()  # the update leaves the thread's mode as it was


def test_a_bad_setting_is_named():
    with pytest.raises(ValueError, match="subnormals must be one of 'auto', 'flush', 'keep', got 'off'"):
        DDPGAgent(OBS, GOAL, ACT, hidden=HIDDEN, subnormals="off")
