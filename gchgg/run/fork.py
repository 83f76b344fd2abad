"""Start a run from another run's checkpoint with other settings (``init_from=<run folder>``): a fork.

Paired forks take the between-seed noise out of a comparison: two forks of one checkpoint, say as
GC-HGG and as G-HGG with the same fresh seed, share everything up to the fork point and differ only
in what the fork changes.

**Taken over** from ``<init_from>/checkpoint.pt`` (the source's last checkpoint, through the resume
path: :meth:`gchgg.train.Trainer.load_state_dict`): the replay buffer's rows (the files its manifest
lists in ``<init_from>/replay/``, hard-linked, else copied, into the fork's own ``replay/``; the
source's files are only ever replaced, never written in place, so the links stay valid whatever the
source does next) and its writer, the actor, critic, their targets, normalisers and optimisers, the
HGG goal generator's pool and stop flag, the iteration and env-step counters, and the metrics rows
0..i-1: the fork's ``metrics.csv`` holds the source's rows, then its own from iteration i on.

**New**: the sampler and its trade-off λ, built from the fork's ``algo.sampler``, ``curriculum.*``,
``tradeoff.*`` and ``cher.*`` (carried over only when none of those, ``algo.*``, the graph but its
``cache_dir``, nor the seed changed; a new curriculum sampler behind an HGG that has already stopped
starts stopped, as the source's had). The random streams (the envs' goal draws, exploration, HER,
the buffer's draws, observation noise, torch's) start from the fork's ``seed`` as a new run with that
seed starts them, unless the seed is the source's: then they continue. So a fork that changes
nothing (but its length, logging and the like) continues exactly as ``resume=true`` would, and the
two forks of a pair (same checkpoint, same new seed) draw the same targets at the fork point.

**May differ**: :data:`MAY_DIFFER`. How the products are computed (``threads``, ``matmul``,
``precision``, ``gradients``, ``subnormals``, and ``plain``, which fixes them and runs the algorithm
without its speed devices) may: the carried parameters are float32 whatever the products' dtype,
flushed subnormals leave them as they are, and the sampler's state and the stored rows load into
either path (a fast sampler's candidates drawn ahead are drawn afresh on the plain path). The metric (``algo.metric``,
``graph.*``) and HGG's parameters (``env.stop_threshold``, ``hgg.c``, ``hgg.L``) may, because no
carried state depends on them: the pool holds raw achieved-goal trajectories, HGG's ``max_dis`` is
recomputed with the fork's metric, and the stop flag is carried as it is (a stop
that fired stays fired). Every other setting shapes the carried state or the loop that wrote the
source's rows (task, networks, buffer, HER, episodes, updates, goal generator, pool size, evaluation
episodes) and must be the source's; a fork that changes one is refused, naming it with both values.
A setting the source's ``config.yaml`` lacks (added to the code after the source ran) counts as
changed; outside :data:`MAY_DIFFER` it is refused too, with a hint: ``~<setting>`` drops it from the
fork's config where its absence reads as the source's behaviour.

The fork writes its first checkpoint (iteration i) and ``fork.yaml`` (source, source iteration, the
changed settings source → fork, what was renewed) into its own folder before it trains: from then
on it is a run of its own, resumed with ``resume=true`` from its own checkpoint (``init_from`` is
not read again) and independent of the source's folder. A ``resume=true`` that names an
``init_from`` other than the one the folder's ``fork.yaml`` records (or a folder holding no fork) is
refused (:func:`check_resume`): the folder holds another run. A fork's folder name in a Hydra sweep
leaves ``init_from`` out (``hydra.job.config.override_dirname.exclude_keys``: a path would nest
folders), so a sweep of forks names its source in ``hydra.sweep.dir``.
"""

from __future__ import annotations

import logging
import os
import shutil
from dataclasses import dataclass, field
from fnmatch import fnmatchcase
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from gchgg.common import files
from gchgg.run import checkpoint

__all__ = ["MAY_DIFFER", "Fork", "changed_settings", "check_resume", "prepare", "start"]

log = logging.getLogger(__name__)

RECORD = "fork.yaml"
SOURCE_CONFIG = "config.yaml"
MAY_DIFFER = (
    "seed", "resume", "init_from", "threads", "matmul", "precision", "gradients", "subnormals", "plain",
    "algo.name", "algo.sampler", "algo.metric", "graph", "graph.*",
    "curriculum", "curriculum.*", "tradeoff", "tradeoff.*", "cher", "cher.*",  # a section, or null where unread
    "env.stop_threshold", "hgg.c", "hgg.L",
    "train.iterations", "train.stop_success", "train.stop_patience",
    "eval.every", "eval.background", "checkpoint.every", "logging.*",
)  # fmt: skip
"""Settings a fork may change (``*``: any key under it); every other one must be the source's."""
SAMPLER = ("seed", "algo.*", "graph", "graph.name", "graph.n", "graph.margin", "graph.snap", "curriculum",
           "curriculum.*", "tradeoff", "tradeoff.*", "cher", "cher.*")  # fmt: skip
