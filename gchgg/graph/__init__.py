"""Obstacle-aware goal-space graph and its shortest-path distance d_G (Sec. III-C, IV-B, eqs. 8–14).

- :mod:`gchgg.graph.metric`: the :class:`Metric` protocol (``distance`` and ``lattice``), the
  :class:`Lattice` view a graph gives of its vertices, and :class:`EuclideanMetric`;
- :mod:`gchgg.graph.lattice`: :class:`GoalGraph`, goals to vertices (eq. 14) and d_G from its table
  (eq. 13);
- :mod:`gchgg.graph.grid`: the lattice it is built on (eqs. 9–12: vertices, obstacle removal,
  26-connectivity) and :func:`check_density_criterion`;
- :mod:`gchgg.graph.table`: the all-pairs distance table (Dijkstra, int16) and its disk cache
  (:func:`default_cache_dir`);
- :mod:`gchgg.graph.plot`: :func:`plot_path`; ``python -m gchgg.graph push_new --out graph.png``
  draws a task's graph and one shortest path.
"""

from gchgg.graph.lattice import (
    DEFAULT_MARGIN,
    DEFAULT_N,
    USER_CACHE_DIR,
    GoalGraph,
    check_density_criterion,
    default_cache_dir,
)
from gchgg.graph.metric import EuclideanMetric, Lattice, Metric
from gchgg.graph.plot import plot_path

__all__ = [
    "DEFAULT_MARGIN",
    "DEFAULT_N",
    "EuclideanMetric",
    "GoalGraph",
    "Lattice",
    "Metric",
    "USER_CACHE_DIR",
    "check_density_criterion",
    "default_cache_dir",
    "plot_path",
]
