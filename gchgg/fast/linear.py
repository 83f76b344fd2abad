"""Linear layers whose CPU matrix products run on oneDNN: the speed device of the DDPG update.

PyTorch computes a float32 :class:`torch.nn.Linear` on the CPU with its BLAS (MKL on x86). On
the AMD EPYC (AVX-512) cores this project runs on, oneDNN's matmul runs the update's 256-wide
layers about twice as fast as MKL; on an AMD EPYC that torch runs at AVX2 it is slower (the
hidden layers' products 0.82–0.93×; ``python benchmarks/linear.py`` prints both, per layer shape
and batch size; ``python benchmarks/agent_update.py`` the whole update on each), so
``matmul=auto`` takes oneDNN only where torch runs at a CPU capability in :data:`ONEDNN_FASTER`.

:class:`OneDNNLinear` *is* an ``nn.Linear`` (same parameters, same state dict, same math): its
forward and backward compute ``x·Wᵀ + b``, ``∂x = ∂y·W`` and ``∂W = ∂yᵀ·x`` with oneDNN for 2-D
float32 CPU batches of at least :data:`MIN_BATCH` rows, and call ``F.linear`` otherwise (small
batches, where oneDNN's call costs more than it saves; tracing, export and ``torch.compile``;
other dtypes and devices). Only the order in which the products are summed differs from MKL's,
so values agree to float32 rounding (``tests/test_linear.py``). :func:`use_onednn` converts the
layers of a network in place; :func:`resolve_matmul` turns the ``matmul`` setting into a backend.

oneDNN is reached through ``torch.ops.mkldnn._linear_pointwise``, the dense-input linear that
TorchInductor's CPU backend calls; where a torch build lacks it, or the CPU is not one it was
measured faster on, ``matmul=auto`` uses torch's own BLAS.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Iterator

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["MATMUL_BACKENDS", "MIN_BATCH", "MIN_FEATURES", "ONEDNN_FASTER", "PRECISIONS", "OneDNNLinear",
           "bf16_available", "cpu_capability", "cpu_vendor", "onednn_available", "onednn_linear", "onednn_mm",
           "products_in", "resolve_matmul", "resolve_precision", "use_onednn"]  # fmt: skip

MATMUL_BACKENDS = ("auto", "onednn", "default")
"""``auto``: oneDNN where this torch has it and the products are bfloat16 or the CPU is one it was
measured faster on in float32 (:data:`ONEDNN_FASTER`), else torch's BLAS; ``onednn``: oneDNN or an
error; ``default``: torch's BLAS (``F.linear``) everywhere."""

ONEDNN_FASTER = (("AVX512", "AuthenticAMD"),)
"""The CPUs, as (capability torch runs at, vendor), on which ``matmul=auto`` takes oneDNN for float32
products: those where the whole update was measured faster on it than on torch's BLAS (MKL), one
thread, batch 256 (``python benchmarks/agent_update.py --threads 1``; docs/benchmarks.md): AMD EPYC
at AVX512 (2 cores) 1.59x. Not AMD EPYC at AVX2: 0.80x, every product but one of the update slower
on oneDNN (``benchmarks/linear.py``: the 256-wide hidden layers' 0.82-0.93x at batch 256); not an
Intel Xeon at AVX512 with AMX: 0.79x (MKL is Intel's own BLAS). Other CPUs are unmeasured and keep
torch's BLAS. bfloat16 products are oneDNN's wherever they are native (:func:`resolve_matmul`)."""

MIN_BATCH = 64
"""Rows from which a batch goes to oneDNN: below it a call's fixed cost outweighs the faster kernel
(``benchmarks/linear.py``: acting in one env, a 1-row product costs 3–12× as much on oneDNN; from 64
rows the hidden layers gain, at 256 every product of the input and hidden layers does)."""

MIN_FEATURES = 16
"""Layers narrower than this on either side (the 1–4-wide output layers) stay on ``F.linear``: their
products are too thin for oneDNN to gain (``benchmarks/linear.py``: 0.5–0.7× at 256 rows). The
input layers (observation, goal and, in the critic, action: 31 features on push_new) gain at 256
rows, and so does the whole update with them on oneDNN (``benchmarks/agent_update.py --min-features 64``
times it with the hidden layers alone)."""


