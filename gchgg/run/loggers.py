"""The run's experiment trackers (``logging.backend``): TorchRL's loggers, built from plain arguments.

``metrics.csv`` is the run's record (resume, :mod:`gchgg.analysis.plot` and :mod:`gchgg.analysis.claims` read it) and is
always written by the trainer; the backends here receive the same rows as it, one call per complete
row with ``step = iteration``, and the run's hyperparameters once:

- ``csv``: ``metrics.csv`` alone, nothing more: TorchRL's ``CSVLogger`` would write the same numbers
  again, one headerless file per scalar, a second CSV record beside the one every tool reads;
- ``tensorboard``: ``TensorboardLogger`` into ``<run>/tensorboard/`` (``pip install -e ".[tensorboard]"``);
- ``wandb``: ``WandbLogger``, run ``name`` in ``group`` of ``project``; ``WANDB_MODE=offline`` keeps it on
  disk for ``wandb sync`` (``pip install -e ".[wandb]"``);
- ``mlflow``: ``MLFlowLogger``, run ``name`` in experiment ``group``, at ``mlflow_uri`` (default:
  :func:`mlflow_tracking_uri`) (``pip install -e ".[mlflow]"``).

``<run>/trackers.json`` keeps the W&B and MLflow run ids and the last iteration logged, so a resumed
run goes on in the same tracker runs, without logging again the iterations it repeats (those after
its last checkpoint); hyperparameters go to new tracker runs only. Nothing here reads Hydra:
the trainer passes names as strings.
"""

from __future__ import annotations

import contextlib
import importlib.util
import json
import os
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

from gchgg.common import files

__all__ = ["BACKENDS", "STATE", "RunLoggers", "check_backends", "flatten", "make_loggers", "mlflow_tracking_uri"]

BACKENDS = ("csv", "tensorboard", "wandb", "mlflow")
NEEDS = {"tensorboard": ("tensorboard", "tensorboard"), "wandb": ("wandb", "wandb"), "mlflow": ("mlflow", "mlflow")}
"""backend -> (the module it imports, the ``pip install -e ".[extra]"`` that brings it)"""
STATE = "trackers.json"  # in the run folder: the W&B and MLflow run ids and the last iteration logged
SETTING = "logging.backend"


def check_backends(backend: str | Sequence[str] | None) -> list[str]:
    """The backends ``backend`` names (one name or a list), in order, each once; a ``ValueError``
    naming the setting for an unknown one, an ``ImportError`` with the extra to install for one whose
    package is missing.

    >>> check_backends("csv"), check_backends(["csv", "tensorboard", "csv"])
    (['csv'], ['csv', 'tensorboard'])
    """
    names = [backend] if isinstance(backend, str) else list(backend or [])
    for name in names:
        if name not in BACKENDS:
            raise ValueError(
                f"{SETTING}: unknown backend {name!r}; the backends are {', '.join(BACKENDS)} "
                f"(one, or several: {SETTING}=[csv,wandb])"
            )
    names = list(dict.fromkeys(names))
    for name in names:
        if name in NEEDS and importlib.util.find_spec(NEEDS[name][0]) is None:
            module, extra = NEEDS[name]
            raise ImportError(f'{SETTING}={name} needs the {module} package: pip install -e ".[{extra}]"')
    return names


