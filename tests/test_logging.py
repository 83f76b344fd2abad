"""logging.backend: TorchRL's loggers (TensorBoard, W&B offline, MLflow in a local store) get the rows of
metrics.csv and the settings once; a resumed run goes on in the same tracker runs; sweeps are grouped."""

from __future__ import annotations

import csv
import json
import struct
import time
from pathlib import Path
from types import SimpleNamespace

import pytest
from hydra.types import RunMode
from test_train import config, read_metrics, tiny

from gchgg import train
from gchgg.run import config as gchgg_config
from gchgg.run import loggers, run_info


def run(tmp_path: Path, backend: str, iterations: int = 2, *extra: str) -> Path:
    run_dir = tmp_path / "run"
    overrides = ["env=reach", "algo=her", *tiny(tmp_path, iterations), f"logging.backend={backend}", *extra]
    train.run(config(overrides), run_dir)
    return run_dir


def columns(run_dir: Path) -> dict[str, list[tuple[int, float]]]:
    """metrics.csv as column -> [(iteration, value)]."""
    out: dict[str, list[tuple[int, float]]] = {}
    for row in read_metrics(run_dir):
        for key, text in row.items():
            if text != "":
                out.setdefault(key, []).append((int(row["iteration"]), float(text)))
    return out


def test_default_is_metrics_csv_alone(tmp_path):
    run_dir = run(tmp_path, "csv", iterations=1)
    assert [r["iteration"] for r in read_metrics(run_dir)] == ["0"]
    assert not (run_dir / "tensorboard").exists() and not (run_dir / loggers.STATE).exists()
    assert config([]).logging.backend == "csv"


def test_tensorboard_holds_the_scalars_of_metrics_csv(tmp_path):
    pytest.importorskip("tensorboard", reason='needs pip install -e ".[tensorboard]"')
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    run_dir = run(tmp_path, "[csv,tensorboard]")
    events = EventAccumulator(str(run_dir / "tensorboard"))
    events.Reload()
    expected = columns(run_dir)
    assert set(events.Tags()["scalars"]) == set(expected)
    for key, points in expected.items():
        logged = [(e.step, e.value) for e in events.Scalars(key)]
        assert logged == [(step, pytest.approx(value, rel=1e-6, abs=1e-6)) for step, value in points], key
    assert any(p.is_dir() for p in (run_dir / "tensorboard").iterdir())  # add_hparams' folder: the settings


def wandb_records(run_folder: Path) -> list:
    """The records of a W&B run file (``run-<id>.wandb``: a 7-byte header, then LevelDB-log blocks)."""
    from wandb.proto import wandb_internal_pb2

    data = next(run_folder.glob("run-*.wandb")).read_bytes()
    records, pending, position, block = [], b"", 7, 32768
    while position + 7 <= len(data):
        left = block - position % block
        _, length, kind = struct.unpack("<IHB", data[position : position + 7])
        if left < 7 or (length == 0 and kind == 0):  # block trailer / padding
            position += left
            continue
        if position + 7 + length > len(data):  # being written
            break
        pending += data[position + 7 : position + 7 + length]
        position += 7 + length
        if kind in (1, 4):  # a full record, or a record's last fragment
            record = wandb_internal_pb2.Record()
            record.ParseFromString(pending)
            records.append(record)
            pending = b""
    return records


