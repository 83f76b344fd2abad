"""Checkpoints: atomic, checksummed files that a run killed at any moment leaves intact, and the parts' state.

A checkpoint file is a small header (magic, SHA-256 of the payload, payload length) followed by a
``torch.save`` payload. :func:`save` writes to a temporary file in the same folder, flushes it to
disk and renames it over the old checkpoint, so a reader sees either the previous checkpoint or the
new one, never a partial file. :func:`load` verifies the header and the checksum and raises
:class:`CorruptCheckpointError` when anything does not match.

:func:`check_identity` refuses to resume another run's checkpoint; :func:`save_policy` writes the
actor alone beside each checkpoint. :func:`parts_state` and :func:`load_parts_state` are what a
run's checkpoint holds of its parts (:class:`gchgg.parts.Parts`): the agent, the buffer's sampler,
writer and generator states and its storage's length (the rows are in the replay files,
:mod:`gchgg.replay_log`), the trade-off, the goal generator, and every random stream and env state;
the trainer adds the loop's own state.
"""

from __future__ import annotations

import hashlib
import io
import os
import struct
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from omegaconf import OmegaConf

from gchgg.evaluator import env_state

if TYPE_CHECKING:
    from gchgg.parts import Parts
    from gchgg.replay_log import ReplayLog

_MAGIC = b"GCHGGCK1"
_HEADER = struct.Struct("<8s32sQ")  # magic, sha256 digest, payload length


class CorruptCheckpointError(RuntimeError):
    """The checkpoint file is truncated, altered or not a gchgg checkpoint."""


