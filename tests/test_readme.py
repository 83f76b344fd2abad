"""The README says what is true: its Python block runs, the commands it names exist, its results block is what
the claims' generator writes today, the speed figures it quotes are what the named scripts print into the files
it names, its links point at files, and it stays a page a newcomer reads in five minutes."""

from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import pytest

from gchgg.analysis import claims

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
TEXT = README.read_text()
BLOCKS = re.findall(r"```python\n(.*?)```", TEXT, flags=re.S)
PROSE = re.sub(r"\s+", " ", TEXT)  # commands wrapped over lines read as one
ROUNDS_COMMAND = ("docs/iteration_rounds.py", "docs/benchmark_logs/459565c.txt",
                  "docs/benchmark_logs/7b9aaa8-replication.txt", "docs/benchmark_logs/1c92d3a-replication.txt")


def test_the_readme_is_short_and_opens_with_the_two_commands_ci_runs():
    assert len(TEXT.splitlines()) <= 200, "README.md is over 200 lines: move the detail into docs/"
    first_block = re.search(r"```bash\n(.*?)```", TEXT, flags=re.S).group(1).splitlines()
    assert first_block == ['pip install -e ".[test]" && python -m gchgg.train env=push_new algo=gchgg', "pytest"]
    ci = (REPO / ".ci/run").read_text().splitlines()
    assert 'pip install -e ".[test]"' in ci and "pytest" in ci, ".ci/run no longer does what the README says"


@pytest.mark.parametrize("index", range(len(BLOCKS)))
def test_python_block_runs(index, capsys):
    exec(compile(BLOCKS[index], f"README.md block {index}", "exec"), {"__name__": "__readme__"})


def test_every_module_the_readme_runs_with_python_m_exists():
    modules = set(re.findall(r"python -m ([A-Za-z_][\w.]*)", PROSE))
    assert {"gchgg.train", "gchgg.analysis.claims", "gchgg.analysis.plot"} <= modules
    missing = [m for m in sorted(modules) if importlib.util.find_spec(m) is None]
    assert not missing, f"README.md runs modules that do not exist: {missing}"


def test_every_script_and_file_the_readme_names_exists():
    scripts = set(re.findall(r"python ([\w./-]+\.py)", PROSE))
    assert {"docs/iteration_rounds.py", "benchmarks/iteration.py"} <= scripts
    named = set(re.findall(r"`((?:docs|examples|tests|benchmarks|gchgg|conf|\.ci)/[\w./-]+)`", TEXT))
    missing = [p for p in sorted(scripts | named) if "<" not in p and not (REPO / p).exists()]
    assert not missing, f"README.md names files that do not exist: {missing}"


def test_links_point_at_files():
    missing = [link for link in re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", TEXT)
               if not link.startswith("http") and not (README.parent / link).exists()]
    assert not missing, f"README.md links to files that do not exist: {missing}"


def test_the_results_block_is_what_the_generator_writes():
    """After adding runs or claims: python -m gchgg.analysis.claims docs/results --readme README.md"""
    block = claims.readme_results(REPO / "docs/results", readme_dir=REPO)
    assert claims.README_COMMAND in TEXT, "README.md does not name the command that writes its results block"
    assert claims.replace_block(TEXT, block) == TEXT, (
        f"README.md's results block is stale: regenerate it with `{claims.README_COMMAND}`")


def test_the_generator_rewrites_only_the_block_between_the_markers(tmp_path):
    readme = tmp_path / "README.md"
    readme.write_text(f"# title\n\nbefore\n{claims.README_BEGIN}\nSTALE\n{claims.README_END}\nafter\n")
    claims.main([str(REPO / "docs/results"), "--readme", str(readme)])
    text = readme.read_text()
    assert text.startswith(f"# title\n\nbefore\n{claims.README_BEGIN}\n")
    assert text.endswith(f"{claims.README_END}\nafter\n")
    assert "STALE" not in text and "| reach (15) |" in text
    readme.write_text("no markers\n")
    with pytest.raises(SystemExit):
        claims.main([str(REPO / "docs/results"), "--readme", str(readme)])


def test_the_speed_figures_are_what_the_named_scripts_printed():
    printed = subprocess.run([sys.executable, *ROUNDS_COMMAND], cwd=REPO, capture_output=True, text=True,
                             check=True).stdout
    assert " ".join(ROUNDS_COMMAND) in PROSE, "README.md does not name the command behind its pooled figure"
    assert (REPO / "docs/benchmark_logs/iteration_rounds.txt").read_text() == printed, (
        "docs/benchmark_logs/iteration_rounds.txt is not what docs/iteration_rounds.py prints")
    pooled = next(line for line in printed.splitlines() if line.startswith("pooled:"))
    assert f"    {pooled}\n" in TEXT, "README.md does not quote the pooled line docs/iteration_rounds.py prints"
    quoted = re.search(r"`(gchgg / her = [0-9.]+)` in `(docs/benchmark_logs/[\w.-]+)`", PROSE)
    assert quoted, "README.md's GC-HGG / HER figure names no committed output"
    log = (REPO / quoted.group(2)).read_text()
    assert quoted.group(1) in log
    assert "the paper: 179 s / 52 s = 3.4)" in log and "where the paper reports 3.4×" in PROSE
    assert re.search(rf"cost {re.escape(quoted.group(1).split('= ')[1])}× a HER one", PROSE)
