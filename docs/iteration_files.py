"""Which of the project's Python files one training iteration runs: ``python docs/iteration_files.py [--plain]``.

Builds a small push_new trainer (2 episodes, warm-up over, a coarse graph), runs one untimed iteration
to fill the buffer and the goal pool, then records, with a profiler hook, every function of the project
(``gchgg/`` and ``envs/``) that a second ``Trainer.iteration_step`` calls, and prints the files in order
of first call with their line counts, each in its group (:data:`GROUPS`). Building the trainer is
recorded too, for the files that hold the run's values and wire the parts (``gchgg/run/config.py``,
``parts.py``, ``builders.py``): a reader opens those as well. The last line counts what a reader
following the algorithm opens: the algorithm's files the iteration runs and the wiring.
``--plain`` runs it with ``plain=true`` (the algorithm alone, no speed device). ``docs/iteration.md``
quotes its output.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("MUJOCO_GL", "disable")

from hydra import compose, initialize_config_dir  # noqa: E402

from gchgg.train import CONF_DIR, Trainer  # noqa: E402

GROUPS = {
    "the simulation": ("envs/",),
    "speed devices": ("gchgg/fast/",),
    "the run's record": ("gchgg/run/metrics.py", "gchgg/run/replay_log.py", "gchgg/run/evaluator.py"),
    "argument checks": ("gchgg/common/", "gchgg/transforms/_mask.py", "gchgg/samplers/_storage.py"),
    "values and wiring": ("gchgg/run/config.py", "gchgg/run/parts.py", "gchgg/run/builders.py"),
}
"""Files by what they are to a reader, by path prefix; every other file the iteration runs is the algorithm."""

READER = ("the algorithm", "values and wiring")
"""The groups a reader following the algorithm opens."""


def group_of(path: str) -> str:
    return next((name for name, prefixes in GROUPS.items() if path.startswith(prefixes)), "the algorithm")


def recorded(first_call: dict[str, int]):
    """A profiler hook recording each project file's first call into ``first_call``."""
    def hook(frame, event, arg) -> None:
        if event == "call":
            path = Path(frame.f_code.co_filename).resolve()
            if path.is_relative_to(ROOT) and path.suffix == ".py":
                first_call.setdefault(str(path.relative_to(ROOT)), len(first_call))
    return hook


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--algo", default="gchgg")
    parser.add_argument("--plain", action="store_true",
                        help="plain=true: the algorithm alone, no speed device (gchgg.fast)")
    args = parser.parse_args()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", overrides=[
            "env=push_new", f"algo={args.algo}", "train.episodes=2", "train.updates=4", "train.batch_size=64",
            "train.warmup_steps=0", "eval.episodes=2", "buffer.episodes=16", "graph.n=[11,11,5]",
            "logging.progress=false", "eval.background=false", *(["plain=true"] if args.plain else [])])  # fmt: skip
    built: dict[str, int] = {}
    first_call: dict[str, int] = {}
    with tempfile.TemporaryDirectory() as run_dir:
        sys.setprofile(recorded(built))
        try:
            trainer = Trainer(cfg, Path(run_dir))
        finally:
            sys.setprofile(None)
        trainer.iteration_step()
        sys.setprofile(recorded(first_call))
        try:
            trainer.iteration_step()
        finally:
            sys.setprofile(None)
    files = sorted(first_call, key=first_call.get)
    wiring = [f for f in sorted(built, key=built.get) if group_of(f) == "values and wiring" and f not in first_call]
    lines = {f: sum(1 for _ in open(ROOT / f)) for f in files + wiring}
    print(f"one algo={args.algo} iteration{' (plain=true)' if args.plain else ''} runs {len(files)} files of the "
          f"project, {sum(lines[f] for f in files):,} lines; by group, in order of first call:")
    for name in ("the algorithm", *GROUPS):
        members = [f for f in files if group_of(f) == name] + (wiring if name == "values and wiring" else [])
        if members:
            print(f"{name}: {len(members)} files, {sum(lines[f] for f in members):,} lines")
            for f in members:
                print(f"  {f:40s} {lines[f]:5d} lines" + ("  (building the parts)" if f in wiring else ""))
    reader = [f for f in files + wiring if group_of(f) in READER]
    print(f"a reader following the algorithm opens {len(reader)} files, {sum(lines[f] for f in reader):,} lines "
          f"({' and '.join(READER)})")


if __name__ == "__main__":
    main()
