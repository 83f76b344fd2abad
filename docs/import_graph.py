"""The project's import graph by layer: prints it, checks it (no circle, no import up the layers) and draws it.

    python docs/import_graph.py                 # the layers, each module's imports, and any fault
    python docs/import_graph.py --check         # exit status 1 on a circle or an import up the layers
    python docs/import_graph.py --png FILE      # the picture in docs/architecture.md

The layers, lowest first (``docs/architecture.md``): ``common`` (checks, atomic files), ``fast``
(speed devices), the algorithm (``core``: graph, transforms, samplers, hgg, ddpg) beside the
simulation (``envs``), ``run`` (the machinery and ``gchgg.train``; a package's ``__main__`` is a
command line and counts here) and ``analysis``. A module may import from a lower layer and from its
own; ``core`` and ``envs`` share a rank but not a layer, so neither imports the other.

Imports are read from the source with :mod:`ast` (nothing is imported), those under
``if TYPE_CHECKING:`` included: an annotation's import runs no code, but it is a dependency a reader
follows, so it obeys the same rules. ``--root`` reads
another checkout, and ``--moved`` places an old flat layout's modules by where they live now
(``gchgg.common.moved.MOVED``), which draws the "before" picture.
"""

from __future__ import annotations

import argparse
import ast
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("gchgg", "envs")

RANKS = {"common": 0, "fast": 1, "core": 2, "envs": 2, "run": 3, "analysis": 4}
"""Layer -> rank: an import must go to a lower rank, or stay inside its own layer."""

_CORE = ("gchgg.graph", "gchgg.transforms", "gchgg.samplers", "gchgg.hgg", "gchgg.ddpg")


def layer(module: str) -> str:
    """The layer of a dotted module name in the layered layout."""
    if module.endswith(".__main__") or module == "gchgg.train":
        return "run"
    if module.split(".")[0] == "envs":
        return "envs"
    for name in ("common", "fast", "run", "analysis"):
        if module == f"gchgg.{name}" or module.startswith(f"gchgg.{name}."):
            return name
    if module == "gchgg" or any(module == c or module.startswith(c + ".") for c in _CORE):
        return "core"
    raise ValueError(f"module {module!r} is in no layer: place it in one of {sorted(RANKS)} (docs/architecture.md)")


def modules(root: Path) -> dict[str, Path]:
    """Dotted name -> file, for every module of the project's packages under ``root``."""
    found = {}
    for package in PACKAGES:
        for path in sorted((root / package).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            found[".".join(parts)] = path
    return found


def imports_of(name: str, path: Path, known: set[str]) -> set[str]:
    """The project modules ``name`` imports, at any depth of its code (functions, TYPE_CHECKING blocks)."""
    tree = ast.parse(path.read_text(), str(path))
    is_package = path.name == "__init__.py"
    base = name if is_package else name.rpartition(".")[0]
    targets: set[str] = set()

    def resolve(module: str) -> str | None:  # the longest known prefix: ``gchgg.graph.lattice.X`` -> the module
        while module and module not in known:
            module = module.rpartition(".")[0]
        return module or None

    def visit(node: ast.AST) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.Import):
                targets.update(filter(None, (resolve(alias.name) for alias in child.names)))
            elif isinstance(child, ast.ImportFrom):
                source = child.module or ""
                if child.level:
                    anchor = base.split(".")[: len(base.split(".")) - (child.level - 1)]
                    source = ".".join(anchor + ([source] if source else []))
                for alias in child.names:  # ``from gchgg.run import config`` imports gchgg.run.config
                    target = resolve(f"{source}.{alias.name}") if f"{source}.{alias.name}" in known else resolve(source)
                    if target:
                        targets.add(target)
            visit(child)

    visit(tree)
    targets.discard(name)
    return targets


