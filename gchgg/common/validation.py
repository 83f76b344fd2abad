"""Checks of settings and arguments: one helper for numbers in a range, one for choices, one for a metric's distances.

Every error names the setting, the bad value and what is allowed, e.g.
``ValueError: train.episodes must be an integer > 0, got 0``; NaN and ±inf are refused unless
``finite=False``; ``bool`` is never taken for a number.

>>> check_number("agent.gamma", 0.9, low=0, high=1)
0.9
>>> check_number("train.episodes", 0, integer=True, low=0, low_open=True)
Traceback (most recent call last):
...
ValueError: train.episodes must be an integer > 0, got 0
>>> check_choice("curriculum.scale", "z", ("raw", "standardized"))
Traceback (most recent call last):
...
ValueError: curriculum.scale must be one of 'raw', 'standardized', got 'z'
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from typing import Any

import torch

__all__ = ["check_choice", "check_distances", "check_number"]


def _bound(x: float) -> str:
    return f"{x:g}"


def _allowed(low, high, low_open: bool, high_open: bool) -> str:
    if low is not None and high is not None:
        return f"in {'(' if low_open else '['}{_bound(low)}, {_bound(high)}{')' if high_open else ']'}"
    if low is not None:
        return f"{'>' if low_open else '>='} {_bound(low)}"
    if high is not None:
        return f"{'<' if high_open else '<='} {_bound(high)}"
    return "finite"


def check_number(
    name: str,
    value: Any,
    *,
    integer: bool = False,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    high_open: bool = False,
    finite: bool = True,
):
    """``value`` if it is a number (an integer with ``integer``) within the bounds, else a ``ValueError``.

    Args:
        name: the setting's name, as the user writes it (``"train.episodes"``).
        value: the value to check; returned unchanged.
        integer: require an integer.
        low, high: bounds (``None``: unbounded); ``low_open`` / ``high_open`` exclude them.
        finite: refuse NaN and ±inf (default).
    """
    kind = "an integer" if integer else "a number"
    number = numbers.Integral if integer else numbers.Real
    ok = isinstance(value, number) and not isinstance(value, bool)
    if ok and finite and not math.isfinite(value):
        ok = False
    if ok and low is not None and (value <= low if low_open else value < low):
        ok = False
    if ok and high is not None and (value >= high if high_open else value > high):
        ok = False
    if not ok:
        raise ValueError(f"{name} must be {kind} {_allowed(low, high, low_open, high_open)}, got {value!r}")
    return value


def check_choice(name: str, value: Any, allowed: Sequence[Any]) -> Any:
    """``value`` if it is one of ``allowed``, else a ``ValueError`` listing them."""
    if value not in allowed:
        raise ValueError(f"{name} must be one of {', '.join(map(repr, allowed))}, got {value!r}")
    return value


def check_distances(distance: Any, name: str, shape: torch.Size | tuple | None = None) -> torch.Tensor:
    """``distance`` as a float32 tensor (a metric returning another dtype, e.g. float64, is cast); a
    ``ValueError`` naming the metric (``name``) if it holds NaN or, when ``shape`` is given, has another shape.

    The samplers' check of what a metric returns, on their plain paths and in the nearest-neighbour engine alike.
    """
    distance = torch.as_tensor(distance)
    if shape is not None and distance.shape != torch.Size(shape):
        raise ValueError(
            f"the {name} must return one distance per pair of goals, shape {tuple(shape)} here "
            f"(goals [..., d] -> [...]), got shape {tuple(distance.shape)}"
        )
    if distance.dtype != torch.float32:
        distance = distance.to(torch.float32)
    if bool(torch.isnan(distance).any()):
        raise ValueError(f"the {name} returned NaN distances; goals must be finite")
    return distance
