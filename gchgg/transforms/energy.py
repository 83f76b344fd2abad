"""Trajectory energy of energy-based prioritisation (EBP, Zhao & Tresp 2018) and a transform that writes it per step.

The energy of an episode is computed on its achieved-goal trajectory ``p_0 … p_T`` (the object's
position for the manipulation tasks), treating it as a unit point mass:

    E_t = w_p · g · (h_t − h_0) + w_k · ½ · |v_t|²,   v_t = (p_t − p_{t−1}) / dt,   E_0 = 0
    energy = Σ_{t=1..T} clip(E_t − E_{t−1}, 0, clip)

with g = 9.81 m/s², h the coordinate of the up axis (``up_axis``, by default the last one: z of the
KUKA tasks' goals; ``None`` for a goal space without one, e.g. a planar maze, which leaves the
kinetic term) and the per-step increase clipped to ``[0, clip]`` (0.5 in the original HGG/GC-HGG
code). Goals may have any dimension d ≥ 1. Episodes in which the object never moves have energy 0,
and the EBP sampler (:class:`gchgg.samplers.EnergySampler`) never draws them while any episode has more.
"""

from __future__ import annotations

import torch
from tensordict import NestedKey, TensorDictBase
from torchrl.envs.transforms import Transform

from gchgg.common.validation import check_number
from gchgg.transforms._mask import DEFAULT_MASK_KEY, episode_lengths

__all__ = ["EpisodeEnergy", "trajectory_energy"]

GRAVITY = 9.81  # m/s²
DEFAULT_DT = 0.05  # seconds per control step (20 Hz, paper Sec. V-D; the original code used 0.04)
DEFAULT_CLIP = 0.5  # largest energy increase counted per step (original EBP setting for Fetch/KUKA)


def trajectory_energy(
    positions: torch.Tensor,
    dt: float = DEFAULT_DT,
    clip: float = DEFAULT_CLIP,
    *,
    w_potential: float = 1.0,
    w_kinetic: float = 1.0,
    up_axis: int | None = -1,
) -> torch.Tensor:
    """EBP energy of achieved-goal trajectories.

    Args:
        positions: ``[..., L, d]`` positions ``p_0 … p_{L−1}`` in metres (L ≥ 1, d ≥ 1).
        dt: seconds between two positions (> 0).
        clip: largest energy increase counted per step (> 0).
        w_potential: weight of the potential energy term (≥ 0).
        w_kinetic: weight of the kinetic energy term (≥ 0).
        up_axis: the coordinate that is height (``-d ≤ up_axis < d``); default the last (z of
            ``[x, y, z]`` goals); ``None``: no height, no potential term.

    Returns:
        float32 ``[...]``: the clipped, summed energy increases (≥ 0; 0 for ``L = 1``).

    Example:
        >>> import torch
        >>> still = torch.zeros(5, 3)
        >>> lifted = torch.tensor([[0.0, 0.0, z] for z in (0.0, 0.01, 0.02, 0.03, 0.04)])
        >>> trajectory_energy(torch.stack([still, lifted]), dt=0.05)  # 4 · g · 0.01 m + ½ · (0.2 m/s)²
        tensor([0.0000, 0.4124])
    """
    positions = torch.as_tensor(positions)
    if positions.ndim < 2 or positions.shape[-1] < 1:
        raise ValueError(f"positions must have shape [..., L, d] (d >= 1), got {tuple(positions.shape)}")
    for name, value in (("dt", dt), ("clip", clip)):
        check_number(name, value, low=0, low_open=True)
    for name, value in (("w_potential", w_potential), ("w_kinetic", w_kinetic)):
        check_number(name, value, low=0)
    dim = positions.shape[-1]
    if up_axis is not None and (isinstance(up_axis, bool) or not isinstance(up_axis, int) or not -dim <= up_axis < dim):
        raise ValueError(
            f"up_axis must be None (no height) or an axis of the {dim}-D positions, -{dim} <= up_axis < {dim}, "
            f"got {up_axis!r}"
        )
    positions = positions.to(torch.float64)
    velocity = positions.diff(dim=-2) / dt
    energy = w_kinetic * 0.5 * velocity.square().sum(-1)  # E_1 .. E_{L-1}
    if up_axis is not None:
        height = positions[..., 1:, up_axis] - positions[..., :1, up_axis]
        energy = w_potential * GRAVITY * height + energy
    increase = energy.diff(dim=-1, prepend=torch.zeros_like(energy[..., :1]))
    return increase.clamp(0.0, clip).sum(-1).to(torch.float32)


