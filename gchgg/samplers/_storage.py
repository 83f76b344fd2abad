"""Shared plumbing of the samplers: reading one field from a replay storage, per-row caches, the generator,
state files, one intra-op thread for ``sample``."""

from __future__ import annotations

import functools
import inspect
import json
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import NestedKey, is_tensor_collection
from torchrl.data.replay_buffers.storages import Storage, TensorStorage

_STATE_FILE = "sampler_state.json"


def one_thread(sample):
    """Run a sampler's ``sample`` on one torch intra-op thread, restoring the caller's count after.

    A sample's tensor work is many small operations; fanning them out over threads costs more than
    it gains, and on a machine whose cores are busy (two training runs on two cores) a waiting
    thread makes it several times slower (``benchmarks/samplers.py`` prints 1 against 2 threads).
    The count is the calling thread's (torch's OpenMP and MKL settings are per thread), so other
    threads, e.g. a training loop beside a prefetching buffer, keep theirs.
    """

    @functools.wraps(sample)
    def wrapper(*args, **kwargs):
        threads = torch.get_num_threads()
        if threads == 1:
            return sample(*args, **kwargs)
        torch.set_num_threads(1)
        try:
            return sample(*args, **kwargs)
        finally:
            torch.set_num_threads(threads)

    return wrapper


def check_sampleable(storage: Storage, sampler: object) -> int:
    """Number of stored rows; raises if the storage is empty or not one transition per row."""
    n = len(storage)
    if n == 0:
        raise RuntimeError(f"{type(sampler).__name__}: cannot sample from an empty storage; extend the buffer first")
    ndim = getattr(storage, "ndim", 1)
    if ndim != 1:
        raise ValueError(
            f"{type(sampler).__name__} samples transitions from a 1-D storage (e.g. LazyTensorStorage(max_size)), "
            f"got a storage with ndim={ndim}; store the flattened output of HindsightRelabel"
        )
    return n


def read_field(storage: Storage, key: NestedKey, index: torch.Tensor | None, sampler: object) -> torch.Tensor:
    """``storage[index][key]`` without gathering whole rows (all ``len(storage)`` rows when ``index`` is None)."""
    n = len(storage)
    # TorchRL's TensorStorage has no public way to read one field without gathering every key of the
    # rows: its underlying TensorDict (``_storage``) is read directly, the one private TorchRL
    # attribute the project touches (besides ``Sampler._rng``, which TorchRL sets on every sampler).
    if isinstance(storage, TensorStorage) and is_tensor_collection(storage._storage):
        values = storage._storage.get(key, None)
        if values is None:
            _missing(storage._storage, key, sampler)
        if index is None:
            return values[:n]
        index = torch.as_tensor(index)  # index_select: several times faster than values[index] for [A, K, B] indices
        return values.index_select(0, index.reshape(-1)).view(*index.shape, *values.shape[1:])
    data = storage.get(torch.arange(n) if index is None else index)  # generic storages: gathers rows
    if not is_tensor_collection(data) or data.get(key, None) is None:
        _missing(data, key, sampler)
    return data.get(key)


class WrittenRows:
    """Which stored rows a sampler's per-row cache must (re)compute: those written since it last caught up.

    The sampler calls :meth:`mark` from ``extend``/``add``/``mark_update`` with the written index,
    and :meth:`take` before it reads its cache. ``take(n, size)`` returns the rows below ``n`` (the
    storage's length) to recompute: rows rewritten since, and rows new to the storage; or ``None``
    when the whole cache must be built anew (nothing cached yet, ``size`` (the cache's rows) below
    ``n``, or a write given as something other than row indices, e.g. a slice).

    >>> rows = WrittenRows()
    >>> rows.take(4, size=10) is None  # the first time: build everything
    True
    >>> rows.mark(torch.tensor([1])); rows.current(6)
    False
    >>> rows.take(6, size=10).tolist()  # row 1 rewritten, rows 4 and 5 new
    [1, 4, 5]
    >>> rows.current(6)
    True
    """

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        """Forget everything: the next :meth:`take` asks for a full build."""
        self._known, self._pending, self._all = 0, [], True

    def mark(self, index) -> None:
        """Rows just written: a row index, an integer tensor or array of them, or anything else (all rows)."""
        if isinstance(index, (int, torch.Tensor, np.ndarray)) and not torch.as_tensor(index).is_floating_point():
            self._pending.append(torch.as_tensor(index).reshape(-1).long())
        else:
            self.reset()

    def current(self, n: int) -> bool:
        """Whether a cache that caught up at the last :meth:`take` holds every row of a storage of length ``n``."""
        return not self._all and not self._pending and n == self._known

    def take(self, n: int, size: int) -> torch.Tensor | None:
        """The rows to recompute now (``None``: all ``n``); afterwards the cache counts as current for ``n``."""
        full = self._all or size < n
        fresh = [] if full else [index[index < min(n, self._known)] for index in self._pending]
        if not full and n > self._known:
            fresh.append(torch.arange(self._known, n))
        self._known, self._pending, self._all = n, [], False
        if full:
            return None
        return torch.cat(fresh) if fresh else torch.empty(0, dtype=torch.long)


def init_signature(cls):
    """Class decorator: ``help(cls)`` and ``inspect.signature(cls)`` show ``__init__``'s parameters.

    TorchRL's samplers have a metaclass whose ``__call__(cls, *args, **kwargs)`` would otherwise be
    what they show.
    """
    signature = inspect.signature(cls.__init__)
    cls.__signature__ = signature.replace(parameters=list(signature.parameters.values())[1:])
    return cls


def _missing(data: Any, key: NestedKey, sampler: object):
    keys = sorted(map(str, data.keys(include_nested=True, leaves_only=True))) if is_tensor_collection(data) else []
    raise KeyError(
        f"{type(sampler).__name__} reads {key!r} from the replay storage, but the stored transitions have keys "
        f"{keys}; store it (HindsightRelabel writes 'desired_goal', 'episode_goal' and 'task_goal', "
        "EpisodeEnergy 'energy') "
        f"or pass the right key to the sampler"
    )


def generator(sampler) -> torch.Generator:
    """The buffer's generator (``sampler._rng``); outside a buffer a private, randomly seeded one (not global)."""
    if sampler._rng is None:
        rng = torch.Generator()
        rng.seed()
        sampler._rng = rng
    return sampler._rng


def dump_state(state: dict, path) -> None:
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    (path / _STATE_FILE).write_text(json.dumps(state, indent=1))


def load_state(path) -> dict:
    return json.loads((Path(path) / _STATE_FILE).read_text())
