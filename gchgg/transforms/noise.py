"""Observation noise as a TorchRL env transform: a camera's error on the observed object position.

:class:`ObservationNoise` adds one draw ε ~ N(0, σ²·I₃) per env and per step to every chosen
3-vector slice of the observation (by default the object position and the object-relative
position, so that ``relative = object − grip`` stays true of what the policy sees) and to the
achieved goal where the task's goal is the object. The env computes its reward and ``is_success``
from the true state before the transform runs, and the clean achieved goal is kept under
``true_achieved_goal``, so anything that must be true to physics (HER's rewards, EBP's energy,
HGG's trajectory pool) can read it.

The slices come from a named layout (:func:`envs.observation_layout`), e.g.
``[layout["object_position"], layout["object_relative"]]``; :func:`object_noise` builds the
transform for a KUKA task.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import NestedKey, TensorDictBase
from torchrl.envs.transforms import Transform

from gchgg.common.validation import check_number

__all__ = ["ObservationNoise"]


class ObservationNoise(Transform):
    """Gaussian noise on chosen position slices of the observation and on the achieved goal.

    Every slice receives the *same* draw ε ``[..., 3]`` (one per env and step), as does the
    achieved goal when ``achieved_goal_key`` is given; the clean achieved goal is written to
    ``true_achieved_goal_key`` first. Applied to reset and step outputs of a TorchRL env; nothing
    else (reward, ``is_success``, ``desired_goal``) is touched.

    Args:
        std: σ in metres (>= 0; 0 adds nothing but still writes the true achieved goal).
        slices: slices of length 3 of the last dimension of ``observation_key``.

    Keyword Args:
        generator: ``torch.Generator`` of the draws; by default a fresh, randomly seeded one.
        observation_key: the observation entry. Default ``"observation"``.
        achieved_goal_key: the achieved goal to noise with the same ε, or ``None`` to leave it.
            Default ``"achieved_goal"``.
        true_achieved_goal_key: where the clean achieved goal is kept, or ``None``. Default
            ``"true_achieved_goal"``.

    Example:
        >>> from tensordict import TensorDict
        >>> noise = ObservationNoise(0.01, [slice(3, 6), slice(6, 9)], generator=torch.Generator().manual_seed(0))
        >>> obs = torch.arange(12.0).expand(4, 12)
        >>> out = noise(TensorDict({"observation": obs.clone(), "achieved_goal": obs[:, 3:6].clone()}, [4]))
        >>> eps = out["observation"][:, 3:6] - obs[:, 3:6]
        >>> (torch.allclose(out["observation"][:, 6:9] - obs[:, 6:9], eps, atol=1e-6),
        ...  torch.equal(out["observation"][:, :3], obs[:, :3]))
        (True, True)
        >>> torch.allclose(out["achieved_goal"] - out["true_achieved_goal"], eps, atol=1e-6)
        True
    """

    def __init__(
        self,
        std: float,
        slices: Sequence[slice],
        *,
        generator: torch.Generator | None = None,
        observation_key: NestedKey = "observation",
        achieved_goal_key: NestedKey | None = "achieved_goal",
        true_achieved_goal_key: NestedKey | None = "true_achieved_goal",
    ) -> None:
        check_number("noise std (metres)", std, low=0)
        slices = tuple(slices)
        for s in slices:
            if not isinstance(s, slice) or s.step not in (None, 1) or s.start is None or s.stop - s.start != 3:
                raise ValueError("every noised slice must be a position slice of length 3 (e.g. slice(3, 6)), "
                                 f"got {s!r}")
        in_keys = [observation_key] + ([achieved_goal_key] if achieved_goal_key is not None else [])
        out_keys = in_keys + (
            [true_achieved_goal_key] if achieved_goal_key is not None and true_achieved_goal_key else []
        )
        super().__init__(in_keys=in_keys, out_keys=out_keys)
        self.std = float(std)
        self.slices = slices
        if generator is None:
            generator = torch.Generator()
            generator.seed()
        self.generator = generator
        self.observation_key = observation_key
        self.achieved_goal_key = achieved_goal_key
        self.true_achieved_goal_key = true_achieved_goal_key

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        observation = next_tensordict.get(self.observation_key)
        eps = torch.randn((*observation.shape[:-1], 3), generator=self.generator,
                          dtype=observation.dtype).mul_(self.std)
        noisy = observation.clone()
        for s in self.slices:
            noisy[..., s] += eps
        next_tensordict.set(self.observation_key, noisy)
        if self.achieved_goal_key is not None:
            achieved = next_tensordict.get(self.achieved_goal_key)
            if self.true_achieved_goal_key:
                next_tensordict.set(self.true_achieved_goal_key, achieved.clone())
            next_tensordict.set(self.achieved_goal_key, achieved + eps.to(achieved.dtype))
        return next_tensordict

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Noise a TensorDict directly (outside an env), in place, e.g. ``noise(rollout)``."""
        return self._call(tensordict)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._call(tensordict_reset)

    def transform_observation_spec(self, observation_spec):
        if self.achieved_goal_key is not None and self.true_achieved_goal_key:
            observation_spec[self.true_achieved_goal_key] = observation_spec[self.achieved_goal_key].clone()
        return observation_spec

    def __repr__(self) -> str:
        return (f"{type(self).__name__}(std={self.std}, slices={list(self.slices)}, "
                f"achieved_goal_key={self.achieved_goal_key!r})")
