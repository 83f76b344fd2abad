"""The replay buffer's rows on disk as they are written: one checksummed file per iteration, and their restore.

An incremental checkpoint stores the replay data once. Every ``buffer.extend`` of an iteration is
recorded (the row indices the writer chose and the rows); at a checkpoint, :meth:`ReplayLog.flush`
writes each recorded iteration to ``<folder>/iteration-<k>.pt`` (atomic and checksummed, by
:func:`gchgg.common.files.save`), the checkpoint itself then holds only :meth:`ReplayLog.manifest` (the
files that still hold live rows, oldest first), and :meth:`ReplayLog.prune` deletes the files whose
every row a later file has overwritten. :meth:`ReplayLog.restore` writes the listed files' rows back
into an empty storage at their indices, oldest first, which rebuilds the stored rows exactly as they
were (for any writer: each row ends with the last value written to it). The ``index`` entry a
TorchRL buffer adds to the rows it stores is not recorded: a sampled batch gets its indices from
the sampler.

A run killed at any moment resumes from its last checkpoint: files written after it are not in its
manifest and are written again (with the same rows) by the repeated iterations; files a checkpoint
lists are deleted only after a later checkpoint that no longer needs them has been written. A listed
file that is missing, truncated or altered is an error naming it, never used.

Bytes written per iteration: that iteration's new rows, once.

Files written before the goals were renamed (December 2026) hold the goal an episode was collected
for as ``target_goal``; :func:`read` gives it its name now, ``episode_goal`` (:data:`RENAMED`), so
runs and forks started before the rename resume, and scripts reading replay files see one name.
"""

from __future__ import annotations

from pathlib import Path

import torch
from tensordict import TensorDictBase
from torchrl.data.replay_buffers.storages import Storage

from gchgg.common import files

__all__ = ["RENAMED", "ReplayLog", "read"]

_PATTERN = "iteration-{:06d}.pt"
RENAMED = {"target_goal": "episode_goal"}  # stored key in older replay files -> its name now


def read(path: Path) -> dict:
    """A replay file's ``{"iteration", "index", "rows"}``, its rows under today's key names (:data:`RENAMED`).

    Raises:
        gchgg.run.files.CorruptCheckpointError: the file is truncated, altered or not a replay file.
    """
    saved = files.load(path)
    rows = saved["rows"]
    for old, new in RENAMED.items():
        if old in rows.keys():
            rows.rename_key_(old, new)
    return saved


class ReplayLog:
    """Per-iteration replay files in ``folder`` (created when first written).

    Args:
        folder: where the files go (the run folder's ``replay/``).
        capacity: rows of the storage the files fill (superseded files are found for any writer, but
            at most ``capacity`` rows can be live).
    """

    def __init__(self, folder: str | Path, capacity: int) -> None:
        self.folder = Path(folder)
        self.capacity = int(capacity)
        self._pending: dict[int, list[tuple[torch.Tensor, TensorDictBase]]] = {}
        self._files: list[tuple[str, torch.Tensor]] = []  # written and listed: (name, row indices), oldest first

    def record(self, iteration: int, index: torch.Tensor, rows: TensorDictBase) -> None:
        """Remember rows an ``extend`` of ``iteration`` wrote at ``index`` (kept in memory until :meth:`flush`)."""
        index = torch.as_tensor(index).reshape(-1)
        if len(index) != rows.numel():
            raise ValueError(f"replay log: {len(index)} indices for {rows.numel()} rows")
        self._pending.setdefault(int(iteration), []).append((index.clone(), rows.reshape(-1).clone()))

    def flush(self) -> None:
        """Write every recorded iteration to its file; they join the manifest."""
        for iteration in sorted(self._pending):
            parts = self._pending[iteration]
            index = torch.cat([i for i, _ in parts])
            rows = torch.cat([r for _, r in parts]) if len(parts) > 1 else parts[0][1]
            name = _PATTERN.format(iteration)
            files.save({"iteration": iteration, "index": index, "rows": rows}, self.folder / name, mode=0o644)
            self._files = [(n, i) for n, i in self._files if n != name] + [(name, index)]
        self._pending.clear()

    def manifest(self) -> list[str]:
        """The files that hold live rows, oldest first (what a checkpoint stores)."""
        return [name for name, _ in self._live()]

    def prune(self) -> None:
        """Forget the files whose rows have all been overwritten, and delete every file of the folder
        that the manifest does not list (superseded ones, and leftovers of a killed run)."""
        self._files = self._live()
        keep = {name for name, _ in self._files}
        if self.folder.is_dir():
            for path in self.folder.glob("iteration-*.pt"):
                if path.name not in keep:
                    path.unlink(missing_ok=True)

    def restore(self, manifest: list[str], storage: Storage) -> None:
        """Write the rows of the files ``manifest`` lists into ``storage`` (empty), oldest first.

        Raises:
            FileNotFoundError: a listed file is missing (named).
            gchgg.run.files.CorruptCheckpointError: a listed file is truncated or altered (named).
        """
        self._files, self._pending = [], {}
        for name in manifest:
            path = self.folder / name
            if not path.is_file():
                raise FileNotFoundError(
                    f"replay file {path} is missing: the checkpoint lists it as holding rows of the replay "
                    f"buffer; the run cannot resume exactly without it"
                )
            saved = read(path)
            storage.set(saved["index"], saved["rows"])
            self._files.append((name, saved["index"]))

    def _live(self) -> list[tuple[str, torch.Tensor]]:
        """Listed files with at least one row no later file overwrote, oldest first."""
        written = torch.zeros(self.capacity, dtype=torch.bool)
        live = []
        for name, index in reversed(self._files):
            if not bool(written[index].all()):
                live.append((name, index))
            written[index] = True
        return live[::-1]