def flatten(tree: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """A nested mapping as one level of dotted keys; values other than numbers, strings and booleans
    (lists, ``None``) as their text, which every tracker takes.

    >>> flatten({"train": {"iterations": 200, "stop_success": None}, "agent": {"hidden": [256, 256]}})
    {'train.iterations': 200, 'train.stop_success': 'None', 'agent.hidden': '[256, 256]'}
    """
    out: dict[str, Any] = {}
    for key, value in tree.items():
        if isinstance(value, Mapping):
            out.update(flatten(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value if isinstance(value, (bool, int, float, str)) else str(value)
    return out


def mlflow_tracking_uri(setting: str | None, store_dir: Path) -> str:
    """Where MLflow records: ``setting`` when given, else ``MLFLOW_TRACKING_URI`` (a server, say), else
    an SQLite store ``<store_dir>/mlflow.db`` (MLflow >= 3.10 refuses a plain folder store unless
    ``MLFLOW_ALLOW_FILE_STORE=true``)."""
    return setting or os.environ.get("MLFLOW_TRACKING_URI") or f"sqlite:///{Path(store_dir).resolve() / 'mlflow.db'}"


class RunLoggers:
    """The TorchRL loggers of one run, by backend name: each metrics row to all of them, once.

    Args:
        loggers: backend name -> ``torchrl.record.loggers.Logger``.
        state_path: the run's :data:`STATE` file, where the last iteration logged is kept.
        state: its content.
    """

    def __init__(self, loggers: Mapping[str, Any], state_path: Path | None = None, state: dict | None = None) -> None:
        self.loggers = dict(loggers)
        self.state_path = state_path
        self.state = {} if state is None else state

    def log_row(self, row: Mapping[str, float], step: int) -> None:
        """One metrics row at ``step`` (the iteration), unless a step this far was logged before (by the
        run before a resume): one ``log_metrics`` call per backend, so one W&B history row per iteration."""
        if not self.loggers or step <= self.state.get("logged_through", -1):
            return
        values = {key: float(value) for key, value in row.items()}
        for name, logger in self.loggers.items():
            with files.naming_disk_full(_where(name, logger), f"the {name} tracker's records in"):
                logger.log_metrics(values, step=step)
        self.state["logged_through"] = step
        if self.state_path is not None:
            files.write_text(self.state_path, json.dumps(self.state, indent=1))  # atomic: a resume reads it

    def close(self) -> None:
        """Flush and close every logger (W&B: finish the run; MLflow: end the run)."""
        for name, logger in self.loggers.items():
            with files.naming_disk_full(_where(name, logger), f"the {name} tracker's records in"):
                logger.close()
            if name == "mlflow":  # MLFlowLogger leaves its run active; end it as FINISHED
                import mlflow

                mlflow.end_run()
        self.loggers = {}

    def __bool__(self) -> bool:
        return bool(self.loggers)


def make_loggers(
    backends: str | Sequence[str] | None,
    run_dir: Path,
    name: str,
    group: str | None = None,
    hparams: Mapping[str, Any] | None = None,
    *,
    project: str = "gchgg",
    mlflow_uri: str | None = None,
    store_dir: Path | None = None,
) -> RunLoggers:
    """The loggers of ``backends`` for the run in ``run_dir``, with ``hparams`` (nested or dotted)
    logged once into each new tracker run.

    Args:
        backends: ``logging.backend``: names out of :data:`BACKENDS` (``csv``: ``metrics.csv`` alone).
        run_dir: the run folder (TensorBoard's logs, W&B's files unless ``WANDB_DIR`` is set,
            :data:`STATE`).
        name: the run's name in W&B and MLflow.
        group: W&B's group and MLflow's experiment (a sweep's runs share one); ``None``: no W&B group,
            MLflow experiment ``project``.
        hparams: the settings, versions and such to log once.
        project: the W&B project.
        mlflow_uri: the MLflow tracking URI (:func:`mlflow_tracking_uri` picks the default).
        store_dir: folder of the default local MLflow store (default ``run_dir``; a sweep's folder, so
            that its runs share one store).
    """
    names = check_backends(backends)
    run_dir = Path(run_dir)
    state_path = run_dir / STATE
    state = json.loads(state_path.read_text()) if state_path.exists() else {}
    params = flatten(hparams or {})
    loggers, new = {}, []
    try:
        for backend in names:
            if backend == "tensorboard":
                from torchrl.record.loggers import TensorboardLogger

                fresh = not (run_dir / "tensorboard").exists()
                with files.naming_disk_full(run_dir / "tensorboard", "the tensorboard tracker's records in"):
                    loggers[backend] = TensorboardLogger(exp_name="tensorboard", log_dir=str(run_dir))
            elif backend == "wandb":
                from torchrl.record.loggers import WandbLogger

                saved = state.get("wandb", {}).get("id")
                fresh = saved is None
                loggers[backend] = WandbLogger(
                    exp_name=name,
                    save_dir=None if os.environ.get("WANDB_DIR") else str(run_dir),
                    id=saved,
                    project=project,
                    group=group,
                    log_env_packages=False,  # its config key "env" would mix with the settings' env.*
                )
                state["wandb"] = {"id": loggers[backend].experiment.id, "project": project}
            elif backend == "mlflow":
                loggers[backend], fresh = _mlflow_logger(
                    name, group or project, mlflow_tracking_uri(mlflow_uri, store_dir or run_dir), state
                )
            else:  # csv: metrics.csv, written by the trainer
                continue
            if fresh:
                new.append(backend)
            files.write_text(state_path, json.dumps(state, indent=1))  # atomic: a resume reads it
        for backend in new:
            if params:
                with files.naming_disk_full(_where(backend, loggers[backend]), f"the {backend} tracker's records in"):
                    loggers[backend].log_hparams(params)
    except BaseException:
        RunLoggers(loggers).close()
        raise
    return RunLoggers(loggers, state_path, state)


def _where(name: str, logger: Any) -> str:
    """Where the ``name`` backend's ``logger`` writes (TensorBoard: its folder; MLflow: the tracking URI)."""
    if name == "tensorboard":
        return os.path.join(logger.log_dir, logger.exp_name)
    return str(getattr(logger, "log_dir", None) or os.environ.get("WANDB_DIR") or name)


def _mlflow_logger(name: str, experiment: str, uri: str, state: dict) -> tuple[Any, bool]:
    """TorchRL's ``MLFlowLogger`` in experiment ``experiment`` at ``uri``, going on in the run that
    ``state`` names for this ``uri`` (if any), else a new run called ``name``; and whether it is new.
    A local store is created under a lock, since a sweep's jobs start together."""
    import mlflow
    from torchrl.record.loggers import MLFlowLogger

    saved = state.get("mlflow", {})
    run_id = saved.get("run_id") if saved.get("uri") == uri else None
    with _store_lock(uri), _environ("MLFLOW_RUN_ID", run_id):  # start_run goes on in MLFLOW_RUN_ID's run
        logger = MLFlowLogger(exp_name=experiment, tracking_uri=uri)
    active = logger.experiment.info.run_id
    if run_id is None:
        mlflow.MlflowClient(uri).set_tag(active, "mlflow.runName", name)
    state["mlflow"] = {"uri": uri, "run_id": active}
    return logger, run_id is None


@contextlib.contextmanager
def _environ(key: str, value: str | None) -> Iterator[None]:
    """``os.environ[key] = value`` inside the block (nothing when ``value`` is ``None``)."""
    if value is None:
        yield
        return
    before = os.environ.get(key)
    os.environ[key] = value
    try:
        yield
    finally:
        if before is None:
            os.environ.pop(key, None)
        else:
            os.environ[key] = before


@contextlib.contextmanager
def _store_lock(uri: str) -> Iterator[None]:
    """An exclusive lock beside a local (``sqlite:///``, ``file:``) MLflow store while a logger is built:
    a sweep's jobs would otherwise race to create its tables and its experiment."""
    try:
        import fcntl
    except ImportError:  # not POSIX: no lock
        yield
        return
    if uri.startswith("sqlite:///"):
        path = Path(uri[len("sqlite:///"):] + ".lock")
    elif uri.startswith("file:"):
        from urllib.parse import urlparse
        from urllib.request import url2pathname

        path = Path(url2pathname(urlparse(uri).path)) / ".lock"
    else:
        yield
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)