def graph(root: Path) -> dict[str, set[str]]:
    """Module -> the project modules it imports; a package's own ``__init__`` is not counted as imported by its
    submodules (Python runs it first, but a submodule does not depend on what it re-exports)."""
    found = modules(root)
    known = set(found)
    return {name: {t for t in imports_of(name, path, known) if not name.startswith(t + ".")}
            for name, path in found.items()}


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The import circles: strongly connected components of more than one module (Tarjan), each sorted."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []
    counter = [0]

    def strong(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in edges.get(v, ()):
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    sys.setrecursionlimit(max(10_000, sys.getrecursionlimit()))
    for v in sorted(edges):
        if v not in index:
            strong(v)
    return sorted(found)


def upward(edges: dict[str, set[str]], place=layer) -> list[tuple[str, str]]:
    """Imports that break the layering: to a higher rank, or across layers of the same rank."""
    bad = []
    for source, targets in sorted(edges.items()):
        for target in sorted(targets):
            a, b = place(source), place(target)
            if a != b and RANKS[b] >= RANKS[a]:
                bad.append((source, target))
    return bad


def levels(edges: dict[str, set[str]]) -> dict[str, int]:
    """Each module's depth: 0 for a module importing no project module, else 1 + its imports' deepest
    (modules in a circle share the circle's depth)."""
    depth: dict[str, int] = {}
    in_cycle = {m: tuple(c) for c in cycles(edges) for m in c}

    def visit(v: str, seen: frozenset) -> int:
        if v in depth:
            return depth[v]
        below = [visit(w, seen | {v}) for w in edges.get(v, ())
                 if w not in seen and in_cycle.get(w) != in_cycle.get(v, ())]
        depth[v] = 1 + max(below) if below else 0
        return depth[v]

    for v in sorted(edges):
        visit(v, frozenset())
    return depth


def draw(edges: dict[str, set[str]], place, out: Path, title: str) -> None:
    """A picture of the graph: one column per layer, modules by depth, bad imports in red."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    order = ["common", "fast", "core", "envs", "run", "analysis"]
    bad = set(upward(edges, place)) | {(a, b) for c in cycles(edges) for a in c for b in edges[a] if b in c}
    columns: dict[str, list[str]] = {name: [] for name in order}
    for module in sorted(edges):
        columns[place(module)].append(module)
    height = max(len(v) for v in columns.values())
    position = {m: (order.index(name), height - i) for name, ms in columns.items() for i, m in enumerate(ms)}
    fig, ax = plt.subplots(figsize=(3.2 * len(order), 0.28 * height + 1.5))
    for source, targets in edges.items():
        for target in targets:
            (x0, y0), (x1, y1) = position[source], position[target]
            red = (source, target) in bad
            ax.annotate("", xy=(x1, y1), xytext=(x0, y0), arrowprops=dict(
                arrowstyle="->", lw=1.2 if red else 0.4, color="red" if red else "0.7", alpha=0.9 if red else 0.5,
                connectionstyle="arc3,rad=0.15"))
    for module, (x, y) in position.items():
        ax.text(x, y, module.replace("gchgg.", ""), ha="center", va="center", fontsize=6.5,
                bbox=dict(boxstyle="round,pad=0.2", fc="white", ec="0.5", lw=0.5))
    for i, name in enumerate(order):
        ax.text(i, height + 1.2, name, ha="center", fontsize=10, weight="bold")
    ax.set_xlim(-0.7, len(order) - 0.3)
    ax.set_ylim(0, height + 2)
    ax.axis("off")
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def report(edges: dict[str, set[str]], place=layer) -> tuple[str, bool]:
    """The printed summary and whether the graph is clean."""
    circles, bad, depth = cycles(edges), upward(edges, place), levels(edges)
    lines = [f"{len(edges)} modules on {max(depth.values()) + 1} levels; {len(circles)} import circles; "
             f"{len(bad)} imports up the layers"]
    for name in ("common", "fast", "core", "envs", "run", "analysis"):
        members = sorted(m for m in edges if place(m) == name)
        lines.append(f"{name} ({len(members)}): " + ", ".join(m for m in members))
    lines += [f"circle: {' <-> '.join(c)}" for c in circles]
    lines += [f"up the layers: {a} ({place(a)}) imports {b} ({place(b)})" for a, b in bad]
    return "\n".join(lines), not circles and not bad


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, default=REPO, help="the checkout to read (default: this one)")
    parser.add_argument("--moved", action="store_true", help="place modules of the old flat layout by their new home")
    parser.add_argument("--check", action="store_true", help="exit 1 on a circle or an import up the layers")
    parser.add_argument("--png", type=Path, help="draw the graph to this file")
    parser.add_argument("--title", default="import graph")
    args = parser.parse_args(argv)
    edges = graph(args.root)
    place = layer
    if args.moved:
        sys.path.insert(0, str(REPO))
        from gchgg.common.moved import MOVED

        def place(module: str) -> str:
            return layer(MOVED.get(module, module))
    text, clean = report(edges, place)
    print(text)
    if args.png:
        draw(edges, place, args.png, args.title)
        print(f"wrote {args.png}")
    return 0 if clean or not args.check else 1


if __name__ == "__main__":
    sys.exit(main())