PRECISIONS = ("auto", "float32", "bfloat16")
"""The dtype of the wide layers' products inside :func:`products_in`: ``float32`` (the math as
written) or ``bfloat16`` (inputs and weights rounded to bfloat16, float32 accumulation, results
rounded to bfloat16 and returned as float32; parameters, gradients and optimiser state stay float32);
``auto``: ``bfloat16`` where oneDNN computes it natively and the products run on oneDNN, else
``float32`` (:func:`resolve_precision`)."""

_product_dtype = torch.float32  # set by products_in


@contextlib.contextmanager
def products_in(precision: str) -> Iterator[None]:
    """Within the block, :class:`OneDNNLinear` layers compute their products (forward and the backward
    of a ``backward()`` called in the block) in ``precision``, one of :data:`PRECISIONS`.

    The agent wraps its update in it; acting, evaluation and export stay float32. ``bfloat16``
    raises a ``RuntimeError`` on a CPU without native bfloat16 products (:func:`bf16_available`);
    ``auto`` picks it only where it is native, so the example runs on any CPU:

    >>> layer = use_onednn(nn.Sequential(nn.Linear(256, 256)), backend="onednn")[0]
    >>> x = torch.randn(64, 256)
    >>> with products_in("auto"):  # bfloat16 products where native, else float32
    ...     y = layer(x)
    >>> y.dtype, bool(torch.allclose(y, layer(x), rtol=0.05, atol=0.05))
    (torch.float32, True)
    >>> bool(torch.equal(y, layer(x))) == (resolve_precision("auto") == "float32")  # bfloat16 rounds
    True
    """
    global _product_dtype
    dtype = getattr(torch, resolve_precision(precision))
    previous, _product_dtype = _product_dtype, dtype
    try:
        yield
    finally:
        _product_dtype = previous


def onednn_linear(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, relu: bool = False) -> torch.Tensor:
    """``x·weightᵀ + bias`` by oneDNN in the dtype of ``x`` and ``weight`` (float32 accumulation; a
    float32 ``bias`` beside bfloat16 operands is added before the result is rounded); ``x`` [B, in] and
    ``weight`` [out, in] may be strided views. With ``relu=True`` oneDNN applies the ReLU before it rounds
    the result, which gives the same values as a ReLU after (rounding is monotone and keeps 0).
    :class:`OneDNNLinear` and :class:`gchgg.fast.fused_update.FusedDDPGUpdate` compute their products with it.

    Under ``torch.compile`` it is the custom operator ``gchgg::onednn_linear``, which calls the same kernel:
    TorchInductor lowers oneDNN's linear only for the constant weights of a frozen model, and takes a custom
    operator as a call it leaves alone."""
    if torch.compiler.is_compiling():
        return torch.ops.gchgg.onednn_linear(x, weight, bias, relu)
    return _linear_pointwise(x, weight, bias, relu)


def _linear_pointwise(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, relu: bool) -> torch.Tensor:
    return torch.ops.mkldnn._linear_pointwise(x, weight, bias, "relu" if relu else "none", [], "")


# gchgg::onednn_linear: a plain operator whose CPU kernel is _linear_pointwise (a torch.library.custom_op would wrap
# each call in tens of microseconds of Python bookkeeping); its fake kernel gives TorchInductor the result's shape.
_library = torch.library.Library("gchgg", "DEF")
_library.define("onednn_linear(Tensor x, Tensor weight, Tensor? bias, bool relu) -> Tensor")
_library.impl("onednn_linear", _linear_pointwise, "CPU")


@torch.library.register_fake("gchgg::onednn_linear")
def _(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, relu: bool) -> torch.Tensor:
    return x.new_empty(x.shape[0], weight.shape[0])


