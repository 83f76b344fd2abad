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


def _report(monkeypatch, tmp_path):
    """benchmarks/report.py, imported fresh, writing into a docs file under ``tmp_path``."""
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    spec = importlib.util.spec_from_file_location("_benchmark_report", BENCHMARKS / "report.py")
    report = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(report)
    monkeypatch.setattr(report, "DOCS", tmp_path / "benchmarks.md")
    monkeypatch.setattr(report, "_kind", lambda: "AVX512")
    return report


def test_docs_refused_when_a_part_went_without_its_input(monkeypatch, tmp_path, capsys):
    report = _report(monkeypatch, tmp_path)
    report.DOCS.write_text(report.HEADER + "\n## demo.py\n\nearlier run\n\n```text\nfigure A 1.0\nfigure B 2.0\n```\n")
    before = report.DOCS.read_text()

    def main():
        print("figure A 1.1")
        report.missing_input("figure B", tmp_path / "goals.npy", "record_goals.py writes it")

    monkeypatch.setattr(sys, "argv", ["demo.py", "--docs"])
    with pytest.raises(SystemExit, match=r"not written.*figure B \(.*goals\.npy is missing; record_goals\.py"):
        report.run(main, str(BENCHMARKS / "demo.py"))
    assert "figure B: skipped" in capsys.readouterr().out  # the run still says what it skipped
    assert report.DOCS.read_text() == before  # the section keeps figure B


def test_docs_written_when_every_part_ran(monkeypatch, tmp_path):
    report = _report(monkeypatch, tmp_path)
    monkeypatch.setattr(sys, "argv", ["demo.py", "--docs"])
    report.run(lambda: print("figure A 1.1"), str(BENCHMARKS / "demo.py"))
    text = report.DOCS.read_text()
    assert "## demo.py" in text and "figure A 1.1" in text


def test_docs_refused_for_a_narrowed_run(monkeypatch, tmp_path):
    report = _report(monkeypatch, tmp_path)

    def main():
        report.left_out("the other figures", "--only-a")
        print("figure A 1.1")

    monkeypatch.setattr(sys, "argv", ["demo.py", "--docs"])
    with pytest.raises(SystemExit, match=r"left out the other figures \(--only-a\)"):
        report.run(main, str(BENCHMARKS / "demo.py"))
    assert not report.DOCS.exists()
