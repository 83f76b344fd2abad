"""Export a trained policy for a robot: ``python -m gchgg.export RUN --format onnx|torchscript --out FILE``.

The file holds the actor with its observation and goal normalisers folded in: input
``(observation [B, obs_dim], goal [B, 3])`` float32, output ``action [B, A]`` in [−1, 1]. A
metadata file beside it (``FILE.json``) says what a controller needs to use it without gchgg:
the task, the observation layout (named slices), what the action means and its scale, the
control rate, and the checkpoint it came from. ``examples/run_policy.py`` drives a task with it
using onnxruntime (or plain torch for TorchScript) and numpy only.

    python -m gchgg.analysis.export outputs/push_new/gchgg/seed0 --format onnx --out push_new.onnx
"""

from __future__ import annotations

import argparse
import json
import os
import warnings
from pathlib import Path

import torch
from torch import nn

__all__ = ["FORMATS", "export", "metadata"]

FORMATS = ("onnx", "torchscript")
ACTION_SCALE = 0.05  # metres of grip motion per unit action per control step (envs.kuka)
CONTROL_HZ = 20  # control steps per second (envs.kuka: 0.05 s)


class _Policy(nn.Module):
    """``action = actor(observation, goal)``: the deterministic policy, normalisation included."""

    def __init__(self, actor: nn.Module) -> None:
        super().__init__()
        self.actor = actor

    def forward(self, observation: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
        return self.actor(observation, goal)


def metadata(saved: dict, source: str, fmt: str) -> dict:
    """What a controller needs besides the weights (see the module docstring)."""
    import envs

    task, hparams = saved["task"], saved["policy"]["hparams"]
    layout = envs.observation_layout(task)
    action = ["grip dx", "grip dy", "grip dz"] + (
        ["gripper (+1 open, -1 closed)"] if hparams["action_dim"] == 4 else []
    )
    return {
        "task": task,
        "format": fmt,
        "inputs": {"observation": [None, hparams["obs_dim"]], "goal": [None, hparams["goal_dim"]]},
        "output": {"action": [None, hparams["action_dim"]], "range": [-1.0, 1.0]},
        "observation_layout": {name: [s.start, s.stop] for name, s in layout.items()},
        "goal": "desired position of the object (or of the grip in reach), metres, world frame",
        "action": action,
        "action_scale_m_per_unit": ACTION_SCALE,
        "gripper": "action[3] > 0 opens, < 0 closes" if hparams["action_dim"] == 4 else "held closed",
        "control_rate_hz": CONTROL_HZ,
        "success_threshold_m": saved["threshold"],
        "checkpoint": {"source": source, "iteration": saved["iteration"] - 1},
    }


def export(run_dir: str | os.PathLike, fmt: str, out: str | os.PathLike) -> Path:
    """Writes the run's policy to ``out`` in format ``fmt`` and its metadata to ``out`` + ``.json``.

    Raises:
        FileNotFoundError: the run has no ``policy.pt`` (it has not checkpointed yet).
        ValueError: an unknown format.
    """
    from gchgg.analysis.evaluate import load_policy_file
    from gchgg.ddpg.agent import load_policy

    if fmt not in FORMATS:
        raise ValueError(f"format must be one of {FORMATS}, got {fmt!r}")
    saved = load_policy_file(run_dir)
    policy = _Policy(load_policy(saved["policy"], matmul="default")).eval()  # plain layers to trace
    h = saved["policy"]["hparams"]
    example = (torch.zeros(1, h["obs_dim"]), torch.zeros(1, h["goal_dim"]))
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with torch.no_grad(), warnings.catch_warnings():
        # torch 2.13 marks TorchScript as deprecated, and the ONNX exporter warns about the shared
        # batch axis of the two inputs; both files are as intended (tests check their outputs).
        warnings.simplefilter("ignore", DeprecationWarning)
        warnings.filterwarnings("ignore", message=".*axis name")
        if fmt == "torchscript":
            torch.jit.save(torch.jit.trace(policy, example), str(out))
        else:
            batch = torch.export.Dim("batch")
            torch.onnx.export(
                policy,
                example,
                str(out),
                input_names=["observation", "goal"],
                output_names=["action"],
                dynamic_shapes=({0: batch}, {0: batch}),
                dynamo=True,
                external_data=False,  # one self-contained file
                verbose=False,
            )
    meta = metadata(saved, str(Path(run_dir).resolve()), fmt)
    Path(f"{out}.json").write_text(json.dumps(meta, indent=1))
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", help="a training run folder (holding policy.pt), or a policy.pt file")
    parser.add_argument("--format", choices=FORMATS, default="onnx")
    parser.add_argument("--out", required=True, help="the exported file (metadata goes to OUT.json)")
    args = parser.parse_args(argv)
    os.environ.setdefault("MUJOCO_GL", "disable")
    path = export(args.run_dir, args.format, args.out)
    print(f"wrote {path} and {path}.json")


if __name__ == "__main__":
    main()
