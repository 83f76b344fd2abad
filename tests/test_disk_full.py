"""A full disk at any write site of a run stops it with one error naming the file; resumed, it gives identical metrics.

Each case injects ``OSError(ENOSPC)`` at one write of a tiny run: the atomic writer's file write
(:mod:`gchgg.common.files`: it writes half of its data to the temporary file, then fails, as a full
disk does) for the checkpoint, a replay file, ``metrics.csv``, the policy snapshot, the goal graph's
cache, ``config.yaml`` and ``trackers.json``; TensorBoard's ``add_scalar`` for the TensorBoard tracker.
(``logging.backend=csv`` writes ``metrics.csv`` alone: its case is ``metrics.csv``'s.) The run must
stop with :class:`gchgg.common.files.DiskFullError` naming the disk full and the file, leave no
temporary file and every file a resume reads whole; then, the injection gone, ``resume=true`` must
finish with the ``metrics.csv`` of a run never interrupted (timing columns aside).
"""

from __future__ import annotations

import csv
import errno
import os
import sys
import tempfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
from test_train import config, tiny  # noqa: E402

from gchgg import train  # noqa: E402
from gchgg.common import files  # noqa: E402
from gchgg.run import checkpoint, metrics  # noqa: E402

ITERATIONS = 3
TENSORBOARD = ["logging.backend=[csv,tensorboard]"]


def overrides(tmp_path: Path, extra: tuple[str, ...] | list[str] = ()) -> list[str]:
    return ["env=reach", "algo=gchgg", *tiny(tmp_path, iterations=ITERATIONS), "train.warmup_steps=100", *extra]


def rows(run_dir: Path) -> list[dict[str, str]]:
    with open(run_dir / "metrics.csv", newline="") as f:
        return [{k: v for k, v in row.items() if not k.startswith("seconds_")} for row in csv.DictReader(f)]


class FullDisk:
    """Stands in for ``os`` and ``tempfile`` in :mod:`gchgg.common.files`: the ``nth`` write of a file whose
    name matches ``name`` (its temporary file's) writes half its bytes, then raises ``ENOSPC``."""

    def __init__(self, name: str, nth: int = 1) -> None:
        self.name, self.nth, self.seen, self.fds = name, nth, 0, {}

    def __getattr__(self, attribute):  # everything else: the real os / tempfile
        return getattr(os, attribute) if hasattr(os, attribute) else getattr(tempfile, attribute)

    def mkstemp(self, *args, **kwargs):
        fd, tmp = tempfile.mkstemp(*args, **kwargs)
        self.fds[fd] = Path(tmp).name
        return fd, tmp

    def fdopen(self, fd, *args, **kwargs):
        f = os.fdopen(fd, *args, **kwargs)
        name = self.fds.pop(fd, "")
        if Path(name.removeprefix(".")).match(f"{self.name}.*.tmp"):
            self.seen += 1
            if self.seen == self.nth:
                return HalfWrite(f)
        return f


