"""Subnormal floats flushed to zero in the DDPG update: the speed device for Adam's decayed moments.

A ReLU unit that stops firing gets a zero gradient from then on, and Adam's moment estimates of its
weights decay geometrically (the first by β₁ = 0.9 per step, the second by β₂ = 0.999). After hundreds
(the first) or tens of thousands (the second) of steps they pass through float32's subnormal range,
below the smallest normal number (``torch.finfo(torch.float32).tiny``), where an x86 core computes each
operation in microcode, many times slower than in its vector units. A long run
holds many such entries at any time, and its Adam steps slow down with them:
``python benchmarks/subnormals.py --run <run folder>`` prints a run's share of subnormal moments and its
updates with and without them.

:func:`flush_subnormals` turns on the CPU's flush-to-zero and denormals-are-zero modes
(:func:`torch.set_flush_denormal`) for a block: a subnormal result becomes 0, and a subnormal input
counts as 0. The agent wraps its update in it (``subnormals=flush``, what the default ``auto`` resolves to).
What it changes are values that small: a decayed moment m becomes 0, where it would have moved a weight by at most
lr·m/ε (ε: Adam's epsilon), far below the rounding unit of any weight that is not itself nearly 0. The
networks therefore come out the same, bit for bit, as without it (``tests/test_subnormal.py`` checks
this over updates on moments made subnormal; the benchmark over a run's own updates). Acting,
evaluation, the physics and the samplers run outside the block, unchanged.

The modes belong to the calling thread: with ``threads > 1`` torch's worker threads keep subnormals.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterable, Iterator

import torch

__all__ = ["SUBNORMALS", "flush_subnormals", "flushing", "subnormal_share"]

SUBNORMALS = ("auto", "flush", "keep")
"""The ``subnormals`` setting: ``flush`` the update's subnormal results and inputs to zero, or ``keep`` them
(IEEE arithmetic throughout); ``auto`` (the default) is ``flush`` wherever the agent runs its speed devices
and ``keep`` on its plain path (:class:`gchgg.ddpg.agent.DDPGAgent`'s ``fast=False``)."""

_SMALLEST = 5e-324  # the smallest subnormal double: 0 once denormals-are-zero is on


def flushing() -> bool:
    """Whether the calling thread flushes subnormals to zero now (the CPU's denormals-are-zero mode).

    >>> flushing()
    False
    >>> with flush_subnormals():
    ...     flushing()
    True
    """
    smallest = _SMALLEST  # a name, not a literal product, so that the multiply runs here and not at compile time
    return smallest * 1.0 == 0.0


@contextlib.contextmanager
def flush_subnormals(on: bool = True) -> Iterator[None]:
    """Within the block, the calling thread flushes subnormal floats to zero (``on``; ``False``: a no-op);
    after it, the mode the thread had before. Where the CPU has no such mode
    (:func:`torch.set_flush_denormal` returns ``False``) the block runs unchanged.

    >>> tiny = torch.tensor([1e-39])  # subnormal in float32
    >>> with flush_subnormals():
    ...     float(tiny * 1.0)
    0.0
    >>> float(tiny * 1.0) > 0
    True
    """
    if not on or flushing():
        yield
        return
    supported = torch.set_flush_denormal(True)
    try:
        yield
    finally:
        if supported:
            torch.set_flush_denormal(False)


def subnormal_share(tensors: Iterable[torch.Tensor]) -> float:
    """The fraction of the entries of floating-point ``tensors`` that are subnormal (non-zero and smaller in
    magnitude than their dtype's smallest normal number); 0.0 for no entries.

    >>> subnormal_share([torch.tensor([1e-39, 0.0, 1.0, -1e-40])])
    0.5
    """
    subnormal = total = 0
    for x in tensors:
        tiny = torch.finfo(x.dtype).tiny
        subnormal += int(((x != 0) & (x.abs() < tiny)).sum())
        total += x.numel()
    return subnormal / total if total else 0.0
