"""Scripted controllers for the four KUKA tasks, batched over envs; ``python -m envs.scripted`` measures them.

Each controller maps a batch of observations and desired goals (numpy ``[N, obs_dim]`` and
``[N, 3]``) to actions ``[N, A]`` in [-1, 1]. They hold no state: the phase of each env (approach,
grasp, carry, ...) is read from its observation, so a dropped cube is simply picked up again.
``CONTROLLERS[name]`` is the controller of task ``name``; :func:`policy` wraps one as a TorchRL policy.

    python -m envs.scripted --episodes 100            # success rate of every task's controller
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Callable

import numpy as np
import torch
from tensordict import TensorDictBase

from envs.layout import NO_OBJECT, WITH_OBJECT

_STEP = 0.05  # metres of motion per unit action (the env's action scale)
_FINGER_OPEN = 0.0425  # metres: a finger's opening when fully open

# Pick tasks (the 3 cm cube).
_APPROACH_HEIGHT = 0.05  # metres above the cube's centre before descending onto it
_CARRY_HEIGHT = 1.25  # metres: grip height when carrying the cube over the wall (top at 1.15)
_BEHIND_WALL = -0.09  # metres: y the cube must pass before descending behind the wall

# push_new (the 4 cm cube, the wall from x = 0.5 to 0.87 along y = 0).
_PUSH_HEIGHT = 0.87  # metres: grip height when pushing (the cube's centre)
_SAFE_HEIGHT = 0.935  # metres: grip height that clears the cube when moving around it
_CUBE_HALF = 0.02  # metres: half-width of the pushed cube
_PAD_HALF = (0.02, 0.01)  # metres: half-widths of the closed fingers along world x and y
_CLEARANCE = 0.012  # metres: gap between fingers and cube before a push starts
_PASSAGE_X = 0.915  # metres: x of the cube's path through the passage at the wall's end
_EXIT_Y = -0.16  # metres: y the cube is pushed to after the passage, before it turns to the goal

Controller = Callable[[np.ndarray, np.ndarray], np.ndarray]


def _move(grip: np.ndarray, target: np.ndarray, gain: float = 1.0) -> np.ndarray:
    """Actions that move the grip towards ``target`` (one step covers up to 5 cm)."""
    return np.clip(gain * (target - grip) / _STEP, -1.0, 1.0)


def reach(observation: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """Move the grip straight to the goal."""
    return _move(observation[:, NO_OBJECT["grip_position"]], goal)


def pick_and_place(observation: np.ndarray, goal: np.ndarray, over_wall: bool = False) -> np.ndarray:
    """Approach the cube from above with the fingers open, close on it, carry it to the goal.

    With ``over_wall`` the cube is first lifted to ``_CARRY_HEIGHT`` and lowered only once it is
    behind the wall (y < ``_BEHIND_WALL``).
    """
    part = WITH_OBJECT
    grip, cube = observation[:, part["grip_position"]], observation[:, part["object_position"]]
    rel = observation[:, part["object_relative"]]
    opening = observation[:, part["finger_positions"]].mean(axis=1)
    distance = np.linalg.norm(rel, axis=1)
    held = (distance < 0.02) & (opening > 0.008) & (opening < 0.019)  # fingers closed on the cube
    at_cube = distance < 0.008
    above = np.linalg.norm(rel[:, :2], axis=1) < 0.005
    open_enough = opening > 0.03

    target = cube + np.array([0.0, 0.0, _APPROACH_HEIGHT])
    descend = above & (open_enough | at_cube)
    target = np.where(descend[:, None], cube, target)
    # Starting beside the cube at its height (the pick tasks' original start): rise straight up first,
    # so that the fingers do not drag the cube sideways.
    low = grip[:, 2] < cube[:, 2] + _APPROACH_HEIGHT - 0.01
    rise = low & ~above & ~held
    straight_up = np.column_stack([grip[:, 0], grip[:, 1], cube[:, 2] + _APPROACH_HEIGHT])
    target = np.where(rise[:, None], straight_up, target)
    carry = goal.copy()
    if over_wall:
        before_wall = cube[:, 1] > _BEHIND_WALL
        low = cube[:, 2] < _CARRY_HEIGHT - 0.02
        lift = np.column_stack([cube[:, 0], cube[:, 1], np.full(len(cube), _CARRY_HEIGHT)])
        cross = np.column_stack([goal[:, 0], goal[:, 1], np.full(len(cube), _CARRY_HEIGHT)])
        carry = np.where((before_wall & low)[:, None], lift, np.where(before_wall[:, None], cross, goal))
    target = np.where(held[:, None], carry + (grip - cube), target)
    close = held | at_cube
    gripper = np.where(close, -1.0, 1.0)
    return np.column_stack([_move(grip, target, gain=1.5), gripper])


def pick_obstacle(observation: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """Pick the cube, lift it over the wall and place it at the goal behind."""
    return pick_and_place(observation, goal, over_wall=True)


def push_around_wall(observation: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """Push the cube through the passage at the wall's end, then to the goal.

    The cube's sub-goal is the passage entry while it is north of the wall and west of the
    passage, the passage exit while it is in or beside the passage, and the goal once it is south
    of the wall. The grip pushes from behind the cube (opposite its direction to the sub-goal);
    when it is not there, it rises above the cube, moves behind it and comes down.
    """
    grip, cube = observation[:, WITH_OBJECT["grip_position"]], observation[:, WITH_OBJECT["object_position"]]
    n = len(cube)
    # South of the wall, and clear of the passage: pushed from the passage exit well south of the
    # wall's face, so that the hand behind the cube never scrapes the wall on the way to the goal.
    south = (cube[:, 1] < -0.065) & ((cube[:, 1] < _EXIT_Y + 0.01) | (cube[:, 0] < _PASSAGE_X - 0.04))
    north_west = (cube[:, 1] > 0.07) & (cube[:, 0] < _PASSAGE_X - 0.01)
    entry = np.array([_PASSAGE_X, 0.15])
    exit_ = np.array([_PASSAGE_X, _EXIT_Y])
    sub_goal = np.where(south[:, None], goal[:, :2], np.where(north_west[:, None], entry, exit_))

    to_goal = sub_goal - cube[:, :2]
    remaining = np.linalg.norm(to_goal, axis=1)
    direction = to_goal / np.maximum(remaining, 1e-6)[:, None]
    # Grip centre to cube centre at contact along the direction: the cube's and the closed fingers' half-widths.
    contact = _CUBE_HALF + _PAD_HALF[0] * np.abs(direction[:, 0]) + _PAD_HALF[1] * np.abs(direction[:, 1])
    behind = cube[:, :2] - (contact + _CLEARANCE)[:, None] * direction
    offset = grip[:, :2] - cube[:, :2]
    along = np.sum(offset * direction, axis=1)
    lateral = np.abs(offset[:, 0] * direction[:, 1] - offset[:, 1] * direction[:, 0])
    low = grip[:, 2] < _PUSH_HEIGHT + 0.015
    pushing = low & (along < -contact + 0.008) & (along > -contact - _CLEARANCE - 0.02) & (lateral < 0.012)

    # Pushing: the grip moves along the direction, recentred behind the cube, at up to 0.6 m/s and
    # slowing down near the final goal so that the cube does not slide past it.
    step = np.where(south, np.clip(0.5 * remaining, 0.005, 0.03), 0.03)
    push_target = np.column_stack([behind + (_CLEARANCE + step)[:, None] * direction, np.full(n, _PUSH_HEIGHT)])
    # Repositioning: up if near the cube, over to behind it, then down.
    near_behind = np.linalg.norm(grip[:, :2] - behind, axis=1) < 0.01
    close_to_cube = np.linalg.norm(offset, axis=1) < 0.07
    reposition = np.column_stack([behind, np.full(n, _SAFE_HEIGHT)])
    reposition = np.where((low & close_to_cube & ~near_behind)[:, None],
                          np.column_stack([grip[:, :2], np.full(n, _SAFE_HEIGHT)]), reposition)
    reposition = np.where(near_behind[:, None], np.column_stack([behind, np.full(n, _PUSH_HEIGHT)]), reposition)
    action = np.where(pushing[:, None], _move(grip, push_target), _move(grip, reposition, gain=1.5))
    done = south & (remaining < 0.015)
    return np.where(done[:, None], 0.0, action)


CONTROLLERS: dict[str, Controller] = {
    "reach": reach,
    "push_new": push_around_wall,
    "pick_no_obstacle": pick_and_place,
    "pick_obstacle": pick_obstacle,
}


def policy(name: str) -> Callable[[TensorDictBase], TensorDictBase]:
    """A TorchRL policy (TensorDict in, ``action`` written) running task ``name``'s controller."""
    controller = CONTROLLERS[name]

    def act(tensordict: TensorDictBase) -> TensorDictBase:
        observation = tensordict.get("observation").double().numpy()
        goal = tensordict.get("desired_goal").double().numpy()
        return tensordict.set("action", torch.as_tensor(controller(observation, goal), dtype=torch.float32))

    return act


