"""Checkpoints round-trip exactly, and a truncated or altered file is an error that says so."""

import pytest
import torch

from gchgg.common import files
from gchgg.run import checkpoint


def test_round_trip_preserves_values(tmp_path):
    g = torch.Generator().manual_seed(0)
    state = {"weights": torch.randn(5, 3, generator=g), "iteration": 7, "rng": g.get_state()}
    path = tmp_path / "ckpt.pt"
    checkpoint.save(state, path)
    loaded = checkpoint.load(path)
    assert loaded["iteration"] == 7
    assert torch.equal(loaded["weights"], state["weights"])
    assert torch.equal(loaded["rng"], state["rng"])
    assert [p.name for p in tmp_path.iterdir()] == ["ckpt.pt"]  # no temporary file left behind


def test_overwrite_replaces_previous(tmp_path):
    path = tmp_path / "ckpt.pt"
    checkpoint.save({"iteration": 1}, path)
    checkpoint.save({"iteration": 2}, path)
    assert checkpoint.load(path)["iteration"] == 2


@pytest.mark.parametrize(
    "damage, message",
    [
        (lambda b: b[: len(b) // 2], "truncated"),
        (lambda b: b[:-1] + bytes([b[-1] ^ 0xFF]), "checksum"),
        (lambda b: b"NOTACKPT" + b[8:], "magic"),
        (lambda b: b[:10], "shorter than its header"),
    ],
)
def test_damaged_file_is_reported_as_corrupt(tmp_path, damage, message):
    path = tmp_path / "ckpt.pt"
    checkpoint.save({"x": torch.arange(1000)}, path)
    path.write_bytes(damage(path.read_bytes()))
    with pytest.raises(checkpoint.CorruptCheckpointError, match=message):
        checkpoint.load(path)


# -- replay files -----------------------------------------------------------------------------------


def test_replay_log_keeps_the_files_with_live_rows_and_restores_the_storage(tmp_path):
    from tensordict import TensorDict
    from torchrl.data import LazyTensorStorage

    from gchgg.run.replay_log import ReplayLog

    storage, log = LazyTensorStorage(6), ReplayLog(tmp_path / "replay", capacity=6)
    writes = [(0, [0, 1, 2]), (1, [3, 4, 5]), (2, [0, 1]), (3, [2, 0])]  # iteration 0's rows are all overwritten
    for iteration, rows in writes:
        index = torch.tensor(rows)
        data = TensorDict({"x": torch.full((len(rows), 2), float(iteration))}, [len(rows)])
        storage.set(index, data)
        log.record(iteration, index, data)
        if iteration in (1, 3):  # two checkpoints
            log.flush()
            log.prune()
    assert log.manifest() == ["iteration-000001.pt", "iteration-000002.pt", "iteration-000003.pt"]
    assert sorted(p.name for p in (tmp_path / "replay").iterdir()) == log.manifest()
    restored = LazyTensorStorage(6)
    ReplayLog(tmp_path / "replay", capacity=6).restore(log.manifest(), restored)
    assert len(restored) == len(storage) == 6
    assert torch.equal(restored.get(torch.arange(6))["x"], storage.get(torch.arange(6))["x"])
    assert restored.get(torch.arange(6))["x"][:, 0].tolist() == [3.0, 2.0, 3.0, 1.0, 1.0, 1.0]


def test_replay_files_written_before_the_goal_rename_restore_under_todays_names(tmp_path):
    """A run started before December 2026 stored the goal its episodes were collected for as target_goal:
    resumed (or forked) now, its rows hold it as episode_goal."""
    from tensordict import TensorDict
    from torchrl.data import LazyTensorStorage

    from gchgg.run import replay_log

    index = torch.arange(3)
    old = TensorDict({"desired_goal": torch.zeros(3, 3), "target_goal": torch.ones(3, 3),
                      "task_goal": torch.full((3, 3), 2.0)}, [3])
    checkpoint.save({"iteration": 0, "index": index, "rows": old}, tmp_path / "iteration-000000.pt")
    assert set(replay_log.read(tmp_path / "iteration-000000.pt")["rows"].keys()) == {
        "desired_goal", "episode_goal", "task_goal"}
    restored = LazyTensorStorage(3)
    replay_log.ReplayLog(tmp_path, capacity=3).restore(["iteration-000000.pt"], restored)
    rows = restored.get(index)
    assert torch.equal(rows["episode_goal"], torch.ones(3, 3)) and "target_goal" not in rows.keys()


def test_remove_temporaries_deletes_only_what_a_killed_save_left(tmp_path):
    checkpoint.save({"a": 1}, tmp_path / "checkpoint.pt")
    (tmp_path / ".checkpoint.pt.abc123.tmp").write_bytes(b"partial")
    (tmp_path / "notes.tmp").write_text("mine")
    assert [p.name for p in checkpoint.remove_temporaries(tmp_path)] == [".checkpoint.pt.abc123.tmp"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint.pt", "notes.tmp"]


def test_a_failing_rename_leaves_the_previous_checkpoint_loadable_and_no_temporary_file(tmp_path, monkeypatch):
    path = tmp_path / "checkpoint.pt"
    checkpoint.save({"iteration": 1}, path)

    def failing_replace(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(files.os, "replace", failing_replace)
    with pytest.raises(OSError, match="disk full"):
        checkpoint.save({"iteration": 2}, path)
    monkeypatch.undo()
    assert checkpoint.load(path) == {"iteration": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["checkpoint.pt"]
