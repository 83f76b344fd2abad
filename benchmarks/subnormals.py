"""DDPG updates with Adam's subnormal moments kept against flushed to zero (``subnormals=keep`` / ``flush``).

For each agent it prints the share of subnormal entries in each optimiser's moments, times ``--updates``
updates from the same state once with each setting, in ``--rounds`` alternating rounds (the median of
the rounds' ratios), and says whether the networks and losses after them are the same bit for bit.

The agents: first a push_new-sized one (3 x 256) after 200 updates on random batches, with a share
``--dead`` of each hidden layer's units made dead (they never fire, so their weights get zero gradients)
and those weights' moments set into the subnormal range, as a long run leaves them; then, with
``--run <run folder>``, a training run's own agent and data: its checkpoint and replay files are copied
to a temporary folder (the run may be going on), a trainer is built from the run's Hydra overrides
(``.hydra/overrides.yaml``) and loaded from them, and the batches are drawn from its buffer.

    python benchmarks/subnormals.py [--run RUN_FOLDER] [--updates 300] [--rounds 3] [--dead 0.05]"""

from __future__ import annotations

import argparse
import copy
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "benchmarks")]  # run from a checkout
os.environ.setdefault("MUJOCO_GL", "disable")
os.environ.setdefault("RL_LOGGING_LEVEL", "WARNING")

import torch  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402
from tensordict import TensorDict  # noqa: E402

from gchgg.ddpg.agent import DDPGAgent  # noqa: E402
from gchgg.fast.subnormal import subnormal_share  # noqa: E402

SUBNORMAL = 1e-39  # below float32's smallest normal number


def moments(agent: DDPGAgent) -> dict[str, list[torch.Tensor]]:
    """Each optimiser's Adam moments (``exp_avg`` and ``exp_avg_sq`` of every parameter)."""
    return {name: [state[key] for state in optimizer.state.values() for key in ("exp_avg", "exp_avg_sq")]
            for name, optimizer in (("actor", agent.actor_optimizer), ("critic", agent.critic_optimizer))}  # fmt: skip


def from_run(folder: Path, work: Path, updates: int) -> tuple[DDPGAgent, list[TensorDict], str]:
    """The agent of the run in ``folder`` as its checkpoint left it, batches from its buffer, and a description."""
    from hydra import compose, initialize_config_dir

    from gchgg.run import checkpoint
    from gchgg.train import CHECKPOINT, CONF_DIR, REPLAY, Trainer

    overrides = folder / ".hydra" / "overrides.yaml"
    for needed in (folder / CHECKPOINT, folder / REPLAY, overrides):
        if not needed.exists():
            raise SystemExit(f"--run {folder}: no {needed.name} there; give the folder of a run started with "
                             "python -m gchgg.train (it holds checkpoint.pt, replay/ and .hydra/)")
    shutil.copy(folder / CHECKPOINT, work / CHECKPOINT)
    shutil.copytree(folder / REPLAY, work / REPLAY)
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", overrides=[*OmegaConf.load(overrides), "resume=true", "logging.progress=false"])
    trainer = Trainer(cfg, work)
    trainer.load_state_dict(checkpoint.load(work / CHECKPOINT))
    agent = trainer.agent
    batches = [trainer.buffer.sample() for _ in range(updates)]
    described = (f"run {folder.name} ({cfg.env.name}, {cfg.algo.name}, seed {cfg.seed}) after iteration "
                 f"{trainer.iteration - 1}, {agent.num_updates:,} updates; precision={agent.precision}, "
                 f"gradients={agent.gradients}; batches of {cfg.train.batch_size} from its buffer")  # fmt: skip
    trainer.evaluations.close()
    return agent, batches, described


def random_batches(n: int, generator: torch.Generator, obs_dim: int = 25, goal_dim: int = 3, action_dim: int = 3):
    def batch():
        obs = torch.randn(256, obs_dim, generator=generator)
        return TensorDict({
            "observation": obs, "desired_goal": torch.randn(256, goal_dim, generator=generator),
            "action": torch.rand(256, action_dim, generator=generator) * 2 - 1,
            "next": {"observation": obs + 0.1 * torch.randn(256, obs_dim, generator=generator),
                     "reward": -(torch.rand(256, 1, generator=generator) < 0.8).float()},
        }, [256])  # fmt: skip

    return [batch() for _ in range(n)]