def wandb_run(run_folder: Path, wait_s: float = 60) -> dict:
    """Group, name, config and history (key -> [(step, value)]) of an offline W&B run folder, once its
    file is complete (W&B's service process writes it after ``finish`` returns)."""
    deadline = time.monotonic() + wait_s
    while not any(r.WhichOneof("record_type") == "exit" for r in wandb_records(run_folder)):
        assert time.monotonic() < deadline, f"{run_folder}: no exit record after {wait_s} s"
        time.sleep(0.2)
    out = {"history": {}, "config": {}}
    for record in wandb_records(run_folder):
        kind = record.WhichOneof("record_type")
        if kind == "run":
            out.update(id=record.run.run_id, group=record.run.run_group, name=record.run.display_name)
        elif kind == "config":
            out["config"].update({i.key: json.loads(i.value_json) for i in record.config.update if i.key != "_wandb"})
        elif kind == "history":
            items = {item.nested_key[0] if item.nested_key else item.key: json.loads(item.value_json)
                     for item in record.history.item}  # fmt: skip
            for key, value in items.items():
                if not key.startswith("_") and key != "step":
                    out["history"].setdefault(key, []).append((items["step"], value))
    return out


def test_a_run_writes_csv_tensorboard_and_wandb_offline_and_a_resume_continues_its_wandb_run(tmp_path, monkeypatch):
    pytest.importorskip("wandb", reason='needs pip install -e ".[wandb]"')
    pytest.importorskip("tensorboard", reason='needs pip install -e ".[tensorboard]"')
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_DIR", str(tmp_path / "wandb"))
    monkeypatch.setenv("WANDB_SILENT", "true")
    run_dir = run(tmp_path, "[csv,tensorboard,wandb]")
    assert len(read_metrics(run_dir)) == 2
    assert list((run_dir / "tensorboard").glob("events.out.tfevents.*"))
    (first,) = (tmp_path / "wandb" / "wandb").glob("offline-run-*")
    logged = wandb_run(first)
    assert (logged["group"], logged["name"]) == ("reach/her", "reach/her/seed0")
    assert logged["config"]["train.episodes"] == 2 and logged["config"]["env.name"] == "reach"
    assert "versions.torchrl" in logged["config"] and "versions.commit" in logged["config"]
    expected = columns(run_dir)
    assert logged["history"]["success_rate"] == expected["success_rate"]
    assert set(logged["history"]) == set(expected)

    # resume=true: the same W&B run (its id kept in trackers.json), only the new iteration logged
    run(tmp_path, "[csv,tensorboard,wandb]", 3, "resume=true")
    (second,) = set((tmp_path / "wandb" / "wandb").glob("offline-run-*")) - {first}
    resumed = wandb_run(second)
    assert resumed["id"] == logged["id"] == json.loads((run_dir / loggers.STATE).read_text())["wandb"]["id"]
    assert resumed["history"]["success_rate"] == columns(run_dir)["success_rate"][2:]
    assert "train.episodes" not in resumed["config"]  # the settings went to the run when it was new


def test_mlflow_holds_the_rows_and_the_settings_in_the_default_local_store(tmp_path, monkeypatch):
    pytest.importorskip("mlflow", reason='needs pip install -e ".[mlflow]"')
    pytest.importorskip("sqlalchemy", reason='needs pip install -e ".[mlflow]"')
    import mlflow

    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    run_dir = run(tmp_path, "[csv,mlflow]")
    state = json.loads((run_dir / loggers.STATE).read_text())["mlflow"]
    assert state["uri"] == f"sqlite:///{run_dir.resolve() / 'mlflow.db'}"
    client = mlflow.MlflowClient(state["uri"])
    logged = client.get_run(state["run_id"])
    assert logged.info.run_name == "reach/her/seed0" and logged.info.status == "FINISHED"
    assert client.get_experiment(logged.info.experiment_id).name == "reach/her"
    assert logged.data.params["train.episodes"] == "2" and "versions.torch" in logged.data.params
    for key, points in columns(run_dir).items():
        history = sorted((m.step, m.value) for m in client.get_metric_history(state["run_id"], key))
        assert history == [(step, pytest.approx(value)) for step, value in points], key