def success_rate(name: str, episodes: int, num_envs: int = 50, seed: int = 0) -> float:
    """Fraction of ``episodes`` random episodes of task ``name`` the controller ends in success.

    Success is ``is_success`` at the last step, as in the paper's evaluation.
    """
    from envs.torchrl_env import KukaEnv

    env = KukaEnv(name, num_envs=min(num_envs, episodes), seed=seed)
    successes, done = 0, 0
    while done < episodes:
        rollout = env.rollout(env.geometry.episode_length, policy(name), break_when_any_done=False)
        final = rollout["next", "is_success"][:, -1, 0]
        take = min(episodes - done, env.num_envs)
        successes += int(final[:take].sum())
        done += take
    return successes / episodes


def main() -> None:
    os.environ.setdefault("MUJOCO_GL", "disable")
    from envs.geometry import TASKS

    parser = argparse.ArgumentParser(description="Success rate of the scripted controllers.")
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--num-envs", type=int, default=50)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--tasks", nargs="+", default=list(TASKS), choices=TASKS)
    args = parser.parse_args()
    for name in args.tasks:
        rate = success_rate(name, args.episodes, args.num_envs, args.seed)
        print(f"{name:<18} success {rate:.2f} over {args.episodes} episodes")


if __name__ == "__main__":
    main()
