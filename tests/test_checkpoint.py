"""Checkpoints round-trip exactly, and a truncated or altered file is an error that says so."""

import pytest
import torch

from gchgg import checkpoint


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
