"""Replay-buffer samplers for goal-conditioned TorchRL pipelines: EBP, graph curriculum (Alg. 1), CHER, λ schedules."""

from gchgg.fast.nearest import NearestNeighbours, nearest_neighbour_distances
from gchgg.samplers.cher import CherSampler
from gchgg.samplers.curriculum import GraphCurriculumSampler
from gchgg.samplers.energy import EnergySampler
from gchgg.samplers.tradeoff import AdaptiveTradeoff, ExponentialTradeoff, FixedTradeoff, Tradeoff, as_tradeoff

__all__ = [
    "AdaptiveTradeoff",
    "CherSampler",
    "EnergySampler",
    "ExponentialTradeoff",
    "FixedTradeoff",
    "GraphCurriculumSampler",
    "Tradeoff",
    "as_tradeoff",
    "NearestNeighbours",
    "nearest_neighbour_distances",
]
