"""Tests of gchgg.fast.fused_update: the hand-differentiated DDPG update equals autograd's on the loss module,
bit for bit, on torch's BLAS and on oneDNN layers in float32 and bfloat16, and the agent chooses it
wherever it applies; compiled (``gradients=compiled``) it equals the eager one to float32 rounding."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from torch import nn

from gchgg.ddpg import DDPGAgent, HindsightDDPGLoss, make_ddpg_networks
from gchgg.ddpg.agent import hand_differentiated
from gchgg.fast import fused_update
from gchgg.fast.fused_update import FusedDDPGUpdate, unsupported
from gchgg.fast.linear import bf16_available, onednn_available, products_in, use_onednn

OBS, GOAL, ACT = 6, 3, 2


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def tensors(size: int, seed: int) -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(seed)
    return (
        torch.randn(size, OBS, generator=g) * 2 + 1,
        torch.randn(size, GOAL, generator=g),
        torch.rand(size, ACT, generator=g) * 2 - 1,
        torch.randn(size, OBS, generator=g) * 2 + 1,
        -(torch.rand(size, 1, generator=g) < 0.5).float(),
    )


def batch_of(values: tuple[torch.Tensor, ...]) -> TensorDict:
    obs, goal, action, next_obs, reward = values
    return TensorDict({"observation": obs, "desired_goal": goal, "action": action,
                       "next": {"observation": next_obs, "reward": reward}}, [len(obs)])  # fmt: skip


def loss_module(hidden, seed: int = 0, **kwargs) -> HindsightDDPGLoss:
    g = torch.Generator().manual_seed(seed)
    actor, critic = make_ddpg_networks(OBS, GOAL, ACT, hidden, generator=g)
    loss = HindsightDDPGLoss(actor, critic, **kwargs)
    obs, goal, *_ = tensors(64, seed + 100)
    loss.actor.observation_normalizer.update(obs)
    loss.actor.goal_normalizer.update(goal)
    with torch.no_grad():  # target networks apart from the online ones, as after some updates
        for p in list(loss.target_actor.parameters()) + list(loss.target_critic.parameters()):
            p.add_(torch.randn(p.shape, generator=g) * 0.05)
    return loss


def autograd_gradients(loss: HindsightDDPGLoss, values) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """The reference: the loss module's losses, differentiated by autograd from zeroed gradients."""
    parameters = list(loss.actor.parameters()) + list(loss.critic.parameters())
    for p in parameters:
        p.grad = None
    out = loss.losses(*values)
    (out[0] + out[1]).backward()
    grads = [p.grad.clone() for p in parameters]
    for p in parameters:
        p.grad = None
    return [o.detach() for o in out], grads


@pytest.mark.parametrize(
    "hidden, size, settings",
    [
        ((32, 32), 16, {}),
        ((16,), 5, {"action_l2": 0.0}),
        ((24, 8, 16), 64, {"clip_return": False, "gamma": 0.9, "action_l2": 0.3}),
        ((32, 32), 40, {"action_l2": 0.3}),  # 0.3 / 80 rounds otherwise than 2 · 0.3 / 80: autograd's order matters
        ((32, 32), 256, {"action_l2": 0.7}),
    ],
)
def test_fused_losses_and_gradients_are_autograds_bit_for_bit(hidden, size, settings):
    loss = loss_module(hidden, **settings)
    values = tensors(size, seed=1)
    reference_out, reference_grads = autograd_gradients(loss, values)

    fused = FusedDDPGUpdate(loss)
    for p in list(loss.actor.parameters()) + list(loss.critic.parameters()):  # stale gradients are overwritten
        p.grad = torch.full_like(p, 7.0)
    out = fused.forward(*values)
    fused.backward()
    grads = [p.grad for p in list(loss.actor.parameters()) + list(loss.critic.parameters())]
    for name, a, b in zip(("loss_actor", "loss_value", "pred_value", "target_value"), reference_out, out, strict=True):
        assert torch.equal(a, b), name
        assert not b.requires_grad
    for i, (a, b) in enumerate(zip(reference_grads, grads, strict=True)):
        assert torch.equal(a, b), f"gradient {i}: largest difference {(a - b).abs().max().item():.3g}"
    # nothing reached the target networks or the normalisers
    assert all(p.grad is None for p in list(loss.target_actor.parameters()) + list(loss.target_critic.parameters()))


