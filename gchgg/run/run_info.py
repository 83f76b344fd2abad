"""What a run knows about itself from Hydra and the machine: tracker names, versions and commit, its start-up record.

Also whether the process is a SLURM job the cluster requeued (it then resumes its run by itself).
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from gchgg.run import loggers

__all__ = ["open_loggers", "requeued", "resolved_settings", "startup_record", "tracker_names", "versions"]

REPOSITORY = Path(__file__).resolve().parents[2]  # the checkout the code runs from


def tracker_names(cfg: DictConfig, run_dir: Path) -> tuple[str, str, Path]:
    """The run's name and group in W&B and MLflow, and the folder of a local MLflow store. A job of a
    Hydra sweep (``-m``): its ``override_dirname`` in the group named after the sweep's folder, whose
    store its jobs share; else ``<env>/<algo>/seed<seed>`` in group ``<env>/<algo>``, store in ``run_dir``."""
    name, group, store = f"{cfg.env.name}/{cfg.algo.name}/seed{cfg.seed}", f"{cfg.env.name}/{cfg.algo.name}", run_dir
    if HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN:
        hydra_cfg = HydraConfig.get()
        sweep = Path(hydra_cfg.sweep.dir).resolve()
        name, group, store = hydra_cfg.job.override_dirname or name, sweep.name, sweep
    return name, group, store


def resolved_settings(agent) -> dict[str, str]:
    """How the agent (:class:`gchgg.ddpg.agent.DDPGAgent`) resolved the settings whose ``auto`` depends on the
    machine or on ``plain``: ``matmul``, ``precision``, ``gradients`` and ``subnormals``."""
    return {name: getattr(agent, name) for name in ("matmul", "precision", "gradients", "subnormals")}


def open_loggers(cfg: DictConfig, run_dir: Path, resolved: dict[str, str]) -> loggers.RunLoggers:
    """The trackers ``logging.backend`` names (:mod:`gchgg.run.loggers`), with the settings, those the agent
    resolved (``resolved``: :func:`resolved_settings`, as ``<setting>_resolved``), the package versions and the
    git commit as hyperparameters."""
    name, group, store = tracker_names(cfg, run_dir)
    hparams = {
        **OmegaConf.to_container(cfg, resolve=True),
        "versions": versions(),
        **{f"{setting}_resolved": value for setting, value in resolved.items()},
    }
    settings = cfg.logging
    return loggers.make_loggers(
        settings.backend, run_dir, name, group, hparams,
        project=settings.project, mlflow_uri=settings.mlflow_uri, store_dir=store,
    )  # fmt: skip


def versions() -> dict[str, str]:
    """Installed versions of the packages a result depends on."""
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for package in ("gchgg", "torch", "torchrl", "tensordict", "mujoco", "dm-control", "hydra-core"):
        try:
            out[package] = version(package)
        except PackageNotFoundError:
            out[package] = "not installed"
    try:  # the commit of the checkout the code runs from, "+dirty" with uncommitted changes
        git = ["git", "-C", str(REPOSITORY)]
        commit = subprocess.run([*git, "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                check=True).stdout
        dirty = subprocess.run([*git, "status", "--porcelain", "--untracked-files=no"], capture_output=True,
                               text=True).stdout
        out["commit"] = commit.strip() + ("+dirty" if dirty.strip() else "")
    except (OSError, subprocess.CalledProcessError):
        out["commit"] = "unknown (not a git checkout)"
    return out


def startup_record(cfg: DictConfig, resolved: dict[str, str]) -> str:
    """The run's resolved settings and the installed versions, as logged once at start-up: ``plain``, then each
    setting the agent resolved (``resolved``: :func:`resolved_settings`) as ``setting: value -> resolved``."""
    packages = ", ".join(f"{k} {v}" for k, v in versions().items())
    plain = cfg.get("plain", False)
    alone = " (the algorithm alone: no speed device of gchgg.fast)" if plain else ""
    lines = [f"versions: {packages}", f"plain: {str(plain).lower()}{alone}"]
    lines += [f"{setting}: {cfg.get(setting, 'auto')} -> {value}" for setting, value in resolved.items()]
    return "\n".join(lines) + f"\nresolved config:\n{OmegaConf.to_yaml(cfg, resolve=True)}"


def requeued() -> bool:
    """Whether this process is a SLURM job the cluster requeued (pre-empted or timed out, then
    started again): ``SLURM_RESTART_COUNT`` > 0. Such a job resumes its run by itself."""
    try:
        return int(os.environ.get("SLURM_RESTART_COUNT", "0") or 0) > 0
    except ValueError:
        return False