"""A change in any of these makes the sampler and λ new rather than carried over."""
STREAMS = ("her_rng", "explore_rng", "torch_rng", "env_random", "eval_env_random", "noise_rng")
"""The checkpoint's random-stream entries (and the buffer's ``_rng``), renewed with a new seed."""
NOT_LISTED = ("resume", "init_from")  # how a run starts, not what it is: not reported as changed
WHY = {  # setting prefix -> what of the carried state it shapes (first match)
    "env.": "the task of the stored transitions and the pool",
    "agent.": "the networks, normalisers and optimisers",
    "buffer.": "the replay buffer",
    "her.": "the relabelled transitions stored",
    "noise.": "the stored observations",
    "algo.goal_generator": "the HGG pool",
    "hgg.": "the HGG pool",
    "train.": "the loop that wrote the source's rows",
    "eval.": "the evaluations in the source's rows",
}
_ABSENT = "<absent>"


@dataclass
class Fork:
    """What :func:`prepare` found: the source, its checkpoint and the settings the fork changes."""

    source: Path
    state: dict[str, Any] = field(repr=False)
    changes: dict[str, tuple[Any, Any]]  # setting -> (source's value, fork's value)

    @property
    def iteration(self) -> int:
        return int(self.state["iteration"])

    @property
    def renews_streams(self) -> bool:
        return "seed" in self.changes

    @property
    def renews_sampler(self) -> bool:
        return any(_matches(key, SAMPLER) for key in self.changes)

    def record(self) -> dict[str, Any]:
        """``fork.yaml``'s contents."""
        seed = self.changes.get("seed", (None, None))[1]
        return {
            "source": str(self.source),
            "source_iteration": self.iteration,
            "changed": {key: {"source": old, "fork": new} for key, (old, new) in self.changes.items()},
            "random_streams": f"new, from seed {seed}" if self.renews_streams else "carried over (the source's seed)",
            "sampler": "new" if self.renews_sampler else "carried over (its settings and the seed unchanged)",
        }


def _matches(key: str, patterns: tuple[str, ...]) -> bool:
    return any(key == p or (p.endswith("*") and fnmatchcase(key, p)) for p in patterns)


