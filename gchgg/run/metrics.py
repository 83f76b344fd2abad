"""An iteration's timings and diagnostics, gathered over its chunks and updates; ``metrics.csv``, the run's record."""

from __future__ import annotations

import csv
import io
import time
from pathlib import Path

import numpy as np
import torch

from gchgg.common import files
from gchgg.ddpg.agent import DDPGAgent
from gchgg.run.rollout import fraction

__all__ = ["PHASES", "IterationStats", "PhaseTimer", "log_complete", "write_csv"]

PHASES = ("goals", "rollout", "store", "update")  # an iteration's timed phases (seconds_<phase> columns)


class PhaseTimer:
    """Wall-clock seconds per phase of an iteration: :meth:`lap` charges the time since the last lap."""

    def __init__(self, phases: tuple[str, ...] = PHASES) -> None:
        self.seconds = dict.fromkeys(phases, 0.0)
        self._clock = time.perf_counter()

    def lap(self, phase: str) -> None:
        now = time.perf_counter()
        self.seconds[phase] += now - self._clock
        self._clock = now

    def since_lap(self) -> float:
        return time.perf_counter() - self._clock

    def columns(self) -> dict[str, float]:
        return {f"seconds_{phase}": seconds for phase, seconds in self.seconds.items()}


class IterationStats:
    """Accumulates an iteration's diagnostics over its chunks and updates (tensors, one float at the end)."""

    CURRICULUM = {  # sampled-batch entry (from the sampler's info) -> metrics column
        "diversity": "diversity",
        "proximity": "proximity",
        "tradeoff": "lambda_mean",
        "diversity_spread": "diversity_spread",
        "proximity_spread": "proximity_spread",
        "diversity_decided": "diversity_decided",
    }

    def __init__(self) -> None:
        self.success, self.distance, self.off_table, self.motion = [], [], [], []
        self.trajectories, self.first_observations = [], []
        self.losses: dict[str, list[float]] = {}
        self.clipped: list[torch.Tensor] = []
        self.curriculum: dict[str, list[torch.Tensor]] = {}

    MOTION = {  # column -> (what of the object's displacement from its start, threshold in metres)
        "object_moved": ("distance", 0.01),
        "object_rose_2cm": ("height", 0.02),
        "object_rose_10cm": ("height", 0.10),
    }
    """Per training episode, at any of its steps (the thresholds of ``docs/learnability.py``)."""

    def add_episodes(self, rollout, geometry, achieved_key: str = "achieved_goal") -> None:
        """Training success, final distance, object off the table, how far the object moved and rose,
        and the trajectories, from the (true) achieved goals under ``achieved_key``."""
        final = rollout["next", achieved_key][:, -1]
        self.success.append(rollout["next", "is_success"][:, -1].reshape(-1))
        self.distance.append(torch.linalg.vector_norm(final - rollout["desired_goal"][:, -1], dim=-1))
        trajectory = torch.cat([rollout[achieved_key][:, :1], rollout["next", achieved_key]], dim=1)
        if geometry is not None:
            self.off_table.append(geometry.below_table(final))
            shift = trajectory - trajectory[:, :1]
            furthest = {"distance": torch.linalg.vector_norm(shift, dim=-1).amax(1), "height": shift[..., 2].amax(1)}
            self.motion.append(torch.stack([furthest[what] > limit for what, limit in self.MOTION.values()], -1))
        self.trajectories.append(trajectory)
        self.first_observations.append(rollout["observation"][:, 0])

    def add_update(self, losses: dict[str, float], batch, agent: DDPGAgent) -> None:
        for key, value in losses.items():
            self.losses.setdefault(key, []).append(value)
        self.clipped.append(torch.stack(agent.clipped_fraction(batch["observation"], batch["desired_goal"])))
        for key in self.CURRICULUM:
            if key in batch.keys():
                self.curriculum.setdefault(key, []).append(batch.get(key)[0])

    def achieved(self) -> torch.Tensor:
        return torch.cat(self.trajectories)

    def initial_observations(self) -> torch.Tensor:
        return torch.cat(self.first_observations)

    def row(self) -> dict[str, float]:
        row = {
            "train_success_rate": fraction(torch.cat(self.success)),
            "train_final_distance": float(torch.cat(self.distance).mean()),
        }
        if self.off_table:
            row["object_off_table"] = fraction(torch.cat(self.off_table))
            row.update(zip(self.MOTION, fraction(torch.cat(self.motion), dim=0), strict=True))
        row.update({key: float(np.mean(values)) for key, values in self.losses.items()})
        if self.clipped:
            observation, goal = torch.stack(self.clipped).mean(0).tolist()
            row.update(observation_clipped=observation, goal_clipped=goal)
        row.update({self.CURRICULUM[key]: float(torch.stack(v).float().mean()) for key, v in self.curriculum.items()})
        return row


def write_csv(history: list[dict[str, float]], path: Path, before: int | None = None) -> None:
    """Write the rows of ``history`` (those of iterations before ``before``, when given) to ``path``
    atomically (:func:`gchgg.common.files.write_text`: a failed write, a full disk's
    :class:`~gchgg.common.files.DiskFullError` included, leaves the previous file whole): columns in order
    of first appearance, a row's missing columns empty."""
    rows = history if before is None else [row for row in history if row["iteration"] < before]
    columns = list(dict.fromkeys(key for row in rows for key in row))
    text = io.StringIO(newline="")
    writer = csv.DictWriter(text, columns)
    writer.writeheader()
    writer.writerows(rows)
    files.write_text(path, text.getvalue())


def log_complete(history: list[dict], logged: int, before: int | None, trackers) -> int:
    """Send the rows of ``history`` from position ``logged`` on to ``trackers`` (each whole, at step = its
    iteration), up to the first of iteration ``before`` (an evaluation still in flight); returns how many
    rows are logged now."""
    while logged < len(history) and (before is None or history[logged]["iteration"] < before):
        if trackers is not None:
            trackers.log_row(history[logged], step=history[logged]["iteration"])
        logged += 1
    return logged
