"""Modules that moved in the layered layout, importable (and runnable with ``python -m``) under their old names.

``import gchgg.agent`` gives the module object of :mod:`gchgg.ddpg.agent` itself, not a copy, so
checkpoints pickled before the move, users' imports and the commands in older run records keep
working. Each old name is answered by :class:`MovedModuleFinder`, installed by ``gchgg/__init__.py``.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys

MOVED = {
    "gchgg.validation": "gchgg.common.validation",
    "gchgg.adam_step": "gchgg.fast.adam_step",
    "gchgg.fused_update": "gchgg.fast.fused_update",
    "gchgg.linear": "gchgg.fast.linear",
    "gchgg.samplers.nearest": "gchgg.fast.nearest",
    "gchgg.storage": "gchgg.fast.storage",
    "gchgg.subnormal": "gchgg.fast.subnormal",
    "gchgg.agent": "gchgg.ddpg.agent",
    **{f"gchgg.{name}": f"gchgg.run.{name}" for name in (
        "builders", "checkpoint", "config", "evaluator", "fork", "loggers", "metrics", "parts", "replay_log",
        "rollout", "run_info")},
    **{f"gchgg.{name}": f"gchgg.analysis.{name}" for name in ("claims", "evaluate", "export", "plot", "stats")},
}
"""Old dotted name -> the module's name in the layered layout."""


class _Alias(importlib.abc.Loader):
    """Loads an old name as the new module object; ``python -m <old name>`` runs the new module's code."""

    def __init__(self, new: str):
        self.new = new

    def create_module(self, spec):
        return importlib.import_module(self.new)

    def exec_module(self, module) -> None:  # the new module is already executed
        pass

    def get_code(self, fullname: str):  # runpy, for ``python -m gchgg.plot``
        return importlib.util.find_spec(self.new).loader.get_code(self.new)


class MovedModuleFinder(importlib.abc.MetaPathFinder):
    """A meta-path finder that answers only the names in :data:`MOVED`."""

    def find_spec(self, fullname, path=None, target=None):
        new = MOVED.get(fullname)
        if new is None:
            return None
        origin = importlib.util.find_spec(new).origin  # runpy's __file__ for the module run as __main__
        return importlib.util.spec_from_loader(fullname, _Alias(new), origin=origin)


def install() -> None:
    """Put one :class:`MovedModuleFinder` on ``sys.meta_path`` (again: nothing)."""
    if not any(isinstance(finder, MovedModuleFinder) for finder in sys.meta_path):
        sys.meta_path.append(MovedModuleFinder())
