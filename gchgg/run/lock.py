"""The run-folder lock: one live process per run folder, taken before the run reads or writes anything there.

:func:`gchgg.train.run` holds :class:`RunLock` on its folder for the run's life. A second process that
opens the folder while the run lives (the same command launched twice, a requeued job that starts while
the old one still runs) is refused at once with :class:`RunFolderLocked`, which names the folder and the
holder's pid, host, start time and command. A lock left by a process that is gone (SIGKILL, the OOM
killer, a lost machine) is taken over, with a warning in the log naming whose lock it took over. A fork
(``init_from``) only reads its source's files and takes no lock there, so it works while the source
trains; each job of a sweep has its own folder, hence its own lock.

**What it relies on.** ``fcntl.flock(LOCK_EX | LOCK_NB)`` on ``<run folder>/run.lock``, opened read-write
and held open for the run's life. The kernel drops a flock when the last descriptor of its open file
goes, however the process ends (exit, exception, Ctrl-C, SIGTERM, SIGKILL), so a killed run never
leaves a live lock; the descriptor is not inherited by the processes a run starts (Python opens it
non-inheritable, the evaluator is spawned). The file itself is never removed: removing it would let a
process that opened the old file lock it beside a newcomer that created a new one. The file also holds
a small JSON record (pid, host, start time, command, heartbeat, SLURM job id and restart count): the
error message and the takeover line read it, and so does the rule across hosts below. A run that ends
normally, by an exception or by Ctrl-C empties the file as it lets go, so a record found by a process
that got the flock is a run that did not end that way: its lock is taken over, and the log says so.

**Across hosts (NFS, Lustre, GPFS, BeeGFS).** A Linux NFS client emulates flock with a whole-file POSIX
lock that the server arbitrates between hosts (NFSv4, or NLM under v3), unless the file system is mounted
``nolock`` or ``local_lock=flock|all``: then each host sees only its own locks. Lustre arbitrates flock
between nodes when mounted ``-o flock``, keeps it per node with ``localflock`` and fails it (``ENOSYS``)
with ``noflock``; GPFS arbitrates between nodes; BeeGFS only with ``tuneUseGlobalFileLocks``. So getting
the flock proves only that no process *of this host* holds the folder, and the record decides for
another host's: while the holder lives, a daemon thread rewrites its heartbeat every :data:`HEARTBEAT_S`
seconds, and a record of another host is taken as live until its heartbeat is :data:`STALE_AFTER_S`
old (10 minutes; a lost machine's folder is taken over after that). Only then is it taken over, except
by the same SLURM job requeued (same ``SLURM_JOB_ID``, a higher ``SLURM_RESTART_COUNT``), which takes
over at once: SLURM never runs two instances of one job. Where flock fails (``ENOSYS``, ``EOPNOTSUPP``,
``ENOLCK``) the record alone decides, with a warning: a record of this host is live while its pid
exists, another host's by the heartbeat.

**Not protected**: two hosts that start on one folder in the same moment on a file system whose flock
is per host or absent (each finds no live record: the record is read, then written, not in one atomic
step); and a run stopped (SIGSTOP, a suspended job) for longer than :data:`STALE_AFTER_S` while a
process of another host takes its folder. Heartbeats compare wall clocks of two hosts, which a cluster
keeps within seconds of each other (NTP); 10 minutes leaves room for that.
"""

from __future__ import annotations

import errno
import fcntl
import json
import logging
import os
import shlex
import socket
import sys
import threading
import time
from datetime import datetime
from pathlib import Path
from typing import Any

from gchgg.common import files

__all__ = ["HEARTBEAT_S", "LOCK_FILE", "STALE_AFTER_S", "RunFolderLocked", "RunLock"]

log = logging.getLogger(__name__)

LOCK_FILE = "run.lock"
HEARTBEAT_S = 60.0
"""Seconds between two rewrites of the holder's heartbeat."""
STALE_AFTER_S = 600.0
"""A record of another host whose heartbeat is this old (seconds) is a run that is gone."""
_NO_FLOCK = (errno.ENOSYS, errno.EOPNOTSUPP, errno.ENOTSUP, errno.ENOLCK, errno.EINVAL)
"""flock's errors on a file system that does not support it (Lustre ``noflock``, some NFS mounts)."""


