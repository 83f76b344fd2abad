"""Energy-based prioritisation (EBP): draws stored transitions with probability ∝ their episode's energy."""

from __future__ import annotations

import math
from collections import OrderedDict
from typing import Any

import torch
from tensordict import NestedKey
from torchrl.data.replay_buffers.samplers import Sampler
from torchrl.data.replay_buffers.storages import Storage

from gchgg.samplers._storage import check_sampleable, dump_state, generator, load_state, read_field

__all__ = ["EnergySampler"]


class EnergySampler(Sampler):
    """Draws transitions with probability proportional to the energy stored beside them (EBP).

    Every stored transition carries its episode's trajectory energy (see
    :class:`gchgg.transforms.EpisodeEnergy`), and every episode stores the same number of
    transitions ((k+1)·T after :class:`~gchgg.transforms.HindsightRelabel`), so drawing rows in
    proportion to ``energy`` draws episodes in proportion to their energy and then a transition
    uniformly within the episode, as the original EBP buffer does. A batch's indices come in
    ascending order (the draws are i.i.d.; sorting them makes the lookups cache-friendly).

    Cost: consecutive rows of equal energy (an episode's copies) are merged into runs; the runs'
    cumulative energies are cached and rebuilt (O(n)) on the first ``sample`` after the buffer
    writes (``extend``/``add``); each draw is then a binary search over the runs, O(B log runs).
    Works before the storage is full (only the first ``len(storage)`` rows) and after it wraps.

    Args:
        energy_key: stored entry holding the energy (one value per transition, ≥ 0). Default ``"energy"``.
        epsilon: added to every energy (≥ 0), giving zero-energy episodes a chance. Default 0: as in
            the original, they are never drawn while some episode has energy; if all energies are 0
            the draw is uniform.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
        >>> buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(100), sampler=EnergySampler(),
        ...                                 batch_size=1000, generator=torch.Generator().manual_seed(0))
        >>> _ = buffer.extend(TensorDict({"energy": torch.tensor([0.0, 1.0, 3.0])}, [3]))
        >>> buffer.sample()["index"].bincount(minlength=3).tolist()  # about 0 : 250 : 750
        [0, 254, 746]
    """

    def __init__(self, energy_key: NestedKey = "energy", epsilon: float = 0.0) -> None:
        if not (isinstance(epsilon, (int, float)) and math.isfinite(epsilon) and epsilon >= 0):
            raise ValueError(f"epsilon must be a finite number >= 0, got {epsilon!r}")
        self.energy_key = energy_key
        self.epsilon = float(epsilon)
        self._cache: tuple[torch.Tensor, torch.Tensor, int] | None = None  # see _runs

    def sample(self, storage: Storage, batch_size: int) -> tuple[torch.Tensor, dict]:
        return self.draw(storage, batch_size), {}

    def draw(self, storage: Storage, *shape: int) -> torch.Tensor:
        """Row indices of the given shape drawn with probability ∝ energy (with replacement).

        Each row of the last dimension comes sorted (ascending storage index): the draws are
        i.i.d., only their order is fixed, which keeps the lookups cache-friendly.
        """
        n = check_sampleable(storage, self)
        rng = generator(self)
        cdf, runs = self._runs(storage, n)
        total = cdf[-1]
        if total <= 0:  # no episode has energy yet: uniform
            return torch.randint(n, shape, generator=rng).sort(-1).values
        u = torch.rand(shape, dtype=torch.float64, generator=rng).mul_(total)
        # The run whose cumulative energy first exceeds u (zero-energy runs are never chosen), then
        # a row of that run by where u falls inside it: uniform, as the run's rows weigh the same.
        run = torch.searchsorted(cdf, u, right=True).clamp_(max=len(cdf) - 1)
        below, weight, start, length = runs.index_select(0, run.view(-1)).view(*shape, 4).unbind(-1)
        within = torch.minimum(u.sub_(below).div_(weight).mul_(length).clamp_(min=0), length - 1, out=u)
        return start.add_(within).long().sort(-1).values

    def _runs(self, storage: Storage, n: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Runs of equal consecutive energies (an episode's (k+1)·T rows): the cumulative weights ``[R]``
        and, per run, ``(weight before it, its weight, first row, length)`` as float64 ``[R, 4]``.

        Searching ~one entry per episode instead of one per transition keeps the table small and
        in cache (2.5 M rows of 5,000 episodes: 5,000 runs).
        """
        if self._cache is None or self._cache[2] != n:
            energy = read_field(storage, self.energy_key, None, self).reshape(n, -1)
            if energy.shape[1] != 1:
                raise ValueError(
                    f"{self.energy_key!r} must hold one energy per transition, got {energy.shape[1]} values per row"
                )
            energy = energy[:, 0].to(torch.float64)
            if not torch.isfinite(energy).all() or (energy < 0).any():
                raise ValueError(f"energies under {self.energy_key!r} must be finite and >= 0")
            change = torch.ones(n, dtype=torch.bool)
            change[1:] = energy[1:] != energy[:-1]
            start = change.nonzero().squeeze(-1)
            length = torch.diff(start, append=torch.tensor([n]))
            weight = (energy[start] + self.epsilon) * length
            cdf = weight.cumsum(0)
            runs = torch.stack([cdf - weight, weight.clamp(min=1e-300), start.double(), length.double()], -1)
            self._cache = (cdf, runs, n)
        return self._cache[0], self._cache[1]

    # Writes invalidate the cached cumulative energies.
    def extend(self, index: torch.Tensor) -> None:
        self._cache = None

    def add(self, index: int) -> None:
        self._cache = None

    def mark_update(self, index, *, storage: Storage | None = None) -> None:
        self._cache = None

    def _empty(self) -> None:
        self._cache = None

    def state_dict(self) -> dict[str, Any]:
        return OrderedDict(energy_key=self.energy_key, epsilon=self.epsilon)

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        key = state_dict["energy_key"]
        self.energy_key = tuple(key) if isinstance(key, list) else key
        self.epsilon = float(state_dict["epsilon"])
        self._cache = None

    def dumps(self, path) -> None:
        dump_state(self.state_dict(), path)

    def loads(self, path) -> None:
        self.load_state_dict(load_state(path))

    def __repr__(self) -> str:
        return f"{type(self).__name__}(energy_key={self.energy_key!r}, epsilon={self.epsilon})"

