"""Evaluate and watch a trained policy: ``python -m gchgg.analysis.evaluate RUN_DIR [--episodes N] [--video FILE]``.

Loads only the run's ``policy.pt`` (the actor and its normalisers, written beside every checkpoint;
never the replay buffer, so it starts in seconds for any run), runs ``--episodes`` deterministic
episodes on the task's own target goals and prints the success rate (``is_success`` at the last
step, as the training's evaluation) and the mean final distance to the goal. ``--video`` records
the first ``--video-episodes`` episodes through MuJoCo's offscreen renderer (``MUJOCO_GL=egl``, the
default here, or ``osmesa``) with the goal marked (the green sphere), as MP4 or GIF via imageio.

    python -m gchgg.analysis.evaluate outputs/reach/her/seed0 --episodes 100 --video reach.mp4 --camera front
    python -m gchgg.analysis.evaluate outputs/push_new/gchgg/seed0 --noise 0.01    # a camera's error on the object
"""

from __future__ import annotations

import argparse
import os
import sys
from dataclasses import dataclass
from pathlib import Path

CAMERAS = ("front", "side", "top")


@dataclass
class Evaluation:
    """Success rate and mean final goal distance (metres) over ``episodes`` episodes."""

    success_rate: float
    final_distance: float
    episodes: int


def load_policy_file(run_dir: str | Path) -> dict:
    """The run's ``policy.pt`` (see :meth:`gchgg.train.Trainer.save`), checked.

    A run written before runs saved ``policy.pt`` has only ``checkpoint.pt``: its policy is then
    read from the full checkpoint (slow: the replay buffer is read too) and its ``config.yaml``.
    """
    from gchgg.run import checkpoint

    path = Path(run_dir)
    folder = path if path.is_dir() else path.parent
    path = path / "policy.pt" if path.is_dir() else path
    if path.is_file():
        return checkpoint.load(path)
    if path.name == "policy.pt" and (folder / "checkpoint.pt").is_file() and (folder / "config.yaml").is_file():
        return _policy_from_checkpoint(folder)
    raise FileNotFoundError(
        f"no policy at {path}: pass a run folder written by `python -m gchgg.train` after at least one "
        f"checkpoint (runs save policy.pt beside checkpoint.pt)"
    )


def _policy_from_checkpoint(folder: Path) -> dict:
    """What ``policy.pt`` would hold, from an older run's ``checkpoint.pt`` and ``config.yaml``."""
    from omegaconf import OmegaConf

    from gchgg.ddpg.agent import DDPGAgent
    from gchgg.run import checkpoint

    state = checkpoint.load(folder / "checkpoint.pt")
    config = OmegaConf.to_container(OmegaConf.load(folder / "config.yaml"), resolve=True)
    hparams = dict(state["agent"]["hparams"])
    dims = [hparams.pop(k) for k in ("obs_dim", "goal_dim", "action_dim")]
    agent = DDPGAgent(*dims, **hparams)
    agent.load_state_dict(state["agent"])
    return {
        "iteration": state["iteration"],
        "task": config["env"]["name"],
        "threshold": float(config["env"]["threshold"]),
        "config": config,
        "policy": agent.policy_state(),
    }


def evaluate_policy(
    actor, task: str, episodes: int = 100, seed: int = 0, threshold: float = 0.05, num_envs: int = 100,
    noise_std: float = 0.0, start: str = "original",
) -> Evaluation:
    """Deterministic episodes of ``actor(observation, goal)`` on ``task``'s target goals.

    Runs ``episodes`` episodes in batches of ``num_envs`` simulations, batch ``b`` seeded ``seed + b``
    (:func:`envs.episode_seeds` gives each episode's task seed). With ``noise_std`` the policy sees
    the observed object position (and object-relative position; the grip in reach) with
    N(0, noise_std²) noise, drawn from a generator seeded ``seed``; success is that of the true state.
    ``start`` is the task's start state (``envs.make``'s option; the run's ``env.start``).
    """
    import torch
    from torchrl.envs import TransformedEnv

    import envs
    from gchgg.run.builders import make_observation_noise
    from gchgg.run.rollout import collect, fraction

    generator = torch.Generator().manual_seed(seed)

    done, successes, distances = 0, [], []
    batch = 0
    while done < episodes:
        n = min(num_envs, episodes - done)
        env = envs.make(task, num_envs=n, seed=seed + batch, threshold=threshold, start=start)
        if noise_std:
            env = TransformedEnv(
                env, make_observation_noise(envs.observation_layout(task), env.has_object, noise_std, generator)
            )
        with torch.inference_mode():
            rollout = collect(env, actor, env.geometry.episode_length, env.reset())
        successes.append(rollout["next", "is_success"][:, -1].reshape(-1))
        final = rollout["next", "true_achieved_goal" if noise_std else "achieved_goal"][:, -1]
        distances.append(torch.linalg.vector_norm(final - rollout["desired_goal"][:, -1], dim=-1))
        done, batch = done + n, batch + 1
    return Evaluation(fraction(torch.cat(successes)), float(torch.cat(distances).mean()), episodes)


