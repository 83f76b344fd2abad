"""The layers hold: no import circle and no import up the layers (docs/import_graph.py), and the check catches both."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "docs"))
import import_graph  # noqa: E402


def test_the_project_has_no_circle_and_no_import_up_the_layers():
    done = subprocess.run([sys.executable, str(REPO / "docs" / "import_graph.py"), "--check"], capture_output=True,
                          text=True, cwd=REPO, timeout=120)
    assert done.returncode == 0, done.stdout
    assert "0 import circles; 0 imports up the layers" in done.stdout


def write(root: Path, files: dict[str, str]) -> Path:
    for name, text in files.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    (root / "envs").mkdir(exist_ok=True)
    return root


def test_a_circle_is_found_through_a_type_checking_import(tmp_path):
    root = write(tmp_path, {
        "gchgg/__init__.py": "",
        "gchgg/ddpg/__init__.py": "",
        "gchgg/ddpg/a.py": "from gchgg.ddpg import b\n",
        "gchgg/ddpg/b.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from gchgg.ddpg.a import X\n",
    })
    edges = import_graph.graph(root)
    assert edges["gchgg.ddpg.a"] == {"gchgg.ddpg.b"} and edges["gchgg.ddpg.b"] == {"gchgg.ddpg.a"}
    assert import_graph.cycles(edges) == [["gchgg.ddpg.a", "gchgg.ddpg.b"]]


@pytest.mark.parametrize("source, text, bad", [
    ("gchgg/fast/f.py", "def g():\n    from gchgg.ddpg.a import Loss\n", ("gchgg.fast.f", "gchgg.ddpg.a")),
    ("gchgg/graph/g.py", "from gchgg.run import c\n", ("gchgg.graph.g", "gchgg.run.c")),  # core -> run
    ("gchgg/hgg.py", "import envs.kuka\n", ("gchgg.hgg", "envs.kuka")),  # core -> envs, same rank
])
def test_an_import_up_the_layers_is_named(tmp_path, source, text, bad):
    root = write(tmp_path, {
        "gchgg/__init__.py": "", "gchgg/fast/__init__.py": "", "gchgg/ddpg/__init__.py": "", "gchgg/ddpg/a.py": "",
        "gchgg/run/__init__.py": "", "gchgg/run/c.py": "", "gchgg/graph/__init__.py": "", "envs/__init__.py": "",
        "envs/kuka.py": "", source: text,
    })
    edges = import_graph.graph(root)
    assert import_graph.upward(edges) == [bad]
    text, clean = import_graph.report(edges)
    assert not clean and f"{bad[0]}" in text


def test_downward_imports_are_clean(tmp_path):
    root = write(tmp_path, {
        "gchgg/__init__.py": "", "gchgg/common/__init__.py": "", "gchgg/common/files.py": "",
        "gchgg/fast/__init__.py": "", "gchgg/fast/f.py": "from gchgg.common import files\n",
        "gchgg/samplers/__init__.py": "from gchgg.samplers.s import S\n",
        "gchgg/samplers/s.py": "from gchgg.fast.f import g\nS = 1\n",
        "gchgg/run/__init__.py": "", "gchgg/run/p.py": "import envs\nfrom gchgg.samplers import S\n",
        "gchgg/analysis/__init__.py": "", "gchgg/analysis/plot.py": "from gchgg.run import p\n",
        "envs/__init__.py": "",
    })
    edges = import_graph.graph(root)
    assert edges["gchgg.run.p"] == {"envs", "gchgg.samplers"}
    assert edges["gchgg.analysis.plot"] == {"gchgg.run.p"}
    assert import_graph.cycles(edges) == [] and import_graph.upward(edges) == []
