"""The run-folder lock (gchgg/run/lock.py): a second process on a live run's folder is refused at once, a killed
run's lock is taken over with a line in the log, forks and other folders are not held up.

A child process (:func:`holder`) stands for the live run: it takes the lock as :func:`gchgg.train.run` does and
holds it until the test kills it; the tests call ``train.run`` of tiny runs (``tests/test_train.py``) in this
process, a process other than the holder.
"""

from __future__ import annotations

import errno
import json
import logging
import socket
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
from test_train import config, read_metrics, tiny  # noqa: E402

from gchgg import train  # noqa: E402
from gchgg.run import lock  # noqa: E402
from gchgg.run.lock import LOCK_FILE, RunFolderLocked, RunLock  # noqa: E402

HOLDER = """
import sys, time
from gchgg.run.lock import RunLock
RunLock(sys.argv[1]).acquire()
print("held", flush=True)
time.sleep(600)
"""


@contextmanager
def holder(folder: Path):
    """A child process holding ``folder``'s lock (a live run) until the ``with`` ends or the test kills it."""
    folder.mkdir(parents=True, exist_ok=True)
    child = subprocess.Popen([sys.executable, "-c", HOLDER, str(folder)], stdout=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        assert child.stdout.readline().strip() == "held"
        yield child
    finally:
        child.kill()
        child.wait()
        child.stdout.close()


def reach(tmp_path: Path, *more: str, iterations: int = 1):
    return config(["env=reach", "algo=her", *tiny(tmp_path, iterations=iterations), *more])


def record(folder: Path) -> dict | None:
    text = (folder / LOCK_FILE).read_text().strip()
    return json.loads(text) if text else None


def takeovers(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == lock.__name__ and "took over" in r.getMessage()]


def test_a_second_process_on_a_held_folder_is_refused_at_once_naming_pid_and_host(tmp_path):
    run_dir, cfg = tmp_path / "run", reach(tmp_path)
    with holder(run_dir) as child:
        started = time.perf_counter()
        with pytest.raises(RunFolderLocked) as refused:
            train.run(cfg, run_dir)
        seconds = time.perf_counter() - started
        assert child.poll() is None  # the holder runs on
    message = str(refused.value)
    assert str(run_dir) in message and f"pid {child.pid} on host {socket.gethostname()}" in message
    assert seconds < 2, seconds  # refused at once: nothing built, no waiting for the holder
    assert sorted(p.name for p in run_dir.iterdir()) == [LOCK_FILE]  # nothing of the folder read or written


def test_a_lock_left_by_a_sigkilled_run_is_taken_over_with_a_line_in_the_log(tmp_path, caplog):
    run_dir = tmp_path / "run"
    with holder(run_dir) as child:
        child.kill()  # SIGKILL: no cleanup runs, the record stays; the kernel drops the flock
        child.wait()
    assert record(run_dir)["pid"] == child.pid
    with caplog.at_level(logging.WARNING, logger=lock.__name__):
        train.run(reach(tmp_path), run_dir)
    [line] = takeovers(caplog)
    assert str(run_dir) in line and f"pid {child.pid} on host {socket.gethostname()}" in line
    assert [int(r["iteration"]) for r in read_metrics(run_dir)] == [0]
    assert record(run_dir) is None  # the run ended as it should: released, nothing to take over next time
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger=lock.__name__):
        train.run(reach(tmp_path, "resume=true", iterations=2), run_dir)
    assert takeovers(caplog) == [] and [int(r["iteration"]) for r in read_metrics(run_dir)] == [0, 1]


def test_a_fork_of_a_live_run_works_without_its_lock(tmp_path):
    source, forked = tmp_path / "source", tmp_path / "fork"
    train.run(reach(tmp_path), source)
    with holder(source) as child:  # the source's run is live
        train.run(reach(tmp_path, f"init_from={source}", "seed=5", iterations=2), forked)
        assert child.poll() is None and record(source)["pid"] == child.pid  # its lock untouched
    assert [int(r["iteration"]) for r in read_metrics(forked)] == [0, 1]
    assert record(forked) is None


