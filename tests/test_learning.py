"""Learning checks (slow, excluded by default: `pytest -m slow`): the pipeline learns a real task."""

from __future__ import annotations

import pytest
from hydra import compose, initialize_config_dir

from gchgg import train


@pytest.mark.slow
def test_her_learns_reach_within_ten_iterations(tmp_path):
    with initialize_config_dir(config_dir=str(train.CONF_DIR), version_base="1.3"):
        cfg = compose("config", overrides=["env=reach", "algo=her", "train.iterations=10", "logging.progress=false"])
    history = train.run(cfg, tmp_path / "run")
    success = [row["success_rate"] for row in history]
    assert len(success) == 10
    assert max(success) >= 0.9, success
    assert success[-1] >= 0.9, success