def test_the_fused_update_computes_the_losses_by_the_loss_modules_own_formulas():
    """The loss is the one source of the math: the fused update calls its formulas (here changed ones), it does
    not restate them."""

    class Changed(HindsightDDPGLoss):
        @staticmethod
        def critic_objective(pred_value, target_value):
            return (pred_value - target_value).abs().mean()

        @staticmethod
        def actor_objective(policy_value, policy_action, action_l2):
            return -policy_value.max() + action_l2 * policy_action.abs().mean()

    loss = Changed(*make_ddpg_networks(OBS, GOAL, ACT, (16,), generator=torch.Generator().manual_seed(0)), gamma=0.9)
    values = tensors(8, seed=1)
    out = FusedDDPGUpdate(loss).forward(*values)
    for name, a, b in zip(("loss_actor", "loss_value", "pred_value", "target_value"), loss.losses(*values), out,
                          strict=True):  # fmt: skip
        assert torch.equal(a.detach(), b), name


def test_agent_with_fused_updates_trains_exactly_as_with_autograd():
    agents = {update: DDPGAgent(OBS, GOAL, ACT, hidden=(32, 32), generator=torch.Generator().manual_seed(0),
                                matmul="default", gradients=update)
              for update in ("fused", "autograd")}  # fmt: skip
    assert {a.gradients for a in agents.values()} == {"fused", "autograd"}
    for agent in agents.values():
        agent.update_normalizer(*tensors(200, 5)[:2])
    for step in range(45):  # across two target-network updates (every 20th)
        batch = batch_of(tensors(32, 10 + step))
        results = [agent.update(batch) for agent in agents.values()]
        assert results[0] == results[1]
    fused, reference = (agents[k].state_dict() for k in ("fused", "autograd"))
    for key, value in reference["networks"].items():
        assert torch.equal(fused["networks"][key], value), key
    for which in ("actor_optimizer", "critic_optimizer"):
        for index, state in reference[which]["state"].items():
            for name, value in state.items():
                assert torch.equal(fused[which]["state"][index][name], value), (which, index, name)


ONEDNN_PRECISIONS = [
    pytest.param("float32", marks=pytest.mark.skipif(not onednn_available(), reason="this torch has no oneDNN linear")),
    pytest.param("bfloat16", marks=pytest.mark.skipif(not bf16_available(), reason="no native bfloat16 products")),
]


@pytest.mark.parametrize("precision", ONEDNN_PRECISIONS)
@pytest.mark.parametrize("size", [96, 40])  # oneDNN's products from MIN_BATCH (64) rows, torch BLAS's below
def test_fused_equals_autograd_on_onednn_layers_bit_for_bit(precision, size):
    loss = use_onednn(loss_module((64, 32, 128), action_l2=0.3), "onednn")  # the 2- and 6-wide layers stay plain
    values = tensors(size, seed=4)
    with products_in(precision):
        reference_out, reference_grads = autograd_gradients(loss, values)
    fused = FusedDDPGUpdate(loss, precision=precision)
    out = fused.forward(*values)
    fused.backward()
    grads = [p.grad.clone() for p in list(loss.actor.parameters()) + list(loss.critic.parameters())]
    for name, a, b in zip(("loss_actor", "loss_value", "pred_value", "target_value"), reference_out, out, strict=True):
        assert torch.equal(a, b), name
        assert b.dtype == torch.float32
    for i, (a, b) in enumerate(zip(reference_grads, grads, strict=True)):
        assert torch.equal(a, b), f"gradient {i}: largest difference {(a - b).abs().max().item():.3g}"
    if precision == "bfloat16" and size >= 64:  # the products were rounded: not float32's gradients
        float32 = FusedDDPGUpdate(loss, precision="float32")
        float32.forward(*values)
        float32.backward()
        assert not all(torch.equal(a, p.grad) for a, p in
                       zip(grads, list(loss.actor.parameters()) + list(loss.critic.parameters()), strict=True))


@pytest.mark.parametrize("precision", ONEDNN_PRECISIONS)
def test_agent_on_onednn_trains_with_fused_updates_exactly_as_with_autograd(precision):
    agents = {update: DDPGAgent(OBS, GOAL, ACT, hidden=(64, 64), generator=torch.Generator().manual_seed(0),
                                matmul="onednn", precision=precision, gradients=update)
              for update in ("fused", "autograd")}  # fmt: skip
    assert [a.gradients for a in agents.values()] == ["fused", "autograd"]
    for agent in agents.values():
        agent.update_normalizer(*tensors(200, 5)[:2])
    for step in range(25):  # across a target-network update, batches above and below MIN_BATCH
        batch = batch_of(tensors(80 if step % 3 else 16, 30 + step))
        results = [agent.update(batch) for agent in agents.values()]
        assert results[0] == results[1], step
    fused, reference = (agents[k].state_dict()["networks"] for k in ("fused", "autograd"))
    assert all(torch.equal(fused[key], value) for key, value in reference.items())