def onednn_mm(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a·b`` by oneDNN in the dtype of ``a`` and ``b`` (float32 accumulation), for the backward's products,
    whose operands are transposed views (``∂y·W`` with ``W`` [out, in], ``∂yᵀ·x``).

    In bfloat16 it is ``torch.mm``, which torch computes with oneDNN's matmul on the strided operands as
    they are; :func:`onednn_linear` on the same views gives the same values (``tests/test_linear.py``) but
    first copies each transposed operand contiguous, which makes the weight gradient ``∂yᵀ·x`` slower
    (``python benchmarks/linear.py`` prints both where bfloat16 is native). In float32 ``torch.mm``
    is torch's BLAS, whose sums differ, so float32 stays :func:`onednn_linear`'s."""
    if a.dtype == torch.bfloat16:
        return torch.mm(a, b)
    return onednn_linear(a, b.t(), None)


def _product(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, dtype: torch.dtype) -> torch.Tensor:
    """:func:`onednn_linear` on ``x`` and ``weight`` rounded to ``dtype``, returned as float32."""
    if dtype == torch.float32:
        return onednn_linear(x, weight, bias)
    return onednn_linear(x.to(dtype), weight.to(dtype), bias).float()


class _OneDNNLinearFunction(torch.autograd.Function):
    """``y = x·Wᵀ + b`` with its three gradients, each one oneDNN product (the backward's through
    :func:`onednn_mm`, on the transposed views), in the product dtype given (the backward uses the forward's)."""

    @staticmethod
    def forward(
        ctx, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, dtype: torch.dtype
    ) -> torch.Tensor:
        if dtype != torch.float32:  # round once; the backward reuses the rounded copies
            x, weight = x.to(dtype), weight.to(dtype)
        ctx.save_for_backward(x, weight)
        ctx.has_bias = bias is not None
        y = onednn_linear(x, weight, bias)
        return y if dtype == torch.float32 else y.float()

    @staticmethod
    def backward(ctx, grad_y: torch.Tensor):
        x, weight = ctx.saved_tensors
        grad_y = grad_y.to(x.dtype)
        grad_x = grad_weight = grad_bias = None
        if ctx.needs_input_grad[0]:
            grad_x = onednn_mm(grad_y, weight).float()  # ∂y·W
        if ctx.needs_input_grad[1]:
            grad_weight = onednn_mm(grad_y.t(), x).float()  # ∂yᵀ·x
        if ctx.has_bias and ctx.needs_input_grad[2]:
            grad_bias = grad_y.float().sum(0)
        return grad_x, grad_weight, grad_bias, None


class OneDNNLinear(nn.Linear):
    """An :class:`torch.nn.Linear` whose large CPU float32 batches are computed by oneDNN.

    Same constructor, parameters and state dict as ``nn.Linear``. Batches that are not 2-D float32
    CPU tensors of at least :data:`MIN_BATCH` rows, and every call while tracing, exporting or
    compiling, go through ``F.linear`` unchanged. Build one through :func:`use_onednn`, which checks
    that this torch has oneDNN's linear.

    Examples:
        >>> layer = use_onednn(nn.Sequential(nn.Linear(256, 256)), backend="onednn")[0]
        >>> x = torch.randn(64, 256)
        >>> bool(torch.allclose(layer(x), F.linear(x, layer.weight, layer.bias), atol=1e-4))
        True
    """

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if (
            not (torch.jit.is_tracing() or torch.jit.is_scripting() or torch.compiler.is_compiling())
            and not torch.onnx.is_in_onnx_export()
            and x.dim() == 2
            and x.shape[0] >= MIN_BATCH
            and x.dtype == self.weight.dtype == torch.float32
            and x.device.type == "cpu"
        ):
            if torch.is_grad_enabled() and (x.requires_grad or self.weight.requires_grad):
                return _OneDNNLinearFunction.apply(x, self.weight, self.bias, _product_dtype)
            return _product(x, self.weight, self.bias, _product_dtype)  # nothing to differentiate: no autograd node
        return F.linear(x, self.weight, self.bias)


@functools.cache
def onednn_available() -> bool:
    """Whether this torch build computes a dense float32 linear with oneDNN (checked by one call)."""
    if not torch.backends.mkldnn.is_available():
        return False
    try:
        x, weight = torch.ones(2, 3), torch.ones(4, 3)
        return bool(torch.equal(onednn_linear(x, weight, None), torch.full((2, 4), 3.0)))
    except (AttributeError, RuntimeError, NotImplementedError):
        return False


@functools.cache
def bf16_available() -> bool:
    """Whether oneDNN computes bfloat16 products natively on this CPU (AVX-512 BF16, AMX)."""
    return onednn_available() and bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())


def resolve_precision(precision: str, matmul: str = "auto") -> str:
    """The products' dtype a ``precision`` setting (one of :data:`PRECISIONS`) selects on this machine
    beside the ``matmul`` setting: ``"float32"`` or ``"bfloat16"``.

    ``auto`` is ``bfloat16`` where it is fast and its learning was measured unchanged: oneDNN with
    native bfloat16 products (AVX-512 BF16 or AMX) and ``matmul`` not ``default``; else ``float32``.
    (push_new GC-HGG over 3 seeds reached 0.9 within the float32 runs' range, reach by iteration 10:
    ``docs/results/push_new/RUNS.md``; the update is 1.2-1.4x faster than in float32 on oneDNN:
    ``benchmarks/agent_update.py``.)

    Raises:
        ValueError: ``precision`` is not one of :data:`PRECISIONS`, or ``bfloat16`` with ``matmul="default"``
            (torch's BLAS has no bfloat16 products).
        RuntimeError: ``bfloat16`` on a CPU or torch build without native bfloat16 oneDNN products.
    """
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {list(PRECISIONS)}, got {precision!r}")
    if matmul not in MATMUL_BACKENDS:
        raise ValueError(f"matmul must be one of {list(MATMUL_BACKENDS)}, got {matmul!r}")
    if precision == "auto":
        return "bfloat16" if bf16_available() and matmul != "default" else "float32"
    if precision == "bfloat16" and not bf16_available():
        raise RuntimeError(
            "precision='bfloat16' needs oneDNN with native bfloat16 products (AVX-512 BF16 or AMX), which this "
            "CPU or torch build lacks; use precision=auto or precision=float32"
        )
    if precision == "bfloat16" and matmul == "default":
        raise ValueError("precision='bfloat16' computes the products with oneDNN, but matmul='default' "
                         "is torch's BLAS; use matmul=auto or matmul=onednn, or precision=float32")
    return precision


def cpu_capability() -> str:
    """The vector instruction set torch's CPU kernels run at here (``"AVX512"``, ``"AVX2"``, ``"DEFAULT"``, …)."""
    return torch.backends.cpu.get_cpu_capability()


@functools.cache
def cpu_vendor() -> str:
    """The CPU's vendor as ``/proc/cpuinfo`` names it (``"GenuineIntel"``, ``"AuthenticAMD"``), or ``""``
    where it cannot be read."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("vendor_id"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return ""


def resolve_matmul(matmul: str, precision: str = "float32") -> str:
    """The backend a ``matmul`` setting selects on this machine for products in ``precision`` (resolved:
    ``"float32"`` or ``"bfloat16"``, what :func:`resolve_precision` returns): ``"onednn"`` or ``"default"``.

    ``auto`` is ``"onednn"`` where this torch build has oneDNN's linear and either the products are
    bfloat16 (only oneDNN computes them) or (:func:`cpu_capability`, :func:`cpu_vendor`) is one of
    :data:`ONEDNN_FASTER`; else ``"default"`` (torch's BLAS).

    Raises:
        ValueError: ``matmul`` is not one of :data:`MATMUL_BACKENDS`, or ``precision`` is not resolved.
        RuntimeError: ``matmul="onednn"`` and this torch build has no oneDNN linear.
    """
    if matmul not in MATMUL_BACKENDS:
        raise ValueError(f"matmul must be one of {list(MATMUL_BACKENDS)}, got {matmul!r}")
    if precision not in ("float32", "bfloat16"):
        raise ValueError(f"resolve_matmul takes a resolved precision, 'float32' or 'bfloat16', got {precision!r}")
    if matmul == "default":
        return "default"
    if matmul == "onednn" and not onednn_available():
        raise RuntimeError(
            "matmul='onednn' but this torch build has no oneDNN linear (torch.ops.mkldnn._linear_pointwise); "
            "use matmul=auto (falls back to torch's BLAS) or matmul=default"
        )
    faster = precision == "bfloat16" or (cpu_capability(), cpu_vendor()) in ONEDNN_FASTER
    if matmul == "onednn" or (onednn_available() and faster):
        return "onednn"
    return "default"


def use_onednn(module: nn.Module, backend: str = "auto", min_features: int = MIN_FEATURES) -> nn.Module:
    """Set the linear layers of ``module`` to ``backend``, in place, and return ``module``.

    With ``backend`` resolving to oneDNN (:func:`resolve_matmul` for float32 products: pass the resolved
    backend for bfloat16 ones), every ``nn.Linear`` at least
    ``min_features`` wide on both sides becomes a :class:`OneDNNLinear` (its class changes; its
    parameters are the same tensors, so optimisers, target copies and state dicts are unaffected).
    With ``"default"`` every :class:`OneDNNLinear` becomes a plain ``nn.Linear`` again.
    """
    onednn = resolve_matmul(backend) == "onednn"
    for layer in module.modules():
        if onednn and type(layer) is nn.Linear and min(layer.in_features, layer.out_features) >= min_features:
            layer.__class__ = OneDNNLinear
        elif not onednn and type(layer) is OneDNNLinear:
            layer.__class__ = nn.Linear
    return module
