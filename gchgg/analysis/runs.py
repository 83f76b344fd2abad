"""Training runs read back for analysis: their metrics and settings, grouped by the settings that differ, as curves.

:func:`find_runs` reads run folders (``metrics.csv`` and the ``config.yaml`` the trainer saves), folders
holding such runs at any depth (a sweep), ``metrics.csv``-style files, or folders of such files;
:func:`group_runs` groups them by task and by the settings that differ between them. A run without a
config is grouped by its file name without its ``-seed<N>`` suffix, and its task is its folder's name.
``python -m gchgg.analysis.plot`` (:mod:`gchgg.analysis.plot`) draws and tabulates the groups.
"""

from __future__ import annotations

import csv
import math
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["FRACTIONS", "Run", "curves", "find_runs", "first_at", "group_runs", "iqr", "load_run", "seed_of"]

# never a group's setting (subnormals: the same networks either way; flush before its default became auto)
_IGNORED = ("seed", "resume", "threads", "matmul", "subnormals", "logging.", "graph.cache_dir", "hydra.")
_SEED_SUFFIX = re.compile(r"-seed\d+$")


@dataclass
class Run:
    """One training run: where it is, its settings (flattened config) and its ``metrics.csv`` rows."""

    path: Path
    task: str
    settings: dict[str, str] = field(default_factory=dict)
    rows: list[dict[str, float]] = field(default_factory=list)
    label: str = ""

    def column(self, name: str) -> np.ndarray:
        """The column's values per iteration (NaN where a row lacks it)."""
        return np.array([row.get(name, math.nan) for row in self.rows], dtype=float)

    @property
    def hours(self) -> float:
        """Wall-clock hours of the logged iterations: the sum of the ``seconds_*`` columns."""
        return sum(self.iteration_seconds()) / 3600.0

    def iteration_seconds(self) -> list[float]:
        """Each logged iteration's wall-clock seconds: the sum of its ``seconds_*`` columns."""
        return [sum(v for k, v in row.items() if k.startswith("seconds_")) for row in self.rows]


def _flatten(tree: dict, prefix: str = "") -> dict[str, str]:
    out = {}
    for key, value in tree.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(_flatten(value, f"{name}."))
        else:
            out[name] = str(value)
    return out


FRACTIONS = ("success_rate", "train_success_rate", "object_off_table", "object_moved", "object_rose_2cm",
             "object_rose_10cm")
"""Columns that are fractions of episodes, read rounded to 6 decimals: runs before December 2026
wrote them as float32 means, 90 of 100 as 0.8999999762, which must count as reaching 0.9."""


def _read_rows(path: Path) -> list[dict[str, float]]:
    def value(key: str, text: str) -> float:
        return round(float(text), 6) if key in FRACTIONS else float(text)

    with open(path, newline="") as f:
        rows = [{k: value(k, v) for k, v in row.items() if v not in ("", None)} for row in csv.DictReader(f)]
    if not rows or "success_rate" not in rows[0]:
        raise ValueError(f"{path} is not a metrics.csv of a training run (no rows, or no success_rate column)")
    return rows


def load_run(path: str | Path) -> Run:
    """A run from its folder (``metrics.csv`` + ``config.yaml``) or from a metrics CSV file."""
    path = Path(path)
    csv_path = path / "metrics.csv" if path.is_dir() else path
    if not csv_path.is_file():
        raise FileNotFoundError(f"no metrics.csv at {csv_path}: pass a run folder, a sweep folder or a CSV file")
    config = csv_path.parent / "config.yaml" if path.is_dir() else csv_path.with_suffix(".yaml")
    settings, task = {}, ""
    if config.is_file():
        import yaml

        settings = _flatten(yaml.safe_load(config.read_text()) or {})
        task = settings.get("env.name", "")
    label = "" if settings else _SEED_SUFFIX.sub("", csv_path.stem)
    task = task or csv_path.parent.name  # docs/results/push_new/gchgg-seed0.csv: task push_new
    return Run(csv_path.parent if path.is_dir() else csv_path, task, settings, _read_rows(csv_path), label)


