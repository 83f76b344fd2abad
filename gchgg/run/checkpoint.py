"""Checkpoints: what a run's checkpoint holds of its parts, and the checks before a run resumes from one.

The file itself is written and read by :mod:`gchgg.common.files` (atomic, checksummed; re-exported
here as :func:`save`, :func:`load` and :class:`CorruptCheckpointError`).

:func:`check_identity` refuses to resume another run's checkpoint; :func:`save_policy` writes the
actor alone beside each checkpoint. :func:`parts_state` and :func:`load_parts_state` are what a
run's checkpoint holds of its parts (:class:`gchgg.run.parts.Parts`): the agent, the buffer's sampler,
writer and generator states and its storage's length (the rows are in the replay files,
:mod:`gchgg.run.replay_log`), the trade-off, the goal generator, and every random stream and env state;
the trainer adds the loop's own state.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from omegaconf import OmegaConf

from gchgg.common.files import CorruptCheckpointError, load, remove_temporaries, save
from gchgg.run.evaluator import env_state

if TYPE_CHECKING:
    from gchgg.run.parts import Parts
    from gchgg.run.replay_log import ReplayLog

__all__ = ["CorruptCheckpointError", "check_identity", "load", "load_parts_state", "parts_state",
           "remove_temporaries", "save", "save_policy"]


def parts_state(parts: Parts, evaluation: dict | None = None) -> dict[str, Any]:
    """The parts' states, replay rows aside; ``evaluation``: the eval env's state before the background
    evaluations in flight (:func:`gchgg.run.evaluator.env_state`; default: the eval env's state now)."""
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