def test_mlflow_file_store_run_goes_on_after_a_resume(tmp_path, monkeypatch):
    pytest.importorskip("mlflow", reason='needs pip install -e ".[mlflow]"')
    import mlflow

    monkeypatch.setenv("MLFLOW_ALLOW_FILE_STORE", "true")  # MLflow >= 3.10 wants the opt-in for a folder store
    uri = (tmp_path / "mlruns").as_uri()
    first = loggers.make_loggers(["mlflow"], tmp_path, "job", "sweep", {"a": {"b": 1}}, mlflow_uri=uri)
    first.log_row({"success_rate": 0.25}, step=0)
    first.log_row({"success_rate": 0.5}, step=1)
    first.close()
    again = loggers.make_loggers("mlflow", tmp_path, "job", "sweep", {"a": {"b": 1}}, mlflow_uri=uri)
    again.log_row({"success_rate": 0.5}, step=1)  # a repeated iteration: logged before
    again.log_row({"success_rate": 0.75}, step=2)
    again.close()
    client = mlflow.MlflowClient(uri)
    (experiment,) = [e for e in client.search_experiments() if e.name == "sweep"]
    (logged,) = client.search_runs([experiment.experiment_id])
    assert logged.info.run_name == "job" and logged.data.params == {"a.b": "1"}
    history = [(m.step, m.value) for m in client.get_metric_history(logged.info.run_id, "success_rate")]
    assert sorted(history) == [(0, 0.25), (1, 0.5), (2, 0.75)]


def test_sweep_jobs_share_a_group_named_after_the_sweep(tmp_path, monkeypatch):
    cfg = config(["env=reach", "algo=her", "seed=1"])
    assert run_info.tracker_names(cfg, tmp_path) == ("reach/her/seed1", "reach/her", tmp_path)  # no Hydra: a single run
    hydra_cfg = SimpleNamespace(
        mode=RunMode.MULTIRUN,
        sweep=SimpleNamespace(dir=str(tmp_path / "multirun" / "fig5_reach")),
        job=SimpleNamespace(override_dirname="algo=her,seed=1"),
    )
    monkeypatch.setattr(run_info.HydraConfig, "initialized", staticmethod(lambda: True))
    monkeypatch.setattr(run_info.HydraConfig, "get", staticmethod(lambda: hydra_cfg))
    name, group, store = run_info.tracker_names(cfg, tmp_path / "job")
    assert (name, group, store) == ("algo=her,seed=1", "fig5_reach", tmp_path / "multirun" / "fig5_reach")
    hydra_cfg.mode = RunMode.RUN
    assert run_info.tracker_names(cfg, tmp_path)[1] == "reach/her"


@pytest.mark.parametrize("backend", ["tensorbord", "[csv,wandbb]"])
def test_an_unknown_backend_fails_before_training_naming_the_setting(backend):
    with pytest.raises(ValueError, match=r"logging\.backend: unknown backend '(tensorbord|wandbb)'; the backends are "
                                         r"csv, tensorboard, wandb, mlflow"):  # fmt: skip
        gchgg_config.check(config([f"logging.backend={backend}"]))


def test_a_backend_without_its_package_names_the_extra_to_install(monkeypatch):
    find_spec = loggers.importlib.util.find_spec
    monkeypatch.setattr(loggers.importlib.util, "find_spec", lambda name: None if name == "wandb" else find_spec(name))
    message = r'logging\.backend=wandb needs the wandb package: pip install -e "\.\[wandb\]"'
    with pytest.raises(ImportError, match=message):
        gchgg_config.check(config(["logging.backend=[csv,wandb]"]))


def test_metrics_csv_is_unchanged_by_the_backends(tmp_path):
    pytest.importorskip("tensorboard", reason='needs pip install -e ".[tensorboard]"')
    plain, tracked = run(tmp_path / "a", "csv"), run(tmp_path / "b", "[csv,tensorboard]")

    def results(run_dir):
        with open(run_dir / "metrics.csv") as f:
            return [{k: v for k, v in row.items() if not k.startswith("seconds_")} for row in csv.DictReader(f)]

    assert results(plain) == results(tracked)
