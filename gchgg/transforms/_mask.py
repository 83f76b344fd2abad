"""Which steps of padded episodes are real: the valid-step mask of variable-length episodes, checked.

TorchRL's ``split_trajectories`` turns a collector's flat batch into zero-padded episodes
``[N, Tmax]`` and marks the real steps in a boolean mask (``("collector", "mask")`` when the batch
has a ``"collector"`` entry, ``"mask"`` otherwise). The episode transforms read it here.
"""

from __future__ import annotations

import torch
from tensordict import NestedKey, TensorDictBase

DEFAULT_MASK_KEY: NestedKey = ("collector", "mask")


def episode_lengths(tensordict: TensorDictBase, mask_key: NestedKey | None, who: str) -> torch.Tensor | None:
    """Valid steps per episode ``[*batch]`` (int64) from the mask under ``mask_key``, or ``None`` when there
    is no mask (``mask_key`` is ``None`` or absent: every step is valid).

    The mask must be boolean ``[*batch, T]`` (a trailing 1 is allowed) with the valid steps first in
    each episode (as ``split_trajectories`` pads them); anything else is a ``ValueError`` naming
    ``who``, the key and the shape.
    """
    if mask_key is None or mask_key not in tensordict.keys(include_nested=True):
        return None
    mask = tensordict.get(mask_key)
    if mask.shape[tensordict.batch_dims :] == (1,):
        mask = mask.squeeze(-1)
    if mask.dtype != torch.bool or mask.shape != tensordict.shape:
        raise ValueError(
            f"{who}: the valid-step mask {mask_key!r} must be bool with the episodes' batch shape "
            f"{tuple(tensordict.shape)} ([..., T]), got {mask.dtype} of shape {tuple(mask.shape)}"
        )
    lengths = mask.sum(-1)
    prefix = torch.arange(mask.shape[-1], device=mask.device) < lengths.unsqueeze(-1)
    if not bool((prefix == mask).all()):
        raise ValueError(
            f"{who}: the valid-step mask {mask_key!r} must mark each episode's first steps only (valid steps "
            f"first, padding after, as torchrl's split_trajectories pads), but an episode has a padded step "
            f"before a valid one"
        )
    return lengths