def synthetic(dead: float, updates: int) -> tuple[DDPGAgent, list[TensorDict], str]:
    """A push_new-sized agent after 200 updates with ``dead`` of each hidden layer's units dead and the
    moments of their weights (in, bias and out) subnormal."""
    g = torch.Generator().manual_seed(0)
    agent = DDPGAgent(25, 3, 3, generator=g, precision="float32", subnormals="keep")
    for batch in random_batches(200, g):
        agent.update(batch)
    for network, optimizer in ((agent.actor, agent.actor_optimizer), (agent.critic, agent.critic_optimizer)):
        layers = [m for m in network.modules() if isinstance(m, torch.nn.Linear)]
        for layer, after in zip(layers[:-1], layers[1:], strict=True):
            units = torch.randperm(layer.out_features, generator=g)[: round(dead * layer.out_features)]
            with torch.no_grad():
                layer.bias[units] = -1000.0  # never fires
            for parameter, rows in ((layer.weight, units), (layer.bias, units)):
                for key in ("exp_avg", "exp_avg_sq"):
                    optimizer.state[parameter][key][rows] = SUBNORMAL
            for key in ("exp_avg", "exp_avg_sq"):
                optimizer.state[after.weight][key][:, units] = SUBNORMAL
    described = (f"a push_new-sized agent (3 x 256, float32) after 200 updates, {dead:.0%} of each hidden "
                 "layer's units dead and their weights' moments subnormal; random batches of 256")
    return agent, random_batches(updates, g), described


def measure(start: DDPGAgent, batches: list[TensorDict], described: str, rounds: int) -> None:
    """Prints the shares of subnormal moments of ``start`` and its updates on ``batches`` with each setting."""
    print(described)
    shares = {name: subnormal_share(tensors) for name, tensors in moments(start).items()}
    print("  subnormal entries of the Adam moments: " + ", ".join(f"{k} {v:.1%}" for k, v in shares.items()))
    saved = copy.deepcopy(start.state_dict())
    seconds: dict[str, list[float]] = {"keep": [], "flush": []}
    after = {}
    for _ in range(rounds):
        for mode in seconds:
            start.load_state_dict(copy.deepcopy(saved))
            start.subnormals = mode
            begin = time.perf_counter()
            losses = [start.update(batch) for batch in batches]
            seconds[mode].append((time.perf_counter() - begin) / len(batches))
            after[mode] = [p.detach().clone() for p in start.loss_module.parameters()], losses
    keep, flush = (statistics.median(seconds[m]) * 1e3 for m in ("keep", "flush"))
    ratios = [k / f for k, f in zip(seconds["keep"], seconds["flush"], strict=True)]
    same = (after["keep"][1] == after["flush"][1]
            and all(torch.equal(a, b) for a, b in zip(after["keep"][0], after["flush"][0], strict=True)))
    print(f"  subnormals=keep {keep:.2f} ms/update, flush {flush:.2f} ms/update: keep / flush = "
          f"{statistics.median(ratios):.2f} (median of {rounds} alternating rounds of {len(batches)} updates: "
          f"{', '.join(f'{r:.2f}' for r in ratios)})")
    print(f"  networks (online and target) and losses after the updates the same bit for bit: {same}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", default=None, help="also a training run's folder")
    parser.add_argument("--updates", type=int, default=300, help="updates per round")
    parser.add_argument("--rounds", type=int, default=3, help="alternating rounds of keep and flush")
    parser.add_argument("--dead", type=float, default=0.05, help="share of dead units in the synthetic agent")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(f"threads={args.threads}")
    measure(*synthetic(args.dead, args.updates), args.rounds)
    if args.run is not None:
        with tempfile.TemporaryDirectory() as work:
            run_agent, batches, described = from_run(Path(args.run), Path(work), args.updates)
        measure(run_agent, batches, described, args.rounds)


if __name__ == "__main__":
    from report import run  # prints, and with --docs writes docs/benchmarks.md

    run(main, __file__)