class RunFolderLocked(RuntimeError):
    """Another live process holds the run folder."""


def _now() -> float:
    return time.time()


def _slurm() -> tuple[str | None, int]:
    """This process's SLURM job id (None outside SLURM) and restart count."""
    try:
        restart = int(os.environ.get("SLURM_RESTART_COUNT", "0") or 0)
    except ValueError:
        restart = 0
    return os.environ.get("SLURM_JOB_ID") or None, restart


def _number(value: Any) -> float:
    """A record's number (0 where it is missing or not a number)."""
    try:
        return float(value or 0)
    except (TypeError, ValueError):
        return 0.0


def _pid_exists(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def describe(record: dict[str, Any] | None) -> str:
    """The holder in words: ``pid P on host H (started T, command C)``."""
    if record is None:
        return "a process that has not written its record yet"
    if not record:
        return "a process whose record is unreadable"
    return (f"pid {record.get('pid', '?')} on host {record.get('host', '?')} (started {record.get('started', '?')}, "
            f"command: {record.get('command', '?')})")


class RunLock:
    """The lock of one run folder: :meth:`acquire` (or ``with``) takes it, :meth:`release` lets it go.

    Args:
        folder: the run folder (it must exist).
        heartbeat_s: seconds between two rewrites of the heartbeat (default :data:`HEARTBEAT_S`).
        stale_after_s: age of another host's heartbeat at which its run counts as gone (default
            :data:`STALE_AFTER_S`).
    """

    def __init__(self, folder: str | os.PathLike, *, heartbeat_s: float | None = None,
                 stale_after_s: float | None = None) -> None:
        self.folder = Path(folder).absolute()
        self.path = self.folder / LOCK_FILE
        self.heartbeat_s = HEARTBEAT_S if heartbeat_s is None else heartbeat_s
        self.stale_after_s = STALE_AFTER_S if stale_after_s is None else stale_after_s
        self.taken_over: dict[str, Any] | None = None  # the record of the gone holder, when acquire took over
        self.flock = True  # False where the file system refused flock: the record alone decides
        self._fd: int | None = None
        self._record: dict[str, Any] = {}
        self._size = 0
        self._write_lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def __enter__(self) -> RunLock:
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()

    def acquire(self) -> RunLock:
        """Takes the folder's lock, or raises :class:`RunFolderLocked` at once if a live process holds it."""
        if self._fd is not None:
            raise RuntimeError(f"{self.path}: this lock is already held")
        self.taken_over, self.flock, self._size = None, True, 0
        with files.naming_disk_full(self.path, "the run folder's lock"):
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:  # a live process of this host (or, where flock spans hosts, of any host)
                record = _read(fd)
                if record is None:  # it has just taken the lock: its record follows
                    time.sleep(0.1)
                    record = _read(fd)
                raise RunFolderLocked(self._refusal(record, "it holds the folder's lock")) from None
            except OSError as e:
                if e.errno not in _NO_FLOCK:
                    raise
                self.flock = False
                log.warning(f"{self.path}: the file system refuses flock ({os.strerror(e.errno)}): the lock record "
                            "alone keeps a second process out of the folder (gchgg/run/lock.py)")
            record = _read(fd)
            if record is not None:
                self._judge(record)
            job, restart = _slurm()
            started = datetime.now().astimezone().isoformat(" ", "seconds")
            self._record = {"pid": os.getpid(), "host": socket.gethostname(), "started": started,
                            "command": shlex.join(sys.argv)[:2000], "heartbeat": _now(), "slurm_job": job,
                            "slurm_restart": restart}
            self._fd = fd
            with files.naming_disk_full(self.path, "the run folder's lock"):
                self._write()
        except BaseException:
            self._fd = None
            os.close(fd)  # drops the flock if it was taken
            raise
        if self.heartbeat_s > 0:
            self._stop.clear()
            self._thread = threading.Thread(target=self._beat, name=f"run-lock heartbeat {self.folder.name}",
                                            daemon=True)
            self._thread.start()
        return self

    def _judge(self, record: dict[str, Any]) -> None:
        """With the flock taken (or flock refused by the file system), decides whether the previous holder,
        ``record`` (empty: unreadable), is gone: logs the takeover, or raises :class:`RunFolderLocked`."""
        host, pid = record.get("host"), record.get("pid")
        age = _now() - _number(record.get("heartbeat"))
        job, restart = _slurm()
        if not record:
            why = "its record is unreadable and no process of this host holds the lock"
        elif job is not None and record.get("slurm_job") == job and restart > _number(record.get("slurm_restart")):
            why = f"this is SLURM job {job} requeued (restart {restart}), which SLURM runs once at a time"
        elif host == socket.gethostname():
            if not self.flock and isinstance(pid, int) and _pid_exists(pid):
                raise RunFolderLocked(self._refusal(record, f"its pid {pid} exists on this host"))
            why = ("that process no longer holds the lock: it ended without letting go (killed)" if self.flock
                   else f"pid {pid} no longer exists on this host")
        elif age < self.stale_after_s:
            raise RunFolderLocked(self._refusal(
                record, f"its heartbeat is {max(age, 0.0):.0f} s old, and a lock of another host is not seen on "
                f"every file system; it counts as gone once its heartbeat is {self.stale_after_s:.0f} s old"))
        else:
            why = (f"its heartbeat is {age:.0f} s old (a lock of another host counts as gone after "
                   f"{self.stale_after_s:.0f} s)")
        self.taken_over = record
        log.warning(f"took over the lock of run folder {self.folder} from {describe(record)}: {why}")

    def _refusal(self, record: dict[str, Any] | None, why: str) -> str:
        return (f"run folder {self.folder} is in use by {describe(record)}: {why}. Two processes on one run folder "
                f"would both write its metrics.csv, replay files and checkpoint. Wait for that run to end or stop "
                f"it, or give this run another folder (hydra.run.dir=<folder>); if that process is surely gone, "
                f"empty {self.path} (the lock file)")

    def _write(self) -> None:
        """Writes the record in place (the flock belongs to this file: it cannot be replaced by a rename),
        padded with spaces to the longest record written so far, so a reader never sees a shorter tail."""
        data = (json.dumps(self._record) + "\n").encode()
        with self._write_lock:
            if self._fd is None:
                return
            if len(data) < self._size:
                data = data.rstrip(b"\n") + b" " * (self._size - len(data)) + b"\n"
            os.pwrite(self._fd, data, 0)
            if self._size == 0:
                os.ftruncate(self._fd, len(data))  # the first write: a longer record of a gone holder is cut
            self._size = len(data)

    def _beat(self) -> None:
        while not self._stop.wait(self.heartbeat_s):
            self._record["heartbeat"] = _now()
            try:
                self._write()
            except OSError as e:  # a full disk or a network file system's hiccup must not stop the run
                log.debug(f"{self.path}: heartbeat not written: {e}")

    def release(self) -> None:
        """Empties the record (the run ended as it should: nothing to take over) and lets go of the lock."""
        if self._fd is None:
            return
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10)
            self._thread = None
        with self._write_lock:
            fd, self._fd = self._fd, None
            try:
                os.ftruncate(fd, 0)
            except OSError as e:
                log.warning(f"{self.path}: the lock record was not emptied ({e}): the next run will log a takeover")
            finally:
                os.close(fd)  # drops the flock


def _read(fd: int) -> dict[str, Any] | None:
    """The record in the lock file: None when there is none (a new file, or its last holder let go), ``{}``
    when it is unreadable (read again twice first: a heartbeat may be in the middle of its write)."""
    for attempt in range(3):
        size = os.fstat(fd).st_size
        text = os.pread(fd, max(size, 1), 0).decode(errors="replace").strip().strip("\0")
        if not text:
            return None
        try:
            record = json.loads(text)
        except ValueError:
            record = None
        if isinstance(record, dict):
            return record
        if attempt < 2:
            time.sleep(0.05)
    return {}
