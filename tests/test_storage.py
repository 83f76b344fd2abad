"""Tests of gchgg.fast.storage.FieldStorage: the batches TorchRL's LazyTensorStorage gives, read field by field."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, RandomSampler, TensorDictReplayBuffer

from gchgg.fast.storage import FieldStorage


def rows(n: int, seed: int = 0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    return TensorDict(
        {
            "observation": torch.randn(n, 5, generator=g),
            "desired_goal": torch.randn(n, 3, generator=g),
            "action": torch.rand(n, 2, generator=g),
            "energy": torch.rand(n, generator=g),
            "next": {"observation": torch.randn(n, 5, generator=g), "reward": -torch.ones(n, 1),
                     "done": torch.rand(n, 1, generator=g) < 0.1},
        },
        [n],
    )


def buffer_of(storage, seed: int = 1) -> TensorDictReplayBuffer:
    buffer = TensorDictReplayBuffer(storage=storage, sampler=RandomSampler(), batch_size=32,
                                    generator=torch.Generator().manual_seed(seed))  # fmt: skip
    buffer.extend(rows(150))
    return buffer


def leaves(td: TensorDict) -> dict:
    return {key: td.get(key) for key in td.keys(include_nested=True, leaves_only=True)}


def test_batches_equal_lazy_tensor_storage_ones_before_and_after_the_buffer_wraps():
    reference, fields = buffer_of(LazyTensorStorage(200)), buffer_of(FieldStorage(200))
    for step in range(6):
        a, b = leaves(reference.sample()), leaves(fields.sample())
        assert a.keys() == b.keys()
        for key in a:
            assert torch.equal(a[key], b[key]) and a[key].dtype == b[key].dtype, (step, key)
        for buffer in (reference, fields):  # 150 + 40·k rows into 200: the FIFO wraps
            buffer.extend(rows(40, seed=10 + step))


def test_indices_outside_the_written_rows_take_torchrls_path():
    storage, reference = FieldStorage(200), LazyTensorStorage(200)
    for s in (storage, reference):
        s.set(torch.arange(150), rows(150))
    last = storage.get(torch.tensor([-1, 0]))
    assert torch.equal(last["observation"], reference.get(torch.tensor([-1, 0]))["observation"])
    with pytest.raises(IndexError):
        storage.get(torch.tensor([3, 150]))


def test_a_lazy_tensor_storage_state_loads_into_a_field_storage():
    reference = buffer_of(LazyTensorStorage(200))
    storage = FieldStorage(200)
    storage.load_state_dict(reference.storage.state_dict())
    index = torch.tensor([0, 77, 149])
    expected, got = leaves(reference.storage.get(index)), leaves(storage.get(index))
    assert all(torch.equal(expected[k], got[k]) for k in expected)
