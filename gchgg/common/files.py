"""Atomic, checksummed files: what a process killed at any moment leaves intact, and their verified reads.

A file is a small header (magic, SHA-256 of the payload, payload length) followed by a ``torch.save``
payload. :func:`save` writes to a temporary file in the same folder, flushes it to disk and renames it
over the old file, so a reader sees either the previous file or the new one, never a partial file.
:func:`load` verifies the header and the checksum and raises :class:`CorruptCheckpointError` when
anything does not match. Checkpoints, replay files and the goal graph's distance cache are such files;
:func:`write_text` writes a text file (``metrics.csv``, ``config.yaml``, ``trackers.json``) the same way.

A write that fails because the disk is full (``ENOSPC``, or ``EDQUOT``: the user's quota) raises
:class:`DiskFullError`, which names the file and is raised from the original error; the temporary
file is removed first, so the previous file stays whole and a later ``resume=true`` reads it.
:func:`naming_disk_full` turns such an error of any other write into a :class:`DiskFullError`.
"""

from __future__ import annotations

import contextlib
import errno
import functools
import hashlib
import io
import os
import struct
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch

_MAGIC = b"GCHGGCK1"
_HEADER = struct.Struct("<8s32sQ")  # magic, sha256 digest, payload length


DISK_FULL = (errno.ENOSPC, errno.EDQUOT)
"""The errors of a write that found no room: the disk (or file system) full, the user's quota exceeded."""


class CorruptCheckpointError(RuntimeError):
    """The checkpoint file is truncated, altered or not a gchgg checkpoint."""


class DiskFullError(OSError):
    """A write found the disk full (``ENOSPC``) or the quota exceeded (``EDQUOT``); names the file (``filename``)
    and what it is; raised from the original error. The run stops: nothing of it is left half-written."""

    def __init__(self, path: str | os.PathLike, error: BaseException, what: str | None = None) -> None:
        code = _disk_full_errno(error) or errno.ENOSPC
        super().__init__(code, os.strerror(code))
        self.filename = str(path)
        self.message = (
            f"disk full ({os.strerror(code)}) while writing {what + ' ' if what else ''}{path}: the run stopped. "
            f"Nothing half-written is left where a resume reads (the file is replaced whole or not at all); "
            f"free space on that disk (or raise the quota) and continue with resume=true"
        )

    def __str__(self) -> str:
        return self.message


def _disk_full_errno(error: BaseException | None) -> int | None:
    """``ENOSPC``/``EDQUOT`` if ``error``, or an error it was raised from or during, is a full disk (SQLite's
    ``database or disk is full``, as MLflow's local store raises it, counts as ``ENOSPC``); else ``None``."""
    seen = set()
    while error is not None and id(error) not in seen:
        seen.add(id(error))
        if isinstance(error, OSError) and error.errno in DISK_FULL:
            return error.errno
        if "database or disk is full" in str(error):
            return errno.ENOSPC
        error = error.__cause__ or error.__context__
    return None


def is_disk_full(error: BaseException) -> bool:
    """Whether ``error`` (or one it was raised from or during) is a write that found the disk full."""
    return _disk_full_errno(error) is not None


@contextlib.contextmanager
def naming_disk_full(path: str | os.PathLike, what: str | None = None) -> Iterator[None]:
    """Turns a full disk's error inside the block into a :class:`DiskFullError` naming ``path`` (``what``: the
    file in words, e.g. ``"the TensorBoard logs in"``); other errors pass unchanged."""
    try:
        yield
    except DiskFullError:
        raise
    except Exception as error:
        if is_disk_full(error):
            raise DiskFullError(path, error, what) from error
        raise


@functools.cache
def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _write_atomic(path: Path, chunks: tuple[bytes | memoryview, ...], mode: int | None) -> None:
    """``chunks`` into ``path`` atomically: a temporary file beside it (named as :func:`remove_temporaries`
    finds it), fsync, rename; the temporary file removed on any failure, a full disk raised as
    :class:`DiskFullError`."""
    with naming_disk_full(path):
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        try:
            with os.fdopen(fd, "wb") as f:
                for chunk in chunks:
                    f.write(chunk)
                f.flush()
                os.fsync(f.fileno())
            if mode is not None:
                os.chmod(tmp, mode)
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise


def save(state: dict[str, Any], path: str | os.PathLike, *, mode: int | None = None) -> None:
    """Write ``state`` to ``path`` atomically (temporary file + fsync + rename); ``mode`` sets the
    file's permissions (default: the temporary file's 0600).

    Raises:
        DiskFullError: the disk is full (or the quota exceeded); ``path`` is as it was before.
    """
    path = Path(path)
    buffer = io.BytesIO()
    torch.save(state, buffer)
    payload = buffer.getbuffer()
    header = _HEADER.pack(_MAGIC, hashlib.sha256(payload).digest(), len(payload))
    _write_atomic(path, (header, payload), mode)


def write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically, as :func:`save` writes, with the permissions a plain
    ``open(path, "w")`` gives (0666 less the umask).

    Raises:
        DiskFullError: the disk is full (or the quota exceeded); ``path`` is as it was before.
    """
    _write_atomic(Path(path), (text.encode("utf-8"),), 0o666 & ~_umask())


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