class HalfWrite:
    """A file whose first write puts half its data on disk, then finds the disk full."""

    def __init__(self, f) -> None:
        self.f = f

    def __getattr__(self, attribute):
        return getattr(self.f, attribute)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.f.close()

    def write(self, data) -> int:
        self.f.write(bytes(data)[: max(len(data) // 2, 1)])
        self.f.flush()
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    tmp_path = tmp_path_factory.mktemp("whole")
    train.run(config(overrides(tmp_path)), tmp_path / "run")
    return rows(tmp_path / "run")


def assert_nothing_partial(run_dir: Path) -> None:
    """No temporary file left, and every file a resume reads whole."""
    assert not [p for p in run_dir.rglob("*.tmp")], sorted(run_dir.rglob("*"))
    if (run_dir / "checkpoint.pt").exists():
        state = checkpoint.load(run_dir / "checkpoint.pt")  # checksummed: raises if truncated
        for name in state["replay"]:
            files.load(run_dir / "replay" / name)
    if (run_dir / "policy.pt").exists():
        files.load(run_dir / "policy.pt")
    if (run_dir / "metrics.csv").exists():
        rows(run_dir)


CASES = {  # case -> (file name pattern, which of its writes fails, extra overrides)
    "checkpoint": ("checkpoint.pt", 2, ()),
    "replay file": ("iteration-000001.pt", 1, ()),
    "metrics.csv": ("metrics.csv", 2, ()),
    "policy snapshot": ("policy.pt", 2, ()),
    "graph cache": ("goalgraph-*.bin", 1, ()),
    "config.yaml": ("config.yaml", 1, ()),
    "trackers.json": ("trackers.json", 2, TENSORBOARD),
}


@pytest.mark.parametrize("case", CASES)
def test_a_full_disk_at_a_write_stops_the_run_naming_the_file_and_resume_gives_identical_metrics(
    case, uninterrupted, tmp_path, monkeypatch
):
    name, nth, extra = CASES[case]
    if extra == TENSORBOARD:
        pytest.importorskip("tensorboard")
    run_dir = tmp_path / "run"
    full = FullDisk(name, nth)
    monkeypatch.setattr(files, "os", full)
    monkeypatch.setattr(files, "tempfile", full)
    with pytest.raises(files.DiskFullError) as raised:
        train.run(config(overrides(tmp_path, extra)), run_dir)
    assert full.seen == nth
    message = str(raised.value)
    assert message.startswith("disk full (No space left on device) while writing ") and "resume=true" in message
    assert Path(raised.value.filename).match(name) and raised.value.filename in message
    assert isinstance(raised.value.__cause__, OSError) and raised.value.__cause__.errno == errno.ENOSPC
    assert raised.value.errno == errno.ENOSPC
    assert_nothing_partial(run_dir)
    assert not list((tmp_path / "graphs").glob("*.tmp"))
    if case == "metrics.csv":  # the previous metrics.csv, whole
        assert rows(run_dir) == uninterrupted[:1]
    if case == "policy snapshot":  # the previous snapshot, whole
        assert files.load(run_dir / "policy.pt")["iteration"] == 1

    monkeypatch.undo()
    train.run(config(overrides(tmp_path, [*extra, "resume=true"])), run_dir)
    assert rows(run_dir) == uninterrupted


def test_a_full_disk_in_the_tensorboard_tracker_stops_the_run_naming_its_folder(uninterrupted, tmp_path, monkeypatch):
    pytest.importorskip("tensorboard")
    from torch.utils.tensorboard import SummaryWriter

    original = SummaryWriter.add_scalar

    def add_scalar(self, tag, value, global_step=None, *args, **kwargs):
        if global_step == 1:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return original(self, tag, value, global_step, *args, **kwargs)

    monkeypatch.setattr(SummaryWriter, "add_scalar", add_scalar)
    run_dir = tmp_path / "run"
    with pytest.raises(files.DiskFullError, match=r"^disk full .* the tensorboard tracker's records in .*tensorboard"):
        train.run(config(overrides(tmp_path, TENSORBOARD)), run_dir)
    assert_nothing_partial(run_dir)
    monkeypatch.undo()
    train.run(config(overrides(tmp_path, [*TENSORBOARD, "resume=true"])), run_dir)
    assert rows(run_dir) == uninterrupted


def test_a_disk_full_error_names_a_quota_and_other_errors_pass_unchanged(tmp_path):
    with pytest.raises(files.DiskFullError, match=r"^disk full \(Disk quota exceeded\) while writing .*metrics.csv"):
        with files.naming_disk_full(tmp_path / "metrics.csv"):
            raise OSError(errno.EDQUOT, os.strerror(errno.EDQUOT))
    with pytest.raises(PermissionError):
        with files.naming_disk_full(tmp_path / "metrics.csv"):
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES))
    metrics.write_csv([{"iteration": 0, "x": 1.0}], tmp_path / "metrics.csv")  # the atomic writer, no leftovers
    assert rows(tmp_path) == [{"iteration": "0", "x": "1.0"}] and os.listdir(tmp_path) == ["metrics.csv"]


def test_a_full_disk_when_the_run_folder_is_locked_names_the_lock_file(tmp_path, monkeypatch):
    from gchgg.run.lock import LOCK_FILE, RunLock

    def pwrite(fd, data, offset):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "pwrite", pwrite)
    with pytest.raises(files.DiskFullError, match=rf"^disk full .* the run folder's lock .*{LOCK_FILE}"):
        RunLock(tmp_path, heartbeat_s=0).acquire()
    monkeypatch.undo()
    with RunLock(tmp_path, heartbeat_s=0) as lock:  # space freed: taken
        assert lock.held
