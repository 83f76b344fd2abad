"""The benchmark scripts still import: each loads (its imports from the project resolve) and has a main().

They are scripts, not tests (README: benchmarks print their figures), so nothing here runs them; but a
rename in the project must not leave one failing at its first line, as benchmarks/linear.py once did.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
SCRIPTS = sorted(p for p in BENCHMARKS.glob("*.py") if p.name != "report.py")  # report.py: their shared printer


@pytest.mark.parametrize("script", SCRIPTS, ids=[p.stem for p in SCRIPTS])
def test_each_benchmark_imports_and_has_a_main(script, monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))  # they import each other (iteration.py: agent_update, report)
    name = f"_benchmark_{script.stem}"
    spec = importlib.util.spec_from_file_location(name, script)
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, name, module)
    spec.loader.exec_module(module)  # runs its imports, not its main (that is under __name__ == "__main__")
    assert callable(getattr(module, "main", None)), f"{script.name} has no main()"