def save(state: dict[str, Any], path: str | os.PathLike, *, mode: int | None = None) -> None:
    """Write ``state`` to ``path`` atomically (temporary file + fsync + rename); ``mode`` sets the
    file's permissions (default: the temporary file's 0600)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    buffer = io.BytesIO()
    torch.save(state, buffer)
    payload = buffer.getbuffer()
    header = _HEADER.pack(_MAGIC, hashlib.sha256(payload).digest(), len(payload))
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(header)
            f.write(payload)
            f.flush()
            os.fsync(f.fileno())
        if mode is not None:
            os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def remove_temporaries(folder: str | os.PathLike) -> list[Path]:
    """Delete the temporary files that saves killed before their rename left in ``folder`` (a SIGKILL
    runs no cleanup); returns them. Only files named as :func:`save` names its temporaries go."""
    folder = Path(folder)
    stale = sorted(folder.glob(".*.tmp")) if folder.is_dir() else []
    for path in stale:
        path.unlink(missing_ok=True)
    return stale


def load(path: str | os.PathLike) -> dict[str, Any]:
    """Read a checkpoint written by :func:`save`, verifying its checksum.

    Raises:
        FileNotFoundError: there is no file at ``path``.
        CorruptCheckpointError: the file is truncated, altered or not a gchgg checkpoint.
    """
    path = Path(path)
    data = path.read_bytes()
    if len(data) < _HEADER.size:
        raise CorruptCheckpointError(f"checkpoint {path} is corrupt: {len(data)} bytes, shorter than its header")
    magic, digest, length = _HEADER.unpack_from(data)
    payload = memoryview(data)[_HEADER.size :]
    if magic != _MAGIC:
        raise CorruptCheckpointError(f"checkpoint {path} is corrupt: not a gchgg checkpoint (bad magic {magic!r})")
    if len(payload) != length:
        raise CorruptCheckpointError(
            f"checkpoint {path} is corrupt: payload has {len(payload)} bytes, header says {length} (truncated?)"
        )
    if hashlib.sha256(payload).digest() != digest:
        raise CorruptCheckpointError(f"checkpoint {path} is corrupt: checksum mismatch")
    return torch.load(io.BytesIO(payload), weights_only=False)


def parts_state(parts: Parts, evaluation: dict | None = None) -> dict[str, Any]:
    """The parts' states, replay rows aside; ``evaluation``: the eval env's state before the background
    evaluations in flight (:func:`gchgg.evaluator.env_state`; default: the eval env's state now)."""
    buffer = parts.buffer.state_dict()
    storage = buffer["_storage"]
    buffer["_storage"] = {"initialized": storage["initialized"], "_len": storage["_len"]}  # the rows: replay files
    evaluation = evaluation or env_state(parts.eval_env, parts.noise_generators.get("eval_env"))
    noise_rng = {name: g.get_state() for name, g in parts.noise_generators.items()}
    if "eval_env" in noise_rng:
        noise_rng["eval_env"] = evaluation["noise"]
    return {
        "agent": parts.agent.state_dict(),
        "buffer": buffer,
        "tradeoff": None if parts.tradeoff is None else parts.tradeoff.state_dict(),
        "goal_generator": None if parts.goal_generator is None else parts.goal_generator.state_dict(),
        "her_rng": parts.relabel[-1].generator.get_state(),
        "explore_rng": parts.streams["explore"].get_state(),
        "torch_rng": torch.get_rng_state(),
        "env_random": parts.env.random_state(),
        "eval_env_random": evaluation["random"],
        "noise_rng": noise_rng,
    }


def load_parts_state(parts: Parts, state: dict[str, Any], replay_log: ReplayLog) -> None:
    """Restore :func:`parts_state`'s output; the buffer's rows from the replay files ``state["replay"]`` lists
    (checked against the stored length: :class:`CorruptCheckpointError` if they differ)."""
    parts.agent.load_state_dict(state["agent"])
    buffer = dict(state["buffer"])
    if "replay" in state:  # incremental checkpoint: the rows come from the replay files
        replay_log.restore(state["replay"], parts.buffer.storage)
        restored = parts.buffer.storage.state_dict()
        if restored["_len"] != buffer["_storage"]["_len"]:
            raise CorruptCheckpointError(
                f"the replay files in {replay_log.folder} hold {restored['_len']} rows, the checkpoint "
                f"says {buffer['_storage']['_len']}"
            )
        buffer["_storage"] = restored
    parts.buffer.load_state_dict(buffer)
    if parts.tradeoff is not None:
        parts.tradeoff.load_state_dict(state["tradeoff"])
    if parts.goal_generator is not None:
        parts.goal_generator.load_state_dict(state["goal_generator"])  # the sampler's state knows if it stopped
    parts.relabel[-1].generator.set_state(state["her_rng"])
    parts.streams["explore"].set_state(state["explore_rng"])
    torch.set_rng_state(state["torch_rng"])
    parts.env.set_random_state(state["env_random"])
    parts.eval_env.set_random_state(state["eval_env_random"])
    for name, generator in parts.noise_generators.items():
        generator.set_state(state["noise_rng"][name])


def check_identity(saved: dict | None, identity: dict, run_dir: Path) -> None:
    """Refuse a checkpoint whose ``run`` entry (``saved``) is not this run's ``identity``, naming each
    difference; a checkpoint from before ``precision`` was recorded counts as float32."""
    if saved is None:
        return
    saved = {"precision": "float32", **saved}
    if saved != identity:
        differences = ", ".join(f"{key}: checkpoint {saved.get(key)!r}, this run {value!r}"
                                for key, value in identity.items() if saved.get(key) != value)
        raise ValueError(f"the checkpoint in {run_dir} belongs to another run ({differences}); "
                         "resume it with its own settings, or start this one in another folder")


def save_policy(path: Path, cfg, iteration: int, agent) -> None:
    """The policy snapshot (task, threshold, config and actor: what evaluation and export load)."""
    save({"iteration": iteration, "task": cfg.env.name, "threshold": float(cfg.env.threshold),
          "config": OmegaConf.to_container(cfg, resolve=True), "policy": agent.policy_state()}, path)
