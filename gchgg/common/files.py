"""Atomic, checksummed files: what a process killed at any moment leaves intact, and their verified reads.

A file is a small header (magic, SHA-256 of the payload, payload length) followed by a ``torch.save``
payload. :func:`save` writes to a temporary file in the same folder, flushes it to disk and renames it
over the old file, so a reader sees either the previous file or the new one, never a partial file.
:func:`load` verifies the header and the checksum and raises :class:`CorruptCheckpointError` when
anything does not match. Checkpoints, replay files and the goal graph's distance cache are such files.
"""

from __future__ import annotations

import hashlib
import io
import os
import struct
import tempfile
from pathlib import Path
from typing import Any

import torch

_MAGIC = b"GCHGGCK1"
_HEADER = struct.Struct("<8s32sQ")  # magic, sha256 digest, payload length


class CorruptCheckpointError(RuntimeError):
    """The checkpoint file is truncated, altered or not a gchgg checkpoint."""


def save(state: dict[str, Any], path: str | os.PathLike, *, mode: int | None = None) -> None:
    """Write ``state`` to ``path`` atomically (temporary file + fsync + rename); ``mode`` sets the
    file's permissions (default: the temporary file's 0600)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    buffer = io.BytesIO()
    torch.save(state, buffer)
    payload = buffer.getbuffer()
    header = _HEADER.pack(_MAGIC, hashlib.sha256(payload).digest(), len(payload))
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(header)
            f.write(payload)
            f.flush()
            os.fsync(f.fileno())
        if mode is not None:
            os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def remove_temporaries(folder: str | os.PathLike) -> list[Path]:
    """Delete the temporary files that saves killed before their rename left in ``folder`` (a SIGKILL
    runs no cleanup); returns them. Only files named as :func:`save` names its temporaries go."""
    folder = Path(folder)
    stale = sorted(folder.glob(".*.tmp")) if folder.is_dir() else []
    for path in stale:
        path.unlink(missing_ok=True)
    return stale


def load(path: str | os.PathLike) -> dict[str, Any]:
    """Read a checkpoint written by :func:`save`, verifying its checksum.

    Raises:
        FileNotFoundError: there is no file at ``path``.
        CorruptCheckpointError: the file is truncated, altered or not a gchgg checkpoint.
    """
    path = Path(path)
    data = path.read_bytes()
    if len(data) < _HEADER.size:
        raise CorruptCheckpointError(f"checkpoint {path} is corrupt: {len(data)} bytes, shorter than its header")
    magic, digest, length = _HEADER.unpack_from(data)
    payload = memoryview(data)[_HEADER.size :]
    if magic != _MAGIC:
        raise CorruptCheckpointError(f"checkpoint {path} is corrupt: not a gchgg checkpoint (bad magic {magic!r})")
    if len(payload) != length:
        raise CorruptCheckpointError(
            f"checkpoint {path} is corrupt: payload has {len(payload)} bytes, header says {length} (truncated?)"
        )
    if hashlib.sha256(payload).digest() != digest:
        raise CorruptCheckpointError(f"checkpoint {path} is corrupt: checksum mismatch")
    return torch.load(io.BytesIO(payload), weights_only=False)
