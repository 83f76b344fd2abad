"""Drawing a goal graph: a z-slice of the lattice, the obstacles with their margin, a shortest path."""

from __future__ import annotations

import numpy as np
import torch

from gchgg.graph.grid import _AXES
from gchgg.graph.lattice import GoalGraph
from gchgg.graph.metric import EuclideanMetric

__all__ = ["plot_path"]


def plot_path(graph: GoalGraph, a: torch.Tensor, b: torch.Tensor, ax=None):
    """Draw a graph slice, its obstacles and the graph path from ``a`` to ``b`` beside the straight line.

    The view plane is spanned by the axis along which ``a`` and ``b`` differ most and the axis along
    which the graph path leaves the straight line most; the free and removed vertices shown are the
    lattice slice through ``a``'s vertex, and the path is projected onto that plane.

    Args:
        graph: the graph to draw.
        a: start goal ``[3]``.
        b: end goal ``[3]``.
        ax: matplotlib axes to draw on; a new figure's axes by default.

    Returns:
        The matplotlib axes.
    """
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    a, b = torch.as_tensor(a, dtype=torch.float32), torch.as_tensor(b, dtype=torch.float32)
    path = graph.shortest_path(a, b)
    d_graph = graph.distance(a, b).item()
    d_line = EuclideanMetric().distance(a, b).item()
    main = int((b - a).abs().argmax())
    others = [k for k in range(3) if k != main]
    if len(path) > 1:
        t = ((path[:, main] - a[main]) / (b[main] - a[main])).clamp(0, 1)
        deviation = (path - (a + t[:, None] * (b - a))).abs().amax(0)
        side = max(others, key=lambda k: (deviation[k].item(), graph.high[k] - graph.low[k]))
    else:
        side = max(others, key=lambda k: graph.high[k] - graph.low[k])
    h, v = sorted((main, side))
    (depth,) = {0, 1, 2} - {h, v}
    level = round((a[depth].item() - graph.low[depth]) / graph.spacing[depth])
    level = min(max(level, 0), graph.n[depth] - 1)  # the lattice slice through a's vertex
    depth_value = graph.low[depth] + level * graph.spacing[depth]

    if ax is None:
        aspect = (graph.high[v] - graph.low[v]) / (graph.high[h] - graph.low[h])
        _, ax = plt.subplots(figsize=(5.0, min(max(5.0 * aspect, 2.5), 7.0) + 0.8))
    axes = graph.lattice_axes
    grid = np.meshgrid(axes[h].numpy(), axes[v].numpy(), indexing="ij")
    free = np.take(graph.free_mask.numpy(), level, axis=depth)  # [n_h, n_v]
    ax.scatter(grid[0][free], grid[1][free], s=4, c="0.6", lw=0, label="free vertices (slice)")
    ax.scatter(grid[0][~free], grid[1][~free], s=8, c="tab:red", marker="x", lw=0.6,
               label="removed vertices")

    def rectangle(low, high, **style):
        ax.add_patch(Rectangle((low[h], low[v]), high[h] - low[h], high[v] - low[v], **style))

    label = f"obstacle + margin {graph.margin:g} m"
    for low, high in graph.inflated_obstacles:
        if low[depth] - 1e-9 <= depth_value <= high[depth] + 1e-9:
            rectangle(low, high, fill=False, ls="--", ec="tab:red", lw=1.0, label=label)
            label = None
    label = "obstacle"
    for center, half in graph.obstacles:
        low, high = np.asarray(center) - half, np.asarray(center) + half
        if low[depth] <= depth_value <= high[depth]:
            rectangle(low, high, fc="tab:blue", alpha=0.35, ec="none", label=label)
            label = None
    rectangle(graph.low, graph.high, fill=False, ec="0.3", lw=0.8)
    ax.plot([a[h], b[h]], [a[v], b[v]], "--", c="0.2", lw=1.5, label=f"straight line: {d_line:.3f} m")
    if len(path):
        ax.plot(path[:, h], path[:, v], "-o", c="tab:green", ms=3, lw=2,
                label=f"graph path: d_G = {d_graph:.3f} m")
    ax.plot(*a[[h, v]], "o", c="black", ms=7)
    ax.plot(*b[[h, v]], "*", c="black", ms=11)
    ax.annotate("a", a[[h, v]].tolist(), xytext=(6, -10), textcoords="offset points")
    ax.annotate("b", b[[h, v]].tolist(), xytext=(6, 4), textcoords="offset points")
    ax.set_xlabel(f"{_AXES[h]} (m)")
    ax.set_ylabel(f"{_AXES[v]} (m)")
    ax.set_aspect("equal")
    projected = len(path) and (path[:, depth] - path[0, depth]).abs().max() > 1e-6
    ax.set_title(
        f"{'×'.join(map(str, graph.n))} lattice, slice {_AXES[depth]} = {depth_value:.3f} m"
        + (" (path projected)" if projected else ""),
        fontsize=10,
    )
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    return ax


def _demo_goals(geometry) -> tuple[torch.Tensor, torch.Tensor]:
    """Two goals on either side of a task's obstacle: object start and target centre.

    Tasks without an object get the corners of their target range.
    """
    if geometry.object_range is not None:
        return torch.tensor(geometry.object_range.center), torch.tensor(geometry.target_range.center)
    return torch.tensor(geometry.target_range.low), torch.tensor(geometry.target_range.high)
