"""Goal metrics: the :class:`Metric` protocol every metric implements, its :class:`Lattice` view, and the
Euclidean metric."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import torch

__all__ = ["EuclideanMetric", "Lattice", "Metric"]


@runtime_checkable
class Lattice(Protocol):
    """The vertex view of a graph metric: what consumers that score many goals read instead of
    calling ``distance`` pair by pair (the curriculum's nearest-neighbour search, HGG's costs)."""

    field: tuple[tuple[float, ...], tuple[float, ...]]  # (centre, half-sizes), d values each, metres

    @property
    def vertices(self) -> torch.Tensor: ...  # float32 [V, d] vertex positions

    @property
    def resolution(self) -> float: ...  # metres: distances are rounded to this (0: exact)

    def vertex_index(self, goals: torch.Tensor) -> torch.Tensor: ...  # eq. 14; -1 off the graph

    def distance_between_vertices(self, i: torch.Tensor, j: torch.Tensor) -> torch.Tensor: ...  # checked

    def pair_distance(self, i: torch.Tensor, j: torch.Tensor) -> torch.Tensor: ...  # unchecked, for hot loops


@runtime_checkable
class Metric(Protocol):
    """A goal metric: ``distance(a, b)`` and its ``lattice``. Consumers read ``lattice`` rather than
    asking which metric they hold.

    * ``distance(a, b)``: goals ``a`` ``[..., d]`` and ``b`` ``[..., d]`` (any goal dimension d ≥ 1,
      the same for both; their batch shapes broadcast) → one distance per pair, shape the broadcast
      batch shape ``[...]``, ≥ 0, ``inf`` for "unreachable", never NaN. Return float32; the samplers
      cast any other float dtype (float64 from numpy code, say) to float32 and refuse a result of
      another shape, naming the shape expected.
    * ``lattice``: a :class:`Lattice` for a graph metric (its straight lines between vertices must
      never be longer than its distances), ``None`` for one that works on goals directly.

    A user metric is a two-member class::

        class Manhattan:
            lattice = None
            def distance(self, a, b):
                return (a - b).abs().sum(-1).float()
    """

    def distance(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor: ...

    @property
    def lattice(self) -> Lattice | None: ...


class EuclideanMetric:
    """The Euclidean goal distance ‖a − b‖, with the same interface as :class:`GoalGraph`.

    Example:
        >>> import torch
        >>> EuclideanMetric().distance(torch.zeros(2, 3), torch.tensor([3.0, 4.0, 0.0]))
        tensor([5., 5.])
    """

    lattice = None  # no vertices: distances are computed on the goals themselves

    def distance(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """Euclidean distance between goals.

        Args:
            a: goals ``[..., d]``, any dimension d ≥ 1.
            b: goals ``[..., d]``, broadcastable against ``a``.

        Returns:
            float32 ``[...]``: ‖a − b‖ (finite for finite goals; there is no field here).
        """
        a, b = torch.as_tensor(a), torch.as_tensor(b)
        if a.ndim < 1 or b.ndim < 1 or a.shape[-1] != b.shape[-1] or a.shape[-1] < 1:
            raise ValueError(
                f"EuclideanMetric.distance needs goals a [..., d] and b [..., d] with the same d >= 1, "
                f"got shapes {tuple(a.shape)} and {tuple(b.shape)}"
            )
        return torch.linalg.vector_norm(a - b, dim=-1).to(torch.float32)

    def __repr__(self) -> str:
        return "EuclideanMetric()"
