"""Shared plumbing of the samplers: reading and checking one field of a replay storage, the generator, state
files, one intra-op thread for ``sample`` (their per-row caches' bookkeeping is :mod:`gchgg.fast.rows`)."""

from __future__ import annotations

import functools
import inspect
import json
from pathlib import Path
from typing import Any

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


def check_goal_rows(goals: torch.Tensor, key: NestedKey, sampler: object, dim: int | None = None, like: str = ""):
    """Stored goals ``[N, d]`` read under ``key``, checked: one vector of d >= 1 values per row (``dim`` of
    them, as ``like`` has, when given); a ``ValueError`` naming the sampler, the key and the shape otherwise."""
    if goals.ndim != 2 or goals.shape[1] < 1 or (dim is not None and goals.shape[1] != dim):
        allowed = f"[{dim}] like {like}" if dim is not None else "[d] with d >= 1 (a 1-D goal is stored as [1])"
        raise ValueError(
            f"{type(sampler).__name__} reads goals {key!r} from the storage as one vector per transition, "
            f"{allowed}; got {tuple(goals.shape[1:])} per transition"
        )
    return goals


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
