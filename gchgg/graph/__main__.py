"""``python -m gchgg.graph TASK --out FILE``: draw a task's goal graph and one shortest path."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

from gchgg.graph.lattice import DEFAULT_MARGIN, DEFAULT_N, USER_CACHE_DIR, GoalGraph
from gchgg.graph.metric import EuclideanMetric
from gchgg.graph.plot import _demo_goals, plot_path


def main(argv: Sequence[str] | None = None) -> None:
    """``python -m gchgg.graph <task> --out FILE.png``: draw a task's graph and one shortest path."""
    from envs.geometry import TASKS, geometry

    parser = argparse.ArgumentParser(
        prog="python -m gchgg.graph",
        description="Draw a task's goal-space graph, its obstacles and one shortest path.",
    )
    parser.add_argument("task", choices=TASKS)
    parser.add_argument("--out", type=Path, required=True, help="PNG file to write")
    parser.add_argument("--n", type=int, nargs=3, default=DEFAULT_N, metavar=("NX", "NY", "NZ"))
    parser.add_argument("--margin", type=float, default=DEFAULT_MARGIN,
                        help="obstacle safety margin in metres")
    parser.add_argument("--cache-dir", type=Path, default=None,
                        help="distance-table cache folder (default: the per-user cache)")
    args = parser.parse_args(argv)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    task = geometry(args.task)
    graph = GoalGraph(task.field, task.obstacles, args.n, args.margin,
                      cache_dir=args.cache_dir if args.cache_dir is not None else USER_CACHE_DIR)
    a, b = _demo_goals(task)
    ax = plot_path(graph, a, b)
    ax.set_title(f"{args.task}: {ax.get_title()}", fontsize=10)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    ax.figure.savefig(args.out, dpi=110, bbox_inches="tight")
    plt.close(ax.figure)
    print(f"{args.task}: d_G = {graph.distance(a, b).item():.4f} m, "
          f"Euclidean = {EuclideanMetric().distance(a, b).item():.4f} m -> {args.out}")


if __name__ == "__main__":
    main()