def test_auto_takes_the_fused_update_wherever_it_applies():
    agent = DDPGAgent(OBS, GOAL, ACT, hidden=(16,), matmul="default")  # gradients="auto"
    assert agent.gradients == "fused"
    assert DDPGAgent(OBS, GOAL, ACT, hidden=(16,), matmul="default", gradients="autograd").gradients == "autograd"
    if onednn_available():  # oneDNN layers too, in float32 (in bfloat16 auto compiles it where it can: below)
        assert DDPGAgent(OBS, GOAL, ACT, hidden=(32, 32), matmul="onednn", precision="float32").gradients == "fused"
    with pytest.raises(ValueError, match=r"gradients must be one of \[.*'compiled', 'autograd'\], got 'manual'"):
        DDPGAgent(OBS, GOAL, ACT, hidden=(16,), gradients="manual")
    agent = DDPGAgent(OBS, GOAL, ACT, hidden=(16,), matmul="default", gradients="autograd")
    agent.critic.mlp[1] = nn.Tanh()  # a network the fused update does not compute: auto falls back, fused refuses
    assert hand_differentiated(agent.loss_module, "auto", agent.precision) is None
    with pytest.raises(ValueError, match="gradients='fused' differentiates ReLU MLPs.*layer 1 is Tanh"):
        hand_differentiated(agent.loss_module, "fused", agent.precision)


def test_unsupported_networks_are_named():
    loss = loss_module((16,))
    assert unsupported(loss) is None
    loss.critic.mlp[1] = nn.Tanh()
    assert unsupported(loss) == "the critic's mlp: layer 1 is Tanh, not ReLU"
    with pytest.raises(ValueError, match="ReLU MLPs of plain float32 nn.Linear layers: the critic's mlp"):
        FusedDDPGUpdate(loss)
    with pytest.raises(ValueError, match="precision must be 'float32' or 'bfloat16'.*got 'auto'"):
        FusedDDPGUpdate(loss_module((16,)), precision="auto")
    loss = loss_module((16,))
    loss.target_actor.mlp[0].bias = None
    assert unsupported(loss) == "the target_actor's mlp: layer 0 is not a float32 CPU nn.Linear with a bias"


def test_backward_needs_a_forward_and_runs_once_per_forward():
    fused = FusedDDPGUpdate(loss_module((16,)))
    with pytest.raises(RuntimeError, match="needs a forward"):
        fused.backward()
    fused.forward(*tensors(8, 2))
    fused.backward()
    with pytest.raises(RuntimeError, match="runs once per forward"):
        fused.backward()


def test_a_reward_of_the_wrong_shape_is_refused_like_the_loss_module_does():
    values = list(tensors(8, 3))
    values[4] = values[4].reshape(-1)
    with pytest.raises(ValueError, match=r"the reward must be \[B, 1\]"):
        FusedDDPGUpdate(loss_module((16,))).forward(*values)


@pytest.mark.parametrize("precision", ONEDNN_PRECISIONS)
def test_fused_update_follows_target_networks_moved_or_loaded_in_place(precision):
    # The fused update keeps the target networks' rounded weights between updates; a target update
    # (lerp_) and a loaded state (copy_) must both reach them, as they reach autograd's update.
    def agent(gradients: str, seed: int = 0) -> DDPGAgent:
        made = DDPGAgent(OBS, GOAL, ACT, hidden=(64, 64), generator=torch.Generator().manual_seed(seed),
                         matmul="onednn", precision=precision, gradients=gradients)  # fmt: skip
        made.update_normalizer(*tensors(200, 5)[:2])
        return made

    agents = [agent("fused"), agent("autograd")]
    other = agent("autograd", seed=1)
    for step in range(3):
        other.update(batch_of(tensors(80, 60 + step)))
    for step in range(22):  # across a target update (every 20th)
        batch = batch_of(tensors(80, 30 + step))
        assert agents[0].update(batch) == agents[1].update(batch), step
    for made in agents:
        made.load_state_dict(other.state_dict())  # other target networks, copied into the same tensors
    batch = batch_of(tensors(80, 99))
    assert agents[0].update(batch) == agents[1].update(batch)


needs_compiler = pytest.mark.skipif(
    not fused_update.compiler_found(), reason="torch.compile's Inductor needs a C++ compiler"
)
COMPILED_PRECISION = "bfloat16" if bf16_available() else "float32"