def record(actor, task: str, path: str | Path, *, episodes: int = 1, seed: int = 0, camera: str = "front",
           size: tuple[int, int] = (240, 320), every: int = 1, fps: int = 20, threshold: float = 0.05,
           start: str = "original") -> int:
    """Renders ``episodes`` deterministic episodes of ``actor`` on ``task`` into a video file
    (``.mp4`` or ``.gif``; every ``every``-th control step at ``fps``). Returns the number of frames.

    Raises:
        RuntimeError: no OpenGL backend can render (names ``MUJOCO_GL``).
        ValueError: an unknown camera or file type.
    """
    import numpy as np
    import torch

    import envs

    if camera not in CAMERAS:
        raise ValueError(f"camera must be one of {CAMERAS}, got {camera!r}")
    suffix = Path(path).suffix.lower()
    if suffix not in (".mp4", ".gif"):
        raise ValueError(f"video must be a .mp4 or .gif file, got {str(path)!r}")
    try:
        import imageio.v3 as iio
    except ImportError:
        raise ImportError('recording needs imageio (and imageio-ffmpeg for MP4): pip install -e ".[video]"') from None
    env = envs.make(task, num_envs=episodes, seed=seed, threshold=threshold, start=start)
    height, width = size

    def frame() -> list[np.ndarray]:
        try:
            return [physics.render(height, width, camera_id=camera) for physics in env.physics]
        except Exception as error:  # dm_control raises several kinds when no GL context can be made
            raise RuntimeError(
                f"MuJoCo could not render ({type(error).__name__}: {error}). Set MUJOCO_GL=egl (offscreen, "
                f"GPU or Mesa) or MUJOCO_GL=osmesa (software) before starting Python; MUJOCO_GL is now "
                f"{os.environ.get('MUJOCO_GL')!r}"
            ) from error

    frames: list[list[np.ndarray]] = []
    td = env.reset()
    frames.append(frame())
    with torch.inference_mode():
        for step in range(env.geometry.episode_length):
            td.set("action", actor(td["observation"], td["desired_goal"]))
            td = env.step(td)["next"].exclude("reward", "done", "terminated", "truncated")
            if (step + 1) % every == 0:
                frames.append(frame())
    video = np.stack([f[i] for i in range(episodes) for f in frames])  # episode after episode
    if suffix == ".gif":
        iio.imwrite(path, video, duration=1000 / fps, loop=0)
    else:
        iio.imwrite(path, video, fps=fps, codec="libx264")
    return len(video)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", help="a training run folder (holding policy.pt), or a policy.pt file")
    parser.add_argument("--episodes", type=int, default=100, help="evaluation episodes (default 100)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the evaluation goals")
    parser.add_argument("--noise", type=float, default=0.0, help="std (m) of noise on the observed object position")
    parser.add_argument("--video", help="record episodes into this .mp4 or .gif file")
    parser.add_argument("--video-episodes", type=int, default=2, help="episodes recorded (default 2)")
    parser.add_argument("--camera", choices=CAMERAS, default="front")
    args = parser.parse_args(argv)
    if args.episodes < 1 or args.video_episodes < 1:
        parser.error("--episodes and --video-episodes must be >= 1")
    # The GL backend is chosen when MuJoCo's renderer is first imported: set it before any import.
    os.environ.setdefault("MUJOCO_GL", "egl" if args.video else "disable")
    os.environ.setdefault("RL_LOGGING_LEVEL", "WARNING")

    from gchgg.ddpg.agent import load_policy

    saved = load_policy_file(args.run_dir)
    actor = load_policy(saved["policy"])
    task, threshold = saved["task"], saved["threshold"]
    start = saved.get("config", {}).get("env", {}).get("start", "original")  # runs before Dec 2026: "original"
    result = evaluate_policy(actor, task, args.episodes, args.seed, threshold, noise_std=args.noise, start=start)
    print(
        f"{task}: success rate {result.success_rate:.3f}, mean final distance {result.final_distance:.4f} m "
        f"over {result.episodes} episodes (policy of iteration {saved['iteration'] - 1}, seed {args.seed}, "
        f"observation noise {args.noise:g} m)"
    )
    if args.video:
        frames = record(actor, task, args.video, episodes=args.video_episodes, seed=args.seed, camera=args.camera,
                        threshold=threshold, start=start)
        print(f"wrote {args.video} ({frames} frames, camera {args.camera})")


if __name__ == "__main__":
    main(sys.argv[1:])
