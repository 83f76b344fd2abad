"""One linear layer on torch's BLAS against oneDNN (:mod:`gchgg.fast.linear`), per layer shape and batch size.

For the agent's three kinds of layer (input 31 → 256, hidden 256 → 256, output 256 → 3) and batch
sizes from one row (acting in one env) to 256 (an update), prints the microseconds of the forward
product ``x·Wᵀ + b``, of the input gradient ``∂y·W`` and of the weight gradient ``∂yᵀ·x``, each on
torch's BLAS (``F.linear`` / ``mm``, MKL on x86) and on oneDNN, and their ratio (> 1: oneDNN
faster). Both are timed in alternating rounds of one run, the ratio is the median of the rounds'.
These figures choose :data:`gchgg.fast.linear.MIN_BATCH` and :data:`gchgg.fast.linear.MIN_FEATURES`.

Where oneDNN computes bfloat16 natively, it then times the backward's two products in bfloat16 at
batch 256 as :func:`gchgg.fast.linear.onednn_linear` computes them on the transposed views (it copies each
transposed operand contiguous first) against :func:`gchgg.fast.linear.onednn_mm` (``torch.mm``: oneDNN's
matmul on the strided operands), whether the two give the same values, and their ratio (< 1:
``onednn_mm`` faster).

    python benchmarks/linear.py [--threads 1] [--rounds 7] [--calls 200]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from functools import partial

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # run from a checkout

import torch
import torch.nn.functional as F

from gchgg.fast.linear import MIN_BATCH, MIN_FEATURES, bf16_available, onednn_available, onednn_linear, onednn_mm

SHAPES = ((31, 256), (256, 256), (256, 3))  # (in, out): the input, hidden and output layers
BATCHES = (1, 8, 16, 32, 64, 256)


def _time(fn, calls: int) -> float:
    start = time.perf_counter()
    for _ in range(calls):
        fn()
    return (time.perf_counter() - start) / calls


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=1, help="torch.set_num_threads (default 1, as the runs)")
    parser.add_argument("--rounds", type=int, default=7, help="alternating timing rounds")
    parser.add_argument("--calls", type=int, default=200, help="calls per round and implementation")
    args = parser.parse_args()
    if not onednn_available():
        print("this torch build has no oneDNN linear (torch.ops.mkldnn._linear_pointwise): nothing to compare")
        return
    torch.set_num_threads(args.threads)
    generator = torch.Generator().manual_seed(0)
    print(f"threads={args.threads} rounds={args.rounds}x{args.calls} calls; microseconds per call, torch BLAS | "
          f"oneDNN | ratio (MIN_BATCH={MIN_BATCH}, MIN_FEATURES={MIN_FEATURES})")
    print(f"{'in→out':>9} {'batch':>5}  {'forward x·Wᵀ+b':>24}  {'input grad ∂y·W':>24}  {'weight grad ∂yᵀ·x':>24}")
    for n_in, n_out in SHAPES:
        weight = torch.randn(n_out, n_in, generator=generator)
        bias = torch.randn(n_out, generator=generator)
        for batch in BATCHES:
            x = torch.randn(batch, n_in, generator=generator)
            grad_y = torch.randn(batch, n_out, generator=generator)
            pairs = (
                (partial(F.linear, x, weight, bias), partial(onednn_linear, x, weight, bias)),
                (partial(torch.mm, grad_y, weight), partial(onednn_linear, grad_y, weight.t(), None)),
                (partial(torch.mm, grad_y.t(), x), partial(onednn_linear, grad_y.t(), x.t(), None)),
            )
            cells = []
            for blas, onednn in pairs:
                t_blas, t_dnn, ratio = _alternate(blas, onednn, args.rounds, args.calls)
                cells.append(f"{t_blas * 1e6:7.1f} | {t_dnn * 1e6:7.1f} | {ratio:4.2f}")
            print(f"{n_in:>4}→{n_out:<4} {batch:>5}  " + "  ".join(f"{c:>24}" for c in cells))
    if bf16_available():
        bf16_backward(generator, args.rounds, args.calls)


def _alternate(first, second, rounds: int, calls: int) -> tuple[float, float, float]:
    """Median seconds per call of ``first`` and ``second``, timed in alternating rounds, and the median
    of the rounds' ratios first / second."""
    _time(first, 10), _time(second, 10)  # warm-up
    t_first, t_second = [], []
    for r in range(rounds):
        for fn, times in ((first, t_first), (second, t_second))[:: 1 if r % 2 else -1]:
            times.append(_time(fn, calls))
    ratio = statistics.median(a / b for a, b in zip(t_first, t_second, strict=True))
    return statistics.median(t_first), statistics.median(t_second), ratio


def bf16_backward(generator: torch.Generator, rounds: int, calls: int, batch: int = 256) -> None:
    """The backward's bfloat16 products at ``batch`` rows: oneDNN's linear on transposed views against
    :func:`onednn_mm`."""
    print(f"bfloat16 backward products, batch {batch}; microseconds per call, onednn_linear on the transposed "
          "views | onednn_mm | ratio (same values)")
    print(f"{'in→out':>9}  {'input grad ∂y·W':>30}  {'weight grad ∂yᵀ·x':>30}")
    for n_in, n_out in SHAPES[:2]:  # the layers oneDNN computes (the output layer is narrower than MIN_FEATURES)
        weight = torch.randn(n_out, n_in, generator=generator).bfloat16()
        x = torch.randn(batch, n_in, generator=generator).bfloat16()
        grad_y = torch.randn(batch, n_out, generator=generator).bfloat16()
        pairs = (
            (partial(onednn_linear, grad_y, weight.t(), None), partial(onednn_mm, grad_y, weight)),
            (partial(onednn_linear, grad_y.t(), x.t(), None), partial(onednn_mm, grad_y.t(), x)),
        )
        cells = []
        for views, mm in pairs:
            t_mm, t_views, ratio = _alternate(mm, views, rounds, calls)
            same = torch.equal(views(), mm())
            cells.append(f"{t_views * 1e6:7.1f} | {t_mm * 1e6:7.1f} | {ratio:4.2f} ({same})")
        print(f"{n_in:>4}→{n_out:<4}  " + "  ".join(f"{c:>30}" for c in cells))


if __name__ == "__main__":
    from report import run  # prints, and with --docs writes docs/benchmarks.md

    run(main, __file__)
