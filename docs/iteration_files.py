"""Which of the project's Python files one training iteration runs: ``python docs/iteration_files.py [--algo gchgg]``.

Builds a small push_new trainer (2 episodes, warm-up over, a coarse graph), runs one untimed iteration
to fill the buffer and the goal pool, then records, with a profiler hook, every function of the project
(``gchgg/`` and ``envs/``) that a second ``Trainer.iteration_step`` calls, and prints the files in order
of first call with their line counts: the files a reader follows through one iteration. Its output
is quoted in the README's "One iteration, file by file".
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--algo", default="gchgg")
    parser.add_argument("--plain", action="store_true",
                        help="plain=true: the algorithm alone, no speed device of gchgg/fast")
    args = parser.parse_args()
    plain = ["plain=true"] if args.plain else []
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", overrides=[
            "env=push_new", f"algo={args.algo}", "train.episodes=2", "train.updates=4", "train.batch_size=64",
            "train.warmup_steps=0", "eval.episodes=2", "buffer.episodes=16", "graph.n=[11,11,5]",
            "logging.progress=false", "eval.background=false", *plain])  # fmt: skip
    with tempfile.TemporaryDirectory() as run_dir:
        trainer = Trainer(cfg, Path(run_dir))
        trainer.iteration_step()
        first_call: dict[str, int] = {}

        def hook(frame, event, arg) -> None:
            if event == "call":
                path = Path(frame.f_code.co_filename).resolve()
                if path.is_relative_to(ROOT) and path.suffix == ".py":
                    first_call.setdefault(str(path.relative_to(ROOT)), len(first_call))

        sys.setprofile(hook)
        try:
            trainer.iteration_step()
        finally:
            sys.setprofile(None)
    files = sorted(first_call, key=first_call.get)
    lines = {f: sum(1 for _ in open(ROOT / f)) for f in files}
    print(f"one algo={args.algo} iteration (Trainer.iteration_step) runs {len(files)} files of the project, "
          f"{sum(lines.values()):,} lines, in order of first call:")
    for f in files:
        print(f"  {f:40s} {lines[f]:5d} lines")


if __name__ == "__main__":
    main()