@needs_compiler
@pytest.mark.skipif(not onednn_available(), reason="this torch has no oneDNN linear")
def test_compiled_update_equals_the_eager_one_to_float32_rounding():
    loss = use_onednn(loss_module((64, 32, 128), action_l2=0.3), "onednn")
    values = tensors(96, seed=4)  # oneDNN's products (from MIN_BATCH rows)
    parameters = list(loss.actor.parameters()) + list(loss.critic.parameters())
    results = {}
    for compiled in (False, True):
        update = FusedDDPGUpdate(loss, precision=COMPILED_PRECISION, compiled=compiled)
        out = update.forward(*values)
        update.backward()
        results[compiled] = (out, [p.grad.clone() for p in parameters])
    (eager_out, eager_grads), (compiled_out, compiled_grads) = results[False], results[True]
    for name, a, b in zip(("loss_actor", "loss_value", "pred_value", "target_value"), eager_out, compiled_out,
                          strict=True):  # fmt: skip
        assert b.dtype == torch.float32 and b.shape == a.shape, name
        assert torch.allclose(a, b, rtol=1e-5, atol=1e-6), name
    for i, (a, b) in enumerate(zip(eager_grads, compiled_grads, strict=True)):
        scale = a.abs().max().item()
        assert (a - b).abs().max().item() <= 1e-5 * scale, f"gradient {i}"


@needs_compiler
@pytest.mark.skipif(not onednn_available(), reason="this torch has no oneDNN linear")
def test_agent_with_compiled_gradients_trains():
    agent = DDPGAgent(OBS, GOAL, ACT, hidden=(64, 32, 128), action_l2=0.3, generator=torch.Generator().manual_seed(0),
                      matmul="onednn", precision=COMPILED_PRECISION, gradients="compiled")  # fmt: skip
    assert agent.gradients == "compiled"
    agent.update_normalizer(*tensors(200, 5)[:2])
    before = [p.clone() for p in agent.actor.parameters()]
    for step in range(3):
        values = agent.update(batch_of(tensors(96, 30 + step)))
        assert all(math.isfinite(v) for v in values.values())
    assert all(not torch.equal(a, p) for a, p in zip(before, agent.actor.parameters(), strict=True))


@pytest.mark.skipif(not onednn_available(), reason="this torch has no oneDNN linear")
def test_a_compiled_update_that_cannot_be_built_says_so(monkeypatch):
    def unbuildable(*args):
        raise RuntimeError("no C++ compiler found")

    monkeypatch.setattr(fused_update, "_compiled", lambda: unbuildable)
    update = FusedDDPGUpdate(use_onednn(loss_module((64, 64)), "onednn"), compiled=True)
    update.forward(*tensors(8, 2))  # below MIN_BATCH rows: eager, on torch's BLAS
    with pytest.raises(RuntimeError, match=r"gradients='compiled' needs torch.compile.*no C\+\+ compiler found.*"
                                           r"use gradients=fused"):  # fmt: skip
        update.forward(*tensors(64, 2))
    with pytest.raises(ValueError, match=r"compiled=True compiles the updates whose products run on oneDNN.*"
                                         r"matmul=default"):  # fmt: skip
        FusedDDPGUpdate(loss_module((16,)), compiled=True)
    agent = DDPGAgent(OBS, GOAL, ACT, hidden=(16,), matmul="default", gradients="autograd")
    agent.critic.mlp[1] = nn.Tanh()
    with pytest.raises(ValueError, match="gradients='compiled' differentiates ReLU MLPs.*layer 1 is Tanh"):
        hand_differentiated(agent.loss_module, "compiled", agent.precision)
    fallback = FusedDDPGUpdate(use_onednn(loss_module((64, 64)), "onednn"), compiled=True, fall_back=True)
    with pytest.warns(RuntimeWarning, match=r"compiled DDPG update cannot be built here.*no C\+\+ compiler found.*"
                                            r"run eagerly"):  # fmt: skip
        out = fallback.forward(*tensors(64, 2))
    assert not fallback.compiled and all(torch.isfinite(v).all() for v in out)
    if bf16_available():  # gradients=auto falls back; the agent then says it runs the eager update
        agent = DDPGAgent(OBS, GOAL, ACT, hidden=(32, 32), precision="auto", generator=torch.Generator().manual_seed(0))
        if agent.gradients == "compiled":
            agent.update_normalizer(*tensors(200, 5)[:2])
            with pytest.warns(RuntimeWarning, match="cannot be built here"):
                agent.update(batch_of(tensors(64, 3)))
            assert agent.gradients == "fused"


def test_auto_compiles_the_update_where_the_products_are_bfloat16_on_onednn_and_a_compiler_is_found(monkeypatch):
    expected = "compiled" if bf16_available() and fused_update.compiler_found() else "fused"
    assert DDPGAgent(OBS, GOAL, ACT, hidden=(32, 32), precision="auto").gradients == expected
    assert DDPGAgent(OBS, GOAL, ACT, hidden=(32, 32), precision="float32").gradients == "fused"
    monkeypatch.setattr("gchgg.ddpg.agent.compiler_found", lambda: False)
    assert DDPGAgent(OBS, GOAL, ACT, hidden=(32, 32), precision="auto").gradients == "fused"
