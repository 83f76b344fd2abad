"""Records one GIF per task of its scripted controller into docs/media/ (the README shows them).

    MUJOCO_GL=egl python docs/make_gifs.py [--tasks reach push_new ...] [--camera side]

Each GIF is one episode of ``envs.scripted``'s controller on the task's first goal of seed 0,
every second control step at 10 frames per second (the real-time rate), 240 x 320 pixels.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("MUJOCO_GL", "egl")


def main() -> None:
    import torch

    from envs import TASKS, scripted
    from gchgg.analysis.evaluate import record

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=list(TASKS), choices=TASKS)
    parser.add_argument("--camera", default="side")
    parser.add_argument("--out", default=str(ROOT / "docs" / "media"))
    args = parser.parse_args()
    Path(args.out).mkdir(parents=True, exist_ok=True)
    for task in args.tasks:
        controller = scripted.CONTROLLERS[task]

        def act(observation, goal, controller=controller):
            action = controller(observation.double().numpy(), goal.double().numpy())
            return torch.as_tensor(action, dtype=torch.float32)

        path = Path(args.out) / f"{task}.gif"
        frames = record(act, task, path, episodes=1, seed=0, camera=args.camera, every=2, fps=10)
        print(f"{path}: {frames} frames, {path.stat().st_size / 1e6:.2f} MB")


if __name__ == "__main__":
    main()