def _flatten(node: dict, prefix: str = "") -> dict[str, Any]:
    out = {}
    for key, value in node.items():
        if isinstance(value, dict):
            out.update(_flatten(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def changed_settings(source: dict, fork: dict) -> dict[str, tuple[Any, Any]]:
    """The resolved settings (dotted keys) whose values differ: ``{key: (source's, fork's)}``; a key
    one side lacks has the value ``"<absent>"`` there."""
    a, b = _flatten(source), _flatten(fork)
    keys = list(dict.fromkeys([*a, *b]))
    return {k: (a.get(k, _ABSENT), b.get(k, _ABSENT)) for k in keys if a.get(k, _ABSENT) != b.get(k, _ABSENT)}


def prepare(cfg: DictConfig, run_dir: Path, checkpoint_name: str) -> Fork:
    """Check that ``cfg`` may fork ``cfg.init_from`` into ``run_dir``, before anything is built.

    Raises:
        ValueError: ``init_from`` is not another run's folder with a config and checkpoint; a setting
            outside :data:`MAY_DIFFER` differs (all such named, with both values); the source has
            background evaluations in flight or no replay files; ``train.iterations`` does not
            exceed the source's iteration.
    """
    source = Path(str(cfg.init_from)).expanduser().resolve()
    if source == Path(run_dir).resolve():
        raise ValueError(f"init_from must be another run's folder, got this run's own folder {source}")
    for name in (SOURCE_CONFIG, checkpoint_name):
        if not (source / name).is_file():
            raise ValueError(
                f"init_from must be a run folder holding {SOURCE_CONFIG} and {checkpoint_name}, "
                f"got {cfg.init_from!r}, which has no {name}"
            )
    mine = {k: v for k, v in OmegaConf.to_container(cfg, resolve=True).items() if k != "hydra"}
    theirs = OmegaConf.to_container(OmegaConf.load(source / SOURCE_CONFIG), resolve=True)
    changes = {k: v for k, v in changed_settings(theirs, mine).items() if k not in NOT_LISTED}
    refused = {k: v for k, v in changes.items() if not _matches(k, MAY_DIFFER)}
    if refused:
        details = "; ".join(
            f"{key}: {old!r} in the source, {new!r} here"
            + next((f" ({why})" for prefix, why in WHY.items() if key.startswith(prefix)), "")
            + (f" (a setting added since the source ran: ~{key} drops it here if its absence reads as the "
               "source's behaviour)" if old == _ABSENT else "")
            for key, (old, new) in refused.items()
        )
        raise ValueError(
            f"init_from={source}: a fork must keep the source's settings that shape the state it takes over, "
            f"and these differ: {details}. Settings a fork may change: {', '.join(MAY_DIFFER)}"
        )
    fork = Fork(source, checkpoint.load(source / checkpoint_name), changes)
    if fork.state.get("eval_pending"):
        pending = sorted(iteration for iteration, _ in fork.state["eval_pending"])
        raise ValueError(
            f"init_from={source}: its checkpoint has evaluations of iterations {pending} in flight "
            "(eval.background=true); resume the source until they are back, then fork it"
        )
    if "replay" not in fork.state:
        raise ValueError(f"init_from={source}: its checkpoint holds the replay rows itself (an older format "
                         "without replay/ files), which a fork cannot take over")  # fmt: skip
    if cfg.train.iterations <= fork.iteration:
        raise ValueError(
            f"train.iterations must exceed the iteration the fork starts from ({fork.iteration}, the last "
            f"checkpoint of {source}), got train.iterations={cfg.train.iterations}"
        )
    return fork


def check_resume(cfg: DictConfig, run_dir: Path) -> None:
    """Refuse to resume ``run_dir`` with ``init_from`` set unless it holds a fork of that source.

    Raises:
        ValueError: the folder's ``fork.yaml`` records another source, or there is none (the folder
            holds a run that is not a fork).
    """
    source = Path(str(cfg.init_from)).expanduser().resolve()
    record = Path(run_dir) / RECORD
    recorded = OmegaConf.load(record).get("source") if record.is_file() else None
    if recorded is None or Path(recorded) != source:
        holds = f"a fork of {recorded}" if recorded else "a run that is not a fork"
        raise ValueError(
            f"init_from={source}: run folder {run_dir} already holds {holds}; resume it with that init_from "
            f"(or init_from=null), or fork into another folder (hydra.run.dir / hydra.sweep.dir)"
        )


def start(fork: Fork, trainer) -> dict[str, Any]:
    """Load the source's state into ``trainer`` (built from the fork's config in its own, fresh run
    folder), with the sampler and random streams renewed as the module docstring says; write
    ``fork.yaml`` and log what changed. Returns the record. The caller saves the first checkpoint."""
    fresh = trainer.state_dict()  # the new streams and sampler: a run with the fork's settings, at its start
    state = dict(fork.state, run=fresh["run"], buffer=dict(fork.state["buffer"]))
    if fork.renews_streams:
        state.update({key: fresh[key] for key in STREAMS})
        state["buffer"]["_rng"] = fresh["buffer"]["_rng"]
    if fork.renews_sampler:
        state["buffer"]["_sampler"] = fresh["buffer"]["_sampler"]
        state["tradeoff"] = fresh["tradeoff"]
    link_replay(fork.source / trainer.replay_log.folder.name, trainer.replay_log.folder, state["replay"])
    trainer.load_state_dict(state)
    generator = trainer.goal_generator
    if fork.renews_sampler and generator is not None and generator.stopped and trainer.cfg.algo.sampler == "curriculum":
        trainer.sampler.stop_curriculum()  # HGG stopped in the source: the new sampler stops its curriculum too
    record = fork.record()
    files.write_text(trainer.run_dir / RECORD, OmegaConf.to_yaml(OmegaConf.create(record)))  # atomic
    changes = ", ".join(f"{k}: {old!r} -> {new!r}" for k, (old, new) in fork.changes.items()) or "none"
    message = (
        f"forked from {fork.source} after iteration {fork.iteration - 1}: this run starts at iteration "
        f"{fork.iteration}; changed settings: {changes}; random streams {record['random_streams']}; "
        f"sampler {record['sampler']} ({trainer.run_dir / RECORD})"
    )
    log.info(message)  # on the console and in train.log under Hydra
    return record


def link_replay(source: Path, folder: Path, names: list[str]) -> None:
    """Hard-link (else copy) the replay files ``names`` from ``source`` into ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        if not (source / name).is_file():
            raise FileNotFoundError(f"replay file {source / name} is missing: the source's checkpoint lists it")
        (folder / name).unlink(missing_ok=True)
        try:
            os.link(source / name, folder / name)
        except OSError:  # another file system, or links not allowed
            try:
                with files.naming_disk_full(folder / name, "replay file"):
                    shutil.copy2(source / name, folder / name)
            except BaseException:
                (folder / name).unlink(missing_ok=True)  # no partial copy
                raise
