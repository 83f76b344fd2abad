"""The sparse goal reward of all four tasks (eq. 23), one pure batched function for the env and HER."""

from __future__ import annotations

import numpy as np
import torch

DEFAULT_THRESHOLD = 0.05  # metres


def reward(achieved_goal, desired_goal, threshold: float = DEFAULT_THRESHOLD):
    """Sparse reward: 0 where ``||achieved_goal - desired_goal|| <= threshold``, else -1 (eq. 23).

    Works on torch tensors (returns a float32 tensor) and on numpy arrays (returns float32 numpy);
    the last dimension holds the 3 coordinates and leading dimensions broadcast.

    Args:
        achieved_goal: ``[..., 3]`` achieved goals (object or grip positions), metres.
        desired_goal: ``[..., 3]`` desired goals, metres.
        threshold: success distance in metres.

    Returns:
        float32 ``[...]``: 0.0 for success, -1.0 otherwise.

    >>> import torch
    >>> reward(torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]]), torch.zeros(3))
    tensor([ 0., -1.])
    """
    if isinstance(achieved_goal, torch.Tensor) or isinstance(desired_goal, torch.Tensor):
        distance = torch.linalg.vector_norm(torch.as_tensor(achieved_goal) - torch.as_tensor(desired_goal), dim=-1)
        return (distance <= threshold).to(torch.float32) - 1.0
    distance = np.linalg.norm(np.asarray(achieved_goal) - np.asarray(desired_goal), axis=-1)
    return (distance <= threshold).astype(np.float32) - np.float32(1.0)