def test_two_folders_lock_independently(tmp_path):
    (tmp_path / "b").mkdir()
    (tmp_path / "c").mkdir()
    with holder(tmp_path / "a"):
        with RunLock(tmp_path / "b") as b, RunLock(tmp_path / "c") as c:
            assert b.held and c.held and b.taken_over is None and c.taken_over is None
            with pytest.raises(RunFolderLocked):  # in this process too, a second lock of one folder is refused
                RunLock(tmp_path / "b").acquire()
        with pytest.raises(RunFolderLocked):
            RunLock(tmp_path / "a").acquire()


def test_the_lock_is_released_however_the_run_ends(tmp_path, caplog):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "checkpoint.pt").write_bytes(b"")
    with pytest.raises(FileExistsError):  # an exception out of train.run
        train.run(reach(tmp_path), run_dir)
    assert record(run_dir) is None
    with pytest.raises(KeyboardInterrupt), RunLock(run_dir):  # Ctrl-C
        raise KeyboardInterrupt
    assert record(run_dir) is None
    with caplog.at_level(logging.WARNING, logger=lock.__name__), RunLock(run_dir) as again:
        assert again.taken_over is None
    assert takeovers(caplog) == []


def write_record(folder: Path, **fields) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / LOCK_FILE).write_text(json.dumps({"pid": 4242, "host": "node-b", "started": "then", "command": "train",
                                                "heartbeat": time.time(), **fields}))


def test_another_hosts_lock_is_live_until_its_heartbeat_is_stale(tmp_path, caplog, monkeypatch):
    monkeypatch.delenv("SLURM_JOB_ID", raising=False)
    write_record(tmp_path, heartbeat=time.time() - 30)  # flock is per host on some file systems: the record decides
    with pytest.raises(RunFolderLocked, match="pid 4242 on host node-b .*heartbeat is 30 s old"):
        RunLock(tmp_path).acquire()
    write_record(tmp_path, heartbeat=time.time() - lock.STALE_AFTER_S - 1)  # that machine is gone
    with caplog.at_level(logging.WARNING, logger=lock.__name__), RunLock(tmp_path) as taken:
        assert taken.taken_over["host"] == "node-b"
    [line] = takeovers(caplog)
    assert "pid 4242 on host node-b" in line and "heartbeat" in line


def test_a_requeued_slurm_job_takes_its_own_lock_over_at_once(tmp_path, monkeypatch):
    write_record(tmp_path, slurm_job="77", slurm_restart=0)  # a fresh heartbeat, another node
    monkeypatch.setenv("SLURM_JOB_ID", "77")
    monkeypatch.setenv("SLURM_RESTART_COUNT", "1")
    with RunLock(tmp_path) as taken:
        assert taken.taken_over["pid"] == 4242
    monkeypatch.setenv("SLURM_JOB_ID", "78")  # another job: refused
    write_record(tmp_path, slurm_job="77", slurm_restart=0)
    with pytest.raises(RunFolderLocked):
        RunLock(tmp_path).acquire()


def test_without_flock_the_record_decides_by_pid(tmp_path, monkeypatch):
    def no_flock(fd, operation):
        raise OSError(errno.ENOSYS, "flock")

    monkeypatch.setattr(lock.fcntl, "flock", no_flock)
    alive = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        write_record(tmp_path, pid=alive.pid, host=socket.gethostname())
        with pytest.raises(RunFolderLocked, match=f"pid {alive.pid} exists"):
            RunLock(tmp_path).acquire()
    finally:
        alive.kill()
        alive.wait()
    with RunLock(tmp_path) as taken:
        assert not taken.flock and taken.taken_over["pid"] == alive.pid


def test_the_heartbeat_is_rewritten_while_the_lock_is_held(tmp_path):
    with RunLock(tmp_path, heartbeat_s=0.02):
        first = record(tmp_path)
        time.sleep(0.3)
        later = record(tmp_path)
        assert later["heartbeat"] > first["heartbeat"] and later["pid"] == first["pid"]
    assert record(tmp_path) is None
