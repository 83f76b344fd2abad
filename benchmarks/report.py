"""Runs a benchmark's ``main`` and, with ``--docs``, writes what it printed into ``docs/benchmarks.md``.

Every benchmark script ends with ``report.run(main, __file__)``. With ``--docs`` on its command line
(removed before the script parses its own arguments) the figures it printed replace that script's
section of ``docs/benchmarks.md``, under a line that records the command, the commit, the date,
the machine (with the CPU capability torch runs at) and its load average when the run started (and
``$BENCHMARK_NOTE``, e.g. "training runs paused"): these machines are shared, so a figure is only as
quiet as the machine was. Other sections are left as they are. A run where torch runs at a
capability other than AVX-512, or on a CPU with AMX tiles (Intel Xeon: bfloat16 products on AMX,
and its own BLAS's speed), writes its own section, ``<script> on <kind>`` (e.g. ``linear.py on AVX2``,
``iteration.py on AVX512 with AMX``), so the figures of each kind of machine stand side by side.
A part a script leaves out (:func:`left_out`: an option narrowed the run, or :func:`missing_input`: an input
file it reads is missing, e.g. the recorded goals of ``samplers.py``) keeps ``--docs`` from writing: the
section would lose figures it held.
"""

from __future__ import annotations

import contextlib
import datetime
import io
import os
import platform
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs" / "benchmarks.md"
HEADER = """# Benchmarks

Written by the scripts in `benchmarks/` (`python benchmarks/<name>.py --docs`); do not edit by hand.
Each section is the script's output from its last run with `--docs`, under the commit, date,
machine and load average it ran with (and how the machine was shared, where that was noted). \
Speed is printed as ratios measured in the same run: the
machines are shared and noisy, so absolute times vary between runs by up to 2x. A section titled
`<script> on <kind>` ran on such a CPU: AVX2 (torch at AVX2: no AVX-512, so no native bfloat16 and
slower oneDNN products) or AVX512 with AMX (an Intel Xeon: AVX-512 and AMX tiles, bfloat16 products
on AMX); the others on AVX-512 machines without AMX (AMD EPYC).
"""


class _Tee(io.TextIOBase):
    def __init__(self, *streams) -> None:
        self.streams = streams

    def write(self, text: str) -> int:
        for stream in self.streams:
            stream.write(text)
        return len(text)

    def flush(self) -> None:
        for stream in self.streams:
            stream.flush()


_left_out: list[str] = []  # the parts this run left out, and why (left_out)


def left_out(part: str, why: str) -> None:
    """Record that this run leaves ``part`` out (``why``: e.g. the option that narrowed it); :func:`run` then
    refuses ``--docs``, so a script's section never loses the figures of a part."""
    _left_out.append(f"{part} ({why})")


def missing_input(part: str, path: Path, how: str) -> None:
    """Say that ``part`` is skipped because its input file ``path`` is missing (``how``: what writes it),
    and leave it out (:func:`left_out`)."""
    print(f"{part}: skipped, {_shown(path)} is missing ({how})")
    left_out(part, f"{_shown(path)} is missing; {how}")


def _shown(path: Path) -> Path:
    """``path`` relative to the checkout where it lies inside it."""
    return path.relative_to(ROOT) if path.is_relative_to(ROOT) else path


def run(main: Callable[[], None], script: str) -> None:
    """``main()``; with ``--docs`` in ``sys.argv`` also write its output into ``docs/benchmarks.md``, unless a
    part was left out (:func:`left_out`, :func:`missing_input`): then exit with status 1, naming it."""
    write = "--docs" in sys.argv
    if write:
        sys.argv.remove("--docs")
    note = os.environ.get("BENCHMARK_NOTE", "")  # e.g. how the machine was used during the run
    started = _context(script) + (f" {note}" if note else "")
    captured = io.StringIO()
    with contextlib.redirect_stdout(_Tee(sys.stdout, captured)):
        main()
    if write and _left_out:
        sys.exit(f"--docs: not written, this run left out {'; '.join(_left_out)}; the section in {_shown(DOCS)} "
                 "keeps its figures. Run every part to write it.")
    if write:
        name = section_name(Path(script).name, _kind())
        write_section(name, started, captured.getvalue())
        print(f"wrote the {name} section of {_shown(DOCS)}", file=sys.stderr)


def section_name(script: str, kind: str) -> str:
    """The script's section: its name on AVX-512 without AMX, ``<script> on <kind>`` elsewhere."""
    return script if kind == "AVX512" else f"{script} on {kind}"


def _kind() -> str:
    """The machine's kind for its section: the capability torch runs at, ``+ " with AMX"`` where the CPU
    has AMX tiles (``amx_bf16`` in ``/proc/cpuinfo``'s flags)."""
    try:
        amx = any(line.startswith("flags") and " amx_bf16" in line
                  for line in Path("/proc/cpuinfo").read_text().splitlines())  # fmt: skip
    except OSError:
        amx = False
    return _capability() + (" with AMX" if amx else "")


def _capability() -> str:
    """The CPU capability torch's kernels run at (``AVX512``, ``AVX2``, …): :func:`gchgg.fast.linear.cpu_capability`."""
    from gchgg.fast.linear import cpu_capability

    return cpu_capability()


def _context(script: str) -> str:
    """The line above a section: command, commit, date, machine, load."""
    args = " ".join(a for a in sys.argv[1:] if a != "--docs")
    command = f"python benchmarks/{Path(script).name}" + (f" {args}" if args else "")
    commit = _git("rev-parse", "--short", "HEAD") or "unknown commit"
    if _git("status", "--porcelain", "--untracked-files=no", "--", ".", ":!docs/benchmarks.md"):
        commit += " (with uncommitted changes)"
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg()) if hasattr(os, "getloadavg") else "n/a"
    date = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    machine = f"{os.cpu_count()} CPUs ({_cpu_model()}, torch at {_capability()}), Python {platform.python_version()}"
    return f"`{command}` at {commit}, {date}; {machine}; load average {load} at the start."


def _git(*args: str) -> str:
    try:
        out = subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, check=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return ""
    return out.stdout.strip()


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def write_section(name: str, context: str, output: str) -> None:
    """Replace (or add, in name order) the ``name`` section of ``docs/benchmarks.md``."""
    sections = _read_sections()
    sections[name] = f"{context}\n\n```text\n{output.rstrip()}\n```\n"
    body = "".join(f"\n## {key}\n\n{sections[key]}" for key in sorted(sections))
    DOCS.write_text(HEADER + body)


def _read_sections() -> dict[str, str]:
    if not DOCS.is_file():
        return {}
    sections: dict[str, str] = {}
    current = None
    for line in DOCS.read_text().splitlines(keepends=True):
        if line.startswith("## "):
            current = line[3:].strip()
            sections[current] = ""
        elif current is not None:
            sections[current] += line
    return {key: text.strip("\n") + "\n" for key, text in sections.items()}
