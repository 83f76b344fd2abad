"""The oneDNN linear layer computes what ``nn.Linear`` computes, and the ``matmul`` setting picks it."""

from __future__ import annotations

import copy
import io
import os
import platform

import pytest
import torch
from tensordict import TensorDict
from torch import nn

from gchgg.ddpg.agent import DDPGAgent, load_policy
from gchgg.fast import linear
from gchgg.fast.linear import (
    MIN_BATCH,
    OneDNNLinear,
    onednn_available,
    resolve_matmul,
    use_onednn,
)

needs_onednn = pytest.mark.skipif(not onednn_available(), reason="this torch build has no oneDNN linear")


def _reference(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """x·Wᵀ + b in float64, written out (shares nothing with the code under test)."""
    return (x.double()[:, None, :] * weight.double()[None, :, :]).sum(-1) + bias.double()


@needs_onednn
@pytest.mark.parametrize("n_in,n_out", [(31, 256), (256, 256), (256, 3)])
@pytest.mark.parametrize("input_grad", [True, False])
def test_values_and_gradients_match_float64_reference(n_in, n_out, input_grad):
    g = torch.Generator().manual_seed(0)
    layer = OneDNNLinear(n_in, n_out)
    with torch.no_grad():
        layer.weight.copy_(torch.randn(n_out, n_in, generator=g) / n_in**0.5)
        layer.bias.copy_(torch.randn(n_out, generator=g))
    x = torch.randn(256, n_in, generator=g).requires_grad_(input_grad)
    grad_y = torch.randn(256, n_out, generator=g)
    y = layer(x)
    y.backward(grad_y)

    x64, w64 = x.detach().double().requires_grad_(True), layer.weight.detach().double().requires_grad_(True)
    b64 = layer.bias.detach().double().requires_grad_(True)
    y64 = _reference(x64, w64, b64)
    y64.backward(grad_y.double())
    assert y.dtype == torch.float32
    torch.testing.assert_close(y.double(), y64, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(layer.weight.grad.double(), w64.grad, rtol=1e-5, atol=1e-4)
    torch.testing.assert_close(layer.bias.grad.double(), b64.grad, rtol=1e-5, atol=1e-4)
    if input_grad:
        torch.testing.assert_close(x.grad.double(), x64.grad, rtol=1e-5, atol=1e-4)
    else:
        assert x.grad is None


@needs_onednn
def test_small_batches_tracing_and_other_dtypes_take_torch_linear_exactly():
    layer = OneDNNLinear(256, 256)
    small = torch.randn(MIN_BATCH - 1, 256)
    assert torch.equal(layer(small), nn.functional.linear(small, layer.weight, layer.bias))
    big = torch.randn(MIN_BATCH, 256)
    traced = torch.jit.trace(layer, big)
    assert "mkldnn" not in str(traced.graph)
    assert torch.equal(traced(big), nn.functional.linear(big, layer.weight, layer.bias))
    double = copy.deepcopy(layer).double()
    x64 = big.double()
    assert torch.equal(double(x64), nn.functional.linear(x64, double.weight, double.bias))
    batched = torch.randn(2, MIN_BATCH, 256)  # 3-D input
    assert torch.equal(layer(batched), nn.functional.linear(batched, layer.weight, layer.bias))


@needs_onednn
def test_use_onednn_converts_wide_layers_in_place_and_back():
    net = nn.Sequential(nn.Linear(31, 256), nn.ReLU(), nn.Linear(256, 256), nn.ReLU(), nn.Linear(256, 3))
    params = list(net.parameters())
    keys = list(net.state_dict())
    use_onednn(net, "onednn")
    assert [type(m) for m in net if isinstance(m, nn.Linear)] == [OneDNNLinear, OneDNNLinear, nn.Linear]
    assert all(a is b for a, b in zip(params, net.parameters(), strict=True))  # optimisers keep working
    assert list(net.state_dict()) == keys
    use_onednn(net, "default")
    assert all(type(m) is nn.Linear for m in net if isinstance(m, nn.Linear))


def test_resolve_matmul_names_the_setting_and_falls_back(monkeypatch):
    with pytest.raises(ValueError, match=r"matmul must be one of \['auto', 'onednn', 'default'\], got 'mkl'"):
        resolve_matmul("mkl")
    assert resolve_matmul("default") == "default"
    monkeypatch.setattr(linear, "onednn_available", lambda: False)
    assert resolve_matmul("auto") == "default"
    with pytest.raises(RuntimeError, match="matmul='onednn' but this torch build has no oneDNN linear"):
        resolve_matmul("onednn")
    net = use_onednn(nn.Sequential(nn.Linear(256, 256)), "auto")
    assert type(net[0]) is nn.Linear


@needs_onednn
def test_auto_takes_onednn_only_on_cpus_it_was_measured_faster_on(monkeypatch):
    """float32: oneDNN's update 1.59x torch's BLAS on AMD at AVX512, 0.80x on AMD at AVX2 and 0.85x on an
    Intel Xeon at AVX512 (benchmarks/agent_update.py), so auto keeps BLAS there; bfloat16: only oneDNN has it."""
    cases = (("AVX512", "AuthenticAMD", "onednn"), ("AVX512", "GenuineIntel", "default"),
             ("AVX2", "AuthenticAMD", "default"), ("DEFAULT", "", "default"))  # fmt: skip
    for capability, vendor, backend in cases:
        monkeypatch.setattr(linear, "cpu_capability", lambda capability=capability: capability)
        monkeypatch.setattr(linear, "cpu_vendor", lambda vendor=vendor: vendor)
        assert resolve_matmul("auto") == backend, (capability, vendor)
        assert resolve_matmul("auto", "bfloat16") == "onednn"
        assert resolve_matmul("onednn") == "onednn"  # asked for, it is used on any CPU
        assert resolve_matmul("default") == "default"
        net = use_onednn(nn.Sequential(nn.Linear(256, 256)), "auto")
        assert type(net[0]) is (OneDNNLinear if backend == "onednn" else nn.Linear)
    with pytest.raises(ValueError, match="resolve_matmul takes a resolved precision.*got 'auto'"):
        resolve_matmul("auto", "auto")
    # This machine, unpatched: auto's choice follows from its CPU as /proc/cpuinfo describes it (read here).
    monkeypatch.undo()
    vendor, flags = _cpuinfo()
    assert linear.cpu_vendor() == vendor
    expected_capability = _expected_capability(flags)
    if expected_capability is not None:
        assert linear.cpu_capability() == expected_capability
    faster = (linear.cpu_capability(), vendor) == ("AVX512", "AuthenticAMD")  # the one measured-faster row
    assert resolve_matmul("auto") == ("onednn" if faster else "default")
    assert resolve_matmul("auto", "bfloat16") == "onednn"


def _cpuinfo() -> tuple[str, set[str]]:
    """The first CPU's vendor and flags in /proc/cpuinfo ("" and no flags where there is none)."""
    vendor, flags = "", set()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                key, _, value = line.partition(":")
                if key.strip() == "vendor_id" and not vendor:
                    vendor = value.strip()
                if key.strip() == "flags" and not flags:
                    flags = set(value.split())
    except OSError:
        pass
    return vendor, flags


def _expected_capability(flags: set[str]) -> str | None:
    """The capability torch's x86 dispatcher picks from the CPU's flags (ATen: AVX512 needs avx512f, bw, vl, fma
    and dq; AVX2 needs avx2 and fma), lowered by ATEN_CPU_CAPABILITY; None where that cannot be told here."""
    if platform.machine() not in ("x86_64", "AMD64") or not flags:
        return None
    if {"avx512f", "avx512bw", "avx512vl", "avx512dq", "fma"} <= flags:
        found = "AVX512"
    elif {"avx2", "fma"} <= flags:
        found = "AVX2"
    else:
        found = "DEFAULT"
    order = ["DEFAULT", "AVX2", "AVX512"]
    asked = os.environ.get("ATEN_CPU_CAPABILITY", "").upper()
    return order[min(order.index(found), order.index(asked))] if asked in order else found


def test_cpu_vendor_reads_the_vendor_line(monkeypatch):
    """cpu_vendor reads /proc/cpuinfo's vendor_id line, and gives "" where there is none or no file."""
    files = {"intel": "processor\t: 0\nvendor_id\t: GenuineIntel\ncpu family\t: 6\n",
             "amd": "processor\t: 0\nvendor_id\t: AuthenticAMD\nvendor_id\t: Other\n", "arm": "processor\t: 0\n"}
    expected = {"intel": "GenuineIntel", "amd": "AuthenticAMD", "arm": "", "missing": ""}
    try:
        for name, vendor in expected.items():
            def fake_open(path, *args, name=name, **kwargs):
                assert path == "/proc/cpuinfo"
                if name == "missing":
                    raise FileNotFoundError(path)
                return io.StringIO(files[name])

            monkeypatch.setattr(linear, "open", fake_open, raising=False)  # the module's open shadows the builtin
            linear.cpu_vendor.cache_clear()
            assert linear.cpu_vendor() == vendor, name
    finally:
        monkeypatch.undo()
        linear.cpu_vendor.cache_clear()


def _batch(generator: torch.Generator, size: int = 256) -> TensorDict:
    return TensorDict(
        {
            "observation": torch.randn(size, 25, generator=generator),
            "desired_goal": torch.randn(size, 3, generator=generator),
            "action": torch.rand(size, 3, generator=generator) * 2 - 1,
            "next": {
                "observation": torch.randn(size, 25, generator=generator),
                "reward": -(torch.rand(size, 1, generator=generator) < 0.8).float(),
            },
        },
        [size],
    )


@needs_onednn
def test_agent_update_on_onednn_agrees_with_torch_blas_and_repeats_exactly():
    """One update on a fixed batch: the same losses and gradients to float32 rounding; and two oneDNN
    agents fed the same batches stay bit-identical (what exact resume needs)."""
    g = torch.Generator().manual_seed(0)
    batches = [_batch(g) for _ in range(3)]
    agents = {m: DDPGAgent(25, 3, 3, generator=torch.Generator().manual_seed(1), matmul=m)
              for m in ("default", "onednn")}
    assert any(isinstance(m, OneDNNLinear) for m in agents["onednn"].loss_module.modules())
    assert not any(isinstance(m, OneDNNLinear) for m in agents["default"].loss_module.modules())
    for agent in agents.values():
        agent.update_normalizer(batches[0]["observation"], batches[0]["desired_goal"])
    grads = {}
    for name, agent in agents.items():
        loss = agent.loss_module
        out = loss.losses(*loss.inputs(batches[0]))
        (out[0] + out[1]).backward()
        grads[name] = [p.grad.clone() for p in loss.parameters() if p.grad is not None]
        for p in loss.parameters():
            p.grad = None
    assert len(grads["default"]) == len(grads["onednn"]) == 16
    for a, b in zip(grads["default"], grads["onednn"], strict=True):
        assert (a - b).abs().max() <= 1e-5 * a.abs().max()

    twin = copy.deepcopy(agents["onednn"])
    for batch in batches:
        assert agents["onednn"].update(batch) == twin.update(batch)
    for a, b in zip(agents["onednn"].loss_module.parameters(), twin.loss_module.parameters(), strict=True):
        assert torch.equal(a, b)


@needs_onednn
def test_load_policy_takes_the_backend_and_the_state_loads_under_either():
    agent = DDPGAgent(25, 3, 3, generator=torch.Generator().manual_seed(1), matmul="onednn")
    state = agent.policy_state()
    fast, plain = load_policy(state, "onednn"), load_policy(state, "default")
    assert any(isinstance(m, OneDNNLinear) for m in fast.modules())
    assert not any(isinstance(m, OneDNNLinear) for m in plain.modules())
    obs, goal = torch.randn(256, 25), torch.randn(256, 3)
    with torch.no_grad():
        torch.testing.assert_close(fast(obs, goal), plain(obs, goal), rtol=1e-5, atol=1e-6)


needs_bf16 = pytest.mark.skipif(not linear.bf16_available(), reason="no native bfloat16 oneDNN products here")


def _bf16(t: torch.Tensor) -> torch.Tensor:
    return t.to(torch.bfloat16).double()


def _bf16_misses(result: torch.Tensor, reference: torch.Tensor) -> tuple[float, float]:
    """How ``result`` (float32) departs from ``reference`` (float64, the product of bfloat16-rounded operands in
    exact arithmetic): the fraction of entries that are not ``reference`` rounded to bfloat16 (through float32,
    as oneDNN's float32 accumulator rounds), and the largest departure in bfloat16 units in the last place."""
    rounded = reference.float().to(torch.bfloat16).double()
    ulp = torch.ldexp(torch.ones_like(rounded), torch.frexp(rounded.abs().clamp_min(2.0**-100))[1] - 8)
    return (result.double() != rounded).double().mean().item(), ((result.double() - rounded).abs() / ulp).max().item()


@needs_bf16
def test_bfloat16_products_are_float32_results_of_rounded_inputs():
    """Inside products_in("bfloat16"): y and the gradients are the exact products of bfloat16-rounded operands,
    rounded to bfloat16 (a float32 accumulator's double rounding may miss by one unit in the last place, rarely);
    products of float16 or float32 operands miss that rounding on about half the entries (unrounded, they are no
    bfloat16 values at all), so they fail. Outside the block the layer is float32 again."""
    g = torch.Generator().manual_seed(0)
    layer = OneDNNLinear(64, 128)
    x = torch.randn(MIN_BATCH, 64, generator=g).requires_grad_(True)
    grad_y = torch.randn(MIN_BATCH, 128, generator=g)
    with linear.products_in("bfloat16"):
        y = layer(x)
        y.backward(grad_y)
    w, b = layer.weight.detach(), layer.bias.detach()
    assert y.dtype == x.grad.dtype == layer.weight.grad.dtype == torch.float32
    references = {
        "y": (y, _bf16(x.detach()) @ _bf16(w).T + b.double()),  # the float32 bias joins before the rounding
        "x.grad": (x.grad, _bf16(grad_y) @ _bf16(w)),
        "weight.grad": (layer.weight.grad, _bf16(grad_y).T @ _bf16(x.detach())),
    }
    for name, (result, reference) in references.items():
        assert torch.equal(result, result.to(torch.bfloat16).float()), f"{name} is not a bfloat16 value"
        misses, worst = _bf16_misses(result, reference)
        assert misses <= 0.01 and worst <= 1.0, (name, misses, worst)
        # and far from the float32 product of the unrounded operands (bfloat16's 2**-9, not float32's 2**-24)
        plain = {"y": x.detach().double() @ w.double().T + b.double(), "x.grad": grad_y.double() @ w.double(),
                 "weight.grad": grad_y.double().T @ x.detach().double()}[name]
        assert ((result.double() - plain).abs() / plain.abs().clamp_min(1e-3)).median() > 2**-12, name
    assert not torch.equal(y, layer(x))  # float32 outside the block
    torch.testing.assert_close(layer(x).double(), x.detach().double() @ w.double().T + b.double(), rtol=1e-5, atol=1e-5)


@needs_bf16
def test_the_agents_resolved_matmul_gives_an_evaluator_the_agents_layers():
    """With bfloat16 products, matmul=auto puts the agent's layers on oneDNN on any CPU, though float32
    alone would keep torch's BLAS on some: agent.matmul is the backend its layers got, and a policy loaded
    with it (the background evaluator's) has the same layers and acts as the agent does, bit for bit."""
    agent = DDPGAgent(25, 3, 3, generator=torch.Generator().manual_seed(2), precision="auto")
    assert agent.precision == "bfloat16" and agent.matmul == "onednn"
    actor = load_policy(agent.policy_state(), agent.matmul)
    assert [type(m) for m in actor.modules()] == [type(m) for m in agent.actor.modules()]
    g = torch.Generator().manual_seed(3)
    obs, goal = torch.randn(100, 25, generator=g), torch.randn(100, 3, generator=g)
    with torch.no_grad():
        assert torch.equal(actor(obs, goal), agent.act(obs, goal))
    assert DDPGAgent(25, 3, 3, matmul="default", precision="float32").matmul == "default"


@needs_onednn
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
@pytest.mark.parametrize("rows,n_in,n_out", [(256, 31, 256), (256, 256, 256), (64, 256, 256)])
def test_onednn_mm_is_the_backward_product_oneDNN_computes_on_the_views(dtype, rows, n_in, n_out):
    """onednn_mm(a, b) gives the values oneDNN's linear gives on the transposed views the backward
    multiplies (∂y·W and ∂yᵀ·x), and those are a·b of the operands to the dtype's rounding."""
    if dtype == torch.bfloat16 and not linear.bf16_available():
        pytest.skip("no native bfloat16 oneDNN products on this CPU")
    g = torch.Generator().manual_seed(1)
    weight = torch.randn(n_out, n_in, generator=g).to(dtype)
    x = torch.randn(rows, n_in, generator=g).to(dtype)
    grad_y = torch.randn(rows, n_out, generator=g).to(dtype)
    for a, b in ((grad_y, weight), (grad_y.t(), x)):
        product = linear.onednn_mm(a, b)
        assert product.dtype == dtype and product.shape == (a.shape[0], b.shape[1])
        assert torch.equal(product, linear.onednn_linear(a, b.t(), None))
        tolerance = dict(rtol=2**-7, atol=0.05) if dtype == torch.bfloat16 else dict(rtol=1e-5, atol=1e-4)
        torch.testing.assert_close(product.double(), a.double() @ b.double(), **tolerance)


def test_precision_setting_is_checked_and_auto_resolves_by_machine():
    with pytest.raises(ValueError, match="precision must be one of \\['auto', 'float32', 'bfloat16'\\], got 'fp16'"):
        linear.resolve_precision("fp16")
    assert linear.resolve_precision("auto") == ("bfloat16" if linear.bf16_available() else "float32")
    assert linear.resolve_precision("auto", "default") == "float32"  # torch's BLAS: no bfloat16 products
    assert DDPGAgent(5, 3, 2, hidden=(32,), precision="auto", matmul="default").precision == "float32"
    assert DDPGAgent(5, 3, 2, hidden=(32,)).precision == "float32"  # the library's default: the math as written
    if linear.bf16_available():
        with pytest.raises(ValueError,
                           match="precision='bfloat16' computes the products with oneDNN, but matmul='default'"):
            DDPGAgent(5, 3, 2, hidden=(32,), matmul="default", precision="bfloat16")