def find_runs(paths: Iterable[str | Path]) -> list[Run]:
    """Every run under ``paths`` (run folders, sweep folders searched recursively, or CSV files)."""
    runs = []
    for path in map(Path, paths):
        if path.is_dir() and not (path / "metrics.csv").is_file():
            found = sorted(p.parent for p in path.rglob("metrics.csv"))
            if not found:
                found = sorted(path.glob("*.csv"))  # a folder of metrics CSVs: docs/results/push_new
            if not found:
                raise FileNotFoundError(f"no metrics.csv under {path}, nor a CSV file in it")
            runs.extend(load_run(p) for p in found)
        else:
            runs.append(load_run(path))
    return runs


def group_runs(runs: Sequence[Run]) -> dict[tuple[str, str], list[Run]]:
    """Runs by (task, label): the label names the settings that differ between runs of the same task
    (``algo.name=gchgg, curriculum.scale=standardized``), or is the file name for runs without a config."""
    groups: dict[tuple[str, str], list[Run]] = {}
    by_task: dict[str, list[Run]] = {}
    for run in runs:
        by_task.setdefault(run.task, []).append(run)
    for task, members in by_task.items():
        configured = [r for r in members if r.settings]
        keys = sorted({k for r in configured for k in r.settings if not k.startswith(_IGNORED)})
        differing = [k for k in keys if len({r.settings.get(k) for r in configured}) > 1]
        if "algo.name" in differing:  # settings an algo choice implies (its sampler, metric, ...) add nothing
            by_algo: dict[str, list[Run]] = {}
            for r in configured:
                by_algo.setdefault(r.settings.get("algo.name"), []).append(r)
            implied = {
                k for k in differing
                if k != "algo.name" and all(len({r.settings.get(k) for r in rs}) == 1 for rs in by_algo.values())
            }  # fmt: skip
            differing = [k for k in differing if k not in implied]
        for run in members:
            if run.settings:
                label = (", ".join(f"{k}={run.settings.get(k)}" for k in differing)
                         or run.settings.get("algo.name", "run"))
                label = label.replace("algo.name=", "")
            else:
                label = run.label
            groups.setdefault((task, label), []).append(run)
    return groups


def iqr(values: Sequence[float]) -> tuple[float, float, float]:
    """``(median, first quartile, third quartile)`` (linear interpolation; ``inf`` allowed; NaN values,
    runs that did not log a column, are left out).

    >>> iqr([1.0, 2.0, 3.0, 4.0, float("nan")])
    (2.5, 1.75, 3.25)
    """
    values = np.asarray(values, dtype=float)
    values = np.sort(values[~np.isnan(values)])
    if len(values) == 0:
        return (math.nan,) * 3
    q = []
    for p in (0.5, 0.25, 0.75):  # numpy's percentile turns inf - inf into NaN; interpolate by hand
        pos = p * (len(values) - 1)
        lo, hi = int(math.floor(pos)), int(math.ceil(pos))
        frac = pos - lo
        q.append(values[lo] if frac == 0 or values[lo] == values[hi] else values[lo] + frac * (values[hi] - values[lo]))
    return float(q[0]), float(q[1]), float(q[2])


def curves(runs: Sequence[Run], column: str) -> np.ndarray:
    """``[runs, iterations]`` values of ``column``, each run held at its last value to the longest run's end."""
    length = max(len(r.rows) for r in runs)
    out = np.full((len(runs), length), math.nan)
    for i, run in enumerate(runs):
        values = run.column(column)
        out[i, : len(values)] = values
        if len(values):
            out[i, len(values) :] = values[-1]
    return out


def first_at(run: Run, threshold: float, column: str = "success_rate") -> float:
    """The first iteration whose ``column`` is ≥ ``threshold`` (``inf`` if none)."""
    for row in run.rows:
        if row.get(column, -math.inf) >= threshold:
            return row["iteration"]
    return math.inf




def seed_of(run: Run) -> int | None:
    """The run's seed: its config's ``seed``, else the ``-seed<N>`` of its CSV's name (``None`` without either)."""
    if "seed" in run.settings:
        return int(run.settings["seed"])
    match = re.search(r"-seed(\d+)$", Path(run.path).stem)
    return int(match.group(1)) if match else None

