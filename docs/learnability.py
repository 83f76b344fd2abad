"""Learnability of the object tasks: how often a uniform random policy moves, lifts and raises the object.

    python docs/learnability.py [--episodes 1000] [--tasks push_new pick_no_obstacle pick_obstacle]
                                [--out docs/results/learnability.md]

For each task with an object and each of its start states (``"original"``, the authors' start state,
and ``"above"``, the pick tasks' start before December 2026; :func:`envs.geometry.with_start`), runs
``--episodes`` episodes of the uniform random policy (50 simulations at a time, seed 0, actions
drawn from a seeded generator) and prints, per row, the fraction of episodes in which

* a finger or the palm touches the object at the start (the object's start is drawn around the
  grip's, so the open fingers of ``pick_no_obstacle`` sometimes start inside the cube's place),
* the object moves more than 1 cm from its start (at any step),
* it rises more than 2 cm, and more than 10 cm, above its start (at any step).

The table goes to stdout and, with ``--out``, into a Markdown file (the README links it).

``--starts`` prints instead, per task, where the authors' joint angles (``envs.geometry.AUTHORS_JOINTS``)
put this arm's grip, against the tip the task starts at (the authors' tip, REFERENCE.md).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "disable")
os.environ.setdefault("RL_LOGGING_LEVEL", "WARNING")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout

import torch  # noqa: E402

import envs  # noqa: E402
from envs.geometry import ABOVE_START, AUTHORS_JOINTS, with_start  # noqa: E402

BATCH = 50
HAND = ("left_finger", "right_finger", "palm")


def touching(physics) -> bool:
    """Whether a finger or the palm is in contact with the object (after a reset's forward pass)."""
    model, data = physics.model, physics.data
    obj = model.geom("object").id
    hand = {model.geom(name).id for name in HAND}
    for k in range(data.ncon):
        pair = {int(data.contact[k].geom1), int(data.contact[k].geom2)}
        if obj in pair and pair & hand:
            return True
    return False


def measure(task: str, start: str, episodes: int) -> dict[str, float]:
    """Fractions of ``episodes`` random-policy episodes (see the module docstring)."""
    env = envs.make(task, num_envs=BATCH, seed=0, start=start)
    generator = torch.Generator().manual_seed(0)
    steps = env.geometry.episode_length
    counts = {"touching at start": 0, "moved > 1 cm": 0, "rose > 2 cm": 0, "rose > 10 cm": 0}
    done = 0
    while done < episodes:
        td = env.reset()
        counts["touching at start"] += sum(touching(physics) for physics in env.physics)
        actions = torch.rand(steps, BATCH, env.action_dim, generator=generator) * 2 - 1
        start_position = td["achieved_goal"].clone()
        moved = torch.zeros(BATCH)
        rose = torch.zeros(BATCH)
        for t in range(steps):
            td = env.step(td.set("action", actions[t]))["next"]
            shift = td["achieved_goal"] - start_position
            moved = torch.maximum(moved, shift.norm(dim=-1))
            rose = torch.maximum(rose, shift[:, 2])
        counts["moved > 1 cm"] += int((moved > 0.01).sum())
        counts["rose > 2 cm"] += int((rose > 0.02).sum())
        counts["rose > 10 cm"] += int((rose > 0.10).sum())
        done += BATCH
        print(f"  {task} ({start}): {done}/{episodes} episodes", file=sys.stderr, flush=True)
    return {key: value / done for key, value in counts.items()} | {"episodes": done}


def starts() -> None:
    """Where the authors' joint angles put this arm's grip, against each task's start tip."""
    print("| task | the authors' tip (the start) | their joint angles on this arm | difference (m) |")
    print("|---|---|---|---|")
    for task, joints in AUTHORS_JOINTS.items():
        env = envs.load(task, seed=0)
        env.reset()
        physics = env.physics
        tip = physics.grip_position().copy()
        physics.named.data.qpos[[f"joint{i}" for i in range(1, 8)]] = joints
        physics.forward()
        grip = physics.grip_position().copy()
        fmt = lambda v: "(" + ", ".join(f"{x:.3f}" for x in v) + ")"  # noqa: E731
        print(f"| {task} | {fmt(tip)} | {fmt(grip)} | {fmt(grip - tip)} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=1000)
    parser.add_argument("--tasks", nargs="+", default=["push_new", "pick_no_obstacle", "pick_obstacle"])
    parser.add_argument("--out", type=Path, help="also write the table into this Markdown file")
    parser.add_argument("--starts", action="store_true",
                        help="print where the authors' joint angles put this arm's grip")
    args = parser.parse_args()
    if args.starts:
        starts()
        return
    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")
    lines = [
        f"Uniform random policy, {args.episodes} episodes per row (seed 0); "
        "`python docs/learnability.py` prints this table.",
        "",
        "| task | start | grip at start | fingers | touching at start | moved > 1 cm | rose > 2 cm | rose > 10 cm |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for task in args.tasks:
        for start in ("original", "above") if task in ABOVE_START else ("original",):
            geometry = with_start(envs.geometry(task), start)
            row = measure(task, start, args.episodes)
            grip = "(" + ", ".join(f"{v:g}" for v in geometry.gripper_start) + ")"
            cells = [task, start, grip, f"{geometry.finger_start:g} m"]
            cells += [f"{row[key]:.3f}" for key in ("touching at start", "moved > 1 cm", "rose > 2 cm", "rose > 10 cm")]
            lines.append("| " + " | ".join(cells) + " |")
            print(lines[-1], flush=True)
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        args.out.write_text(text)
        print(f"wrote {args.out}", file=sys.stderr)


if __name__ == "__main__":
    main()
