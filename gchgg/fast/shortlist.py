"""The blocked Euclidean shortlist of F_div's nearest-neighbour search: each goal's m nearest in its window.

:class:`~gchgg.fast.nearest.NearestNeighbours` reads the metric only for the pairs this shortlist
names, and trusts it where its bound proves the best of them (see there). The shortlist itself is
integer arithmetic on one batched matrix product of squared Euclidean distances, kept in the core's
L2 cache: goals sorted along one axis are cut into blocks of ``block`` goals, and each block is
compared with itself and its ``span`` neighbouring blocks on either side (a window of
``(2·span + 1)·block`` goals).
"""

from __future__ import annotations

import math
from typing import Any

import torch

__all__ = ["Shortlist"]

_LEVEL_SLACK = 2  # levels added to every squared distance so float32 rounding never makes one negative
_INT32_MAX = 2**31 - 1
_MIN_STRIDE = 128  # the levels of narrower windows are those of a 128-wide one (see _levels)
_SWAP = torch.tensor([0, 1, 2, 4, 3])  # point columns (x, y, z, |p|², 1) -> (x, y, z, 1, |p|²), 3-D goals


class Shortlist:
    """Each goal's m straight-line nearest goals within its block window, and a lower bound on the rest.

    One batched matrix product ``[p, |p|², 1] · [-2p, 1, |p|² + 2q]ᵀ / q`` gives a window's squared
    distances in levels of q = (2·reach)² / levels (the +2 keeps float32 rounding above 0); they are
    truncated to int32 in place with the window column packed below (``key = level · W + column``),
    so ``m + 1`` value-only ``amin`` passes give each goal its m nearest goals in the window and the
    level of the next one (faster than ``topk`` here). A goal outside the shortlist is at least
    ``min(next level, gap)`` away, the gap being the distance along the sort axis to the nearest goal
    outside the window. The block layouts, the keys' scratch matrix and the product's operands are
    kept between calls (:attr:`_scratch`).

    Args:
        block: goals per block (≥ 2); batches of at most ``(2·span + 1)·block`` goals are one window.
        span: blocks on either side of a goal's block in its window (≥ 1).
    """

    def __init__(self, block: int = 32, span: int = 1) -> None:
        self.block = block
        self.span = span
        self._scratch: dict[Any, Any] = {}

    def __call__(
        self, points: torch.Tensor, m: int, repeat: torch.Tensor, axis: torch.Tensor, reach: float, tolerance: float
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """For points sorted along the axis ``[K, B, d + 3]``: each one's m nearest others in its window
        that are not ``repeat`` ones (``[K, B]``, equal to the goal sorted before them), as sorted
        positions ``[K, B, m]`` (-1 where the window has fewer candidates), and a lower bound in metres
        ``[K, B]`` on its straight-line distance to every other non-repeat goal (outside the window:
        the gap along the axis), less ``tolerance``. ``reach``: an upper bound on every point's ``|p|``."""
        k, b, size_of_point = points.shape
        dim = size_of_point - 3  # goal dimension d; columns (p, |p|², 1, id)
        layout = self._layout(b, m)
        size, pad, blocks, width, stride = (layout[key] for key in ("size", "pad", "blocks", "width", "stride"))
        levels = _levels(stride)
        # |p_i − p_j| ≤ 2·reach: no pair is above the top level, so no clamp is needed.
        quantum = max(4.0 * reach * reach, 1e-12) / levels
        left = points[..., : dim + 2]  # [p, |p|², 1]
        rows = blocks * size
        if rows != b:  # padding rows (zeros, masked below) after the sorted goals
            padded = left.new_zeros(k, rows, dim + 2)
            padded[:, :b] = left
        else:
            padded = left
        own = padded.reshape(k * blocks, size, dim + 2)
        # The right operand with its columns as rows, [K, d + 2, pad + rows + pad]: [p, |p|², 1] ->
        # [-2p, 1, |p|² + slack·q] / q for each goal, [0, 0, slack] for padding. In this layout the map and
        # the windows' copy below run along rows of goals, not along rows of d + 2 values.
        scale, shift, swap = self._product_map(quantum, dim)  # [d + 2, 1] each
        right = self._buffer("right", (k, dim + 2, rows + 2 * pad), torch.float32)
        right[..., :pad] = shift
        right[..., pad + b :] = shift
        torch.addcmul(shift, left.transpose(1, 2).index_select(1, swap), scale, out=right[..., pad : pad + b])
        windows = right.unfold(2, width, size).transpose(1, 2).reshape(k * blocks, dim + 2, width)
        squared = self._buffer("squared", (k * blocks, size, width), torch.float32)
        torch.bmm(own, windows, out=squared)  # squared distance in levels, + _LEVEL_SLACK
        # In place (same 4-byte slots, element by element: one scratch matrix, half the cache footprint).
        keys = squared.view(torch.int32)
        keys.copy_(squared)  # truncation: level + slack - 1 <= key level <= level + slack (float32 rounding < 1 level)
        # key = level · S + column (S: a power of two >= W), above every pair's key for the goal itself
        # and padding columns.
        blocked = keys.view(k, blocks, size, width)
        torch.add(layout["offset"], blocked, alpha=stride, out=blocked)
        excluded = layout["excluded"]  # the key of an excluded column: above every pair's
        if bool(repeat.any()):  # repeat columns are excluded too
            flags = repeat.new_zeros(k, rows + 2 * pad)
            flags[:, pad : pad + b] = repeat
            bump = flags.unfold(1, width, size).unsqueeze(2) * excluded  # [K, blocks, 1, W]: 0 or the excluded key
            torch.maximum(blocked, bump, out=blocked)  # an excluded key keeps its column bits
        flat, mask = keys.view(-1), stride - 1
        starts = self._row_starts(k * blocks * size, width).view(k * blocks, size, 1)  # flat index of each row
        nearest = []
        for _ in range(m):
            low = keys.amin(-1, keepdim=True)  # [K·blocks, size, 1]
            nearest.append(low)
            flat.index_fill_(0, torch.add(starts, low.bitwise_and(mask)).view(-1), _INT32_MAX)
        low = torch.cat(nearest, -1)
        cols = low.bitwise_and(mask).long().view(k, rows, m)
        cols = cols[:, :b].add_(layout["first"])  # window column -> sorted position
        cols.masked_fill_(low.view(k, rows, m)[:, :b] >= excluded[0], -1)  # the window ran out of candidates
        bound = _distance(keys.amin(-1).view(k, rows)[:, :b].bitwise_right_shift_(stride.bit_length() - 1), quantum)
        # Goals outside the window are at least the gap along the axis away (``axis``: +inf for repeats).
        ends = torch.cat([axis.new_full((k, 1), -math.inf), axis, axis.new_full((k, 1), math.inf)], 1)
        gap = torch.minimum(axis - ends[:, layout["before"]], ends[:, layout["after"]] - axis).masked_fill_(repeat, 0.0)
        return cols, torch.minimum(bound, gap).sub_(tolerance).clamp_(min=0.0)

    def _layout(self, b: int, m: int) -> dict[str, Any]:
        """Block geometry for B goals, kept per (B, m): block size, padding, number of blocks, window
        width, the keys' column numbers, the mask of excluded keys (a goal itself, padding), each
        sorted position's first window position, and its nearest goals outside the window (indices
        into the axis values with -inf / +inf put at both ends)."""
        cached = self._scratch.get(("layout", b, m))
        if cached is not None:
            return cached
        size, span = self.block, self.span
        if b > (2 * span + 1) * size and size > m:
            pad, blocks, width = span * size, -(-b // size), (2 * span + 1) * size
        else:  # one window holds every goal
            size, pad, blocks, width = b, 0, 1, b
        block = torch.arange(blocks).view(blocks, 1, 1)
        row = torch.arange(size).view(1, size, 1)
        column = torch.arange(width).view(1, 1, width)
        padded = block * size + column  # padded position of each window column
        excluded = (padded < pad) | (padded >= pad + b) | (column == row + pad)
        # Keys are level · S + offset. A pair's level is at most levels + slack, so its key is below
        # (levels + slack + 1) · S; excluded entries (level <= slack + 1: the goal itself, padding) get
        # (levels + 2·slack + 2) · S more, which keeps them above every pair and below int32 max.
        stride = 1 << (width - 1).bit_length()
        exclusion = (_levels(stride) + 2 * _LEVEL_SLACK + 2) * stride
        offset = column.expand(blocks, size, width) + excluded * exclusion
        position = torch.arange(b)
        start = (position // size) * size - pad  # sorted position of the window's first column
        if pad:
            before = (start - 1).clamp(min=-1) + 1
            after = torch.where(start + width < b, start + width + 1, b + 1)
        else:
            before, after = torch.zeros(b, dtype=torch.long), torch.full((b,), b + 1)
        layout = self._scratch[("layout", b, m)] = {
            "size": size,
            "pad": pad,
            "blocks": blocks,
            "width": width,
            "stride": stride,
            "offset": offset.to(torch.int32).contiguous(),
            "excluded": (exclusion + column.view(width)).to(torch.int32),  # an excluded column's key
            "first": start.view(1, b, 1),
            "before": before,
            "after": after,
        }
        return layout

    def _row_starts(self, rows: int, width: int) -> torch.Tensor:
        """Flat index of the first key of each of ``rows`` rows of ``width`` keys (kept per shape)."""
        cached = self._scratch.get(("starts", rows, width))
        if cached is None:
            cached = self._scratch[("starts", rows, width)] = torch.arange(0, rows * width, width)
        return cached

    def _product_map(self, quantum: float, dim: int = 3) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``scale, shift, swap`` with ``[p, |p|², 1][swap] · scale + shift = [-2p, 1, |p|² + slack·q] / q``
        for ``dim``-D points, ``scale`` and ``shift`` as columns ``[d + 2, 1]`` (kept per quantum and dimension)."""
        cached = self._scratch.get("map")
        if cached is None or cached[0] != (quantum, dim):
            scale = (torch.tensor([-2.0] * dim + [1.0, 1.0]) / quantum).unsqueeze(-1)
            shift = torch.tensor([0.0] * (dim + 1) + [float(_LEVEL_SLACK)]).unsqueeze(-1)
            swap = _SWAP if dim == 3 else torch.tensor([*range(dim), dim + 1, dim])
            cached = self._scratch["map"] = ((quantum, dim), (scale, shift, swap))
        return cached[1]

    def _buffer(self, name: str, shape: tuple[int, ...], dtype: torch.dtype) -> torch.Tensor:
        """A scratch tensor of this shape and dtype, kept per name (allocated again when the shape changes)."""
        buffer = self._scratch.get(name)
        if buffer is None or buffer.shape != shape:
            buffer = self._scratch[name] = torch.empty(shape, dtype=dtype)
        return buffer


def _levels(stride: int) -> int:
    """Squared-distance levels for keys ``level · stride + column`` (room is left for excluded entries).

    At most ~2**24 (what a stride of 128 gives): a float32 product holds levels exactly only up to
    there, and beyond it the rounding of a goal's distance to itself could exceed the room left for
    excluded entries (narrow windows, stride < 128, would otherwise get up to 2**28 levels)."""
    return _INT32_MAX // max(stride, _MIN_STRIDE) - 4 * _LEVEL_SLACK - 4


def _distance(level: torch.Tensor, quantum: float) -> torch.Tensor:
    """A lower bound in metres on the distance of a pair whose key has this level: the level less the
    slack and one more for float32 rounding (at least 0), times the quantum, square-rooted."""
    return (level - (_LEVEL_SLACK + 1)).clamp_(min=0).float().mul_(quantum).sqrt_()