class EpisodeEnergy(Transform):
    """Writes each episode's EBP energy into every one of its steps (``[..., T]`` input).

    The trajectory is ``achieved_goal`` of steps 0 … T−1 followed by the last step's
    ``("next", achieved_goal)``. Apply it before :class:`~gchgg.transforms.HindsightRelabel`, which
    carries the entry into every relabelled copy, e.g. ``Compose(EpisodeEnergy(), HindsightRelabel(...))``.
    Padded episodes (TorchRL's ``split_trajectories``) are scored on their valid steps only: the
    trajectory ends with the last valid step's next achieved goal.

    Args:
        dt: seconds per step (> 0). Default 0.05 (20 Hz control).
        clip: largest energy increase counted per step. Default 0.5.

    Keyword Args:
        achieved_goal_key: key of the achieved goal, ``[..., T, d]`` (any d ≥ 1). Default ``"achieved_goal"``.
        out_key: key written, float32 ``[..., T]``. Default ``"energy"``.
        up_axis: the goal coordinate that is height, or ``None`` for none (see :func:`trajectory_energy`).
            Default ``-1``: the last (z of the KUKA tasks' ``[x, y, z]`` goals).
        w_potential: weight of the potential term (≥ 0). Default 1.
        w_kinetic: weight of the kinetic term (≥ 0). Default 1.
        mask_key: boolean valid-step mask ``[..., T]`` of padded episodes, used when present. Default
            ``("collector", "mask")`` (what ``split_trajectories`` writes for a collector's batch).

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> z = torch.tensor([0.0, 0.01, 0.02, 0.03, 0.04])
        >>> ag = torch.stack([torch.zeros(5), torch.zeros(5), z], -1)[None]  # one episode, T = 4
        >>> episode = TensorDict({"achieved_goal": ag[:, :-1], "next": {"achieved_goal": ag[:, 1:]}}, [1, 4])
        >>> EpisodeEnergy()(episode)["energy"]
        tensor([[0.4124, 0.4124, 0.4124, 0.4124]])
    """

    def __init__(
        self,
        dt: float = DEFAULT_DT,
        clip: float = DEFAULT_CLIP,
        *,
        achieved_goal_key: NestedKey = "achieved_goal",
        out_key: NestedKey = "energy",
        up_axis: int | None = -1,
        w_potential: float = 1.0,
        w_kinetic: float = 1.0,
        mask_key: NestedKey | None = DEFAULT_MASK_KEY,
    ) -> None:
        super().__init__(in_keys=[achieved_goal_key], out_keys=[out_key])
        trajectory_energy(torch.zeros(1, 1), dt, clip, w_potential=w_potential, w_kinetic=w_kinetic)  # validates
        if up_axis is not None and (isinstance(up_axis, bool) or not isinstance(up_axis, int)):
            raise ValueError(f"up_axis must be None (no height) or an integer axis of the goals, got {up_axis!r}")
        self.dt = dt
        self.clip = clip
        self.achieved_goal_key = achieved_goal_key
        self.out_key = out_key
        self.up_axis = up_axis
        self.w_potential = w_potential
        self.w_kinetic = w_kinetic
        self.mask_key = mask_key

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if tensordict.batch_dims < 1:
            raise ValueError(f"EpisodeEnergy needs episodes [..., T], got batch_size={tuple(tensordict.shape)}")
        key = self.achieved_goal_key
        next_key = ("next", *key) if isinstance(key, tuple) else ("next", key)
        achieved, achieved_next = tensordict.get(key), tensordict.get(next_key)
        lengths = episode_lengths(tensordict, self.mask_key, "EpisodeEnergy")
        if lengths is None:
            positions = torch.cat([achieved, achieved_next[..., -1:, :]], dim=-2)
        else:  # p_0 .. p_{L-1}, then the last valid step's next achieved goal, repeated over the padding
            steps, dim = achieved.shape[-2], achieved.shape[-1]
            last = (lengths - 1).clamp(min=0)[..., None, None].expand(*lengths.shape, 1, dim)
            sequence = torch.cat([achieved, achieved_next.gather(-2, last)], dim=-2)  # [..., T + 1, d]
            source = torch.arange(steps + 1, device=achieved.device).expand(*lengths.shape, steps + 1)
            source = torch.where(source < lengths.unsqueeze(-1), source, steps)
            positions = sequence.gather(-2, source.unsqueeze(-1).expand(*source.shape, dim))
        energy = trajectory_energy(
            positions, self.dt, self.clip, w_potential=self.w_potential, w_kinetic=self.w_kinetic, up_axis=self.up_axis
        )
        tensordict.set(self.out_key, energy.unsqueeze(-1).expand(tensordict.shape).clone())
        return tensordict

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        raise RuntimeError("EpisodeEnergy works on whole episodes: call it on a rollout, not inside a TransformedEnv")

    def __repr__(self) -> str:
        return (f"{type(self).__name__}(dt={self.dt}, clip={self.clip}, up_axis={self.up_axis}, "
                f"out_key={self.out_key!r})")
