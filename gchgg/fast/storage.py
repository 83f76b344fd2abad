"""A TorchRL ``LazyTensorStorage`` that reads a sampled batch field by field: the same rows at a lower cost.

A ``TensorDictReplayBuffer`` reads a batch as ``storage.get(index)``, which indexes the stored
TensorDict through its general indexing path; for a batch of 256 transitions that costs more than
copying the rows. :class:`FieldStorage` answers a 1-D integer index of written rows with one
``index_select`` per stored field and builds the batch from them; any other index (slices, scalars,
masks, negative or out-of-range rows) takes TorchRL's path and its errors. The batch is the one
``LazyTensorStorage`` returns, field for field (``tests/test_storage.py``); ``python
benchmarks/samplers.py`` prints the cost of reading a batch with each.

Example:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
    >>> data = TensorDict({"observation": torch.randn(10, 5), "next": {"reward": -torch.ones(10, 1)}}, [10])
    >>> def buffer(storage):
    ...     return TensorDictReplayBuffer(storage=storage, batch_size=4, generator=torch.Generator().manual_seed(0))
    >>> fast, plain = buffer(FieldStorage(100)), buffer(LazyTensorStorage(100))
    >>> _, _ = fast.extend(data), plain.extend(data)
    >>> bool((fast.sample() == plain.sample()).all())
    True
"""

from __future__ import annotations

import torch
from tensordict import NestedKey, TensorDict, is_tensor_collection
from torchrl.data import LazyTensorStorage

__all__ = ["FieldStorage"]


class FieldStorage(LazyTensorStorage):
    """``LazyTensorStorage(max_size, **kwargs)`` whose batch reads gather field by field.

    Writing, the samplers' reads of single fields, ``len``, state dicts and checkpoints are
    ``LazyTensorStorage``'s; a state dict of one loads into the other.
    """

    def get(self, index):
        data = self._storage
        if not (isinstance(index, torch.Tensor) and index.ndim == 1 and index.dtype in (torch.int64, torch.int32)
                and self.initialized and is_tensor_collection(data)):  # fmt: skip
            return super().get(index)
        if index.numel():
            low, high = torch.aminmax(index)
            if low < 0 or high >= len(self):  # TorchRL's path: its error, or its negative-index rule
                return super().get(index)
        return TensorDict({key: data.get(key).index_select(0, index) for key in self._keys(data)},
                          batch_size=index.shape)  # fmt: skip

    def _keys(self, data) -> list[NestedKey]:
        """The stored leaf keys, listed once per stored TensorDict (listing them costs more than a batch's copies)."""
        if getattr(self, "_stored", (None,))[0] is not data:
            self._stored = (data, list(data.keys(include_nested=True, leaves_only=True)))
        return self._stored[1]
