"""What the curriculum's choice changes in a batch: Algorithm 1's chosen batches against plain EBP batches.

    python docs/curriculum_choice.py RUN_DIR --iterations 20 40 60 [--tradeoff 50] [--samples 200]

Rebuilds a run's replay buffer as it stood after each of ``--iterations`` (from the run folder's
``replay/`` files, which a run keeps while any of their rows is live: up to ``buffer.episodes`` back),
then draws ``--samples`` mini-batches (the run's ``train.batch_size``) from it twice, with the
training loop's own sampler builder and the run's settings (``config.yaml``):

* **EBP**: one candidate per batch, drawn ∝ episode energy (HGG's and G-HGG's sampler, and GC-HGG's
  after HGG's stop);
* **curriculum**: the best of ``curriculum.num_candidates`` such candidates by F_div + λ·F_prox
  (Algorithm 1, GC-HGG before the stop), with λ the run's ``lambda`` at that iteration
  (``metrics.csv``), or ``--tradeoff``.

It prints, per iteration, the mean over the batches of each batch's

* ``own goal``: fraction of transitions that train on their episode's own goal (HER copy 0); the rest
  train on a relabelled goal, an achieved goal of the same episode;
* ``reward 0``: fraction whose reward is 0, i.e. whose next achieved goal reaches the goal it trains on
  (the only transitions that carry a success signal in a sparse task);
* ``reward 0 (own goal)``: the same among the transitions that train on their episode's own goal;
* ``goal > 2 cm up`` and ``goal > 10 cm up``: fraction whose training goal lies that far above the
  object's start height (``object_range``'s centre; tasks with an object only): in the pick tasks,
  goals that ask for a lift; ``reward 0, goal > 2 cm up``: fraction that reach such a goal (a lift's
  success signal);
* ``goal to target``: mean metric distance from the training goal to the episode's target-task goal
  (``-F_prox / B``, what the curriculum minimises);
* ``diversity decided``: fraction of batches where the chosen candidate is not the nearest one.

and, per statistic, the standard deviation of the EBP batches' values (how much one batch differs from
the next: the best of K i.i.d. candidates can move a statistic by about as many such deviations as
the mean of the largest of K standard normal draws, which the table's heading prints, and only where
the score follows that statistic), and curriculum minus EBP with its standard error
over the batches. ``--out FILE`` also writes the table into a Markdown file. The run can be
in progress: only replay files up to the iteration asked for are read. Any run's folder serves,
whatever sampler it trained with: the question is what each sampler would draw from the same buffer.
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import sys
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "disable")
os.environ.setdefault("RL_LOGGING_LEVEL", "WARNING")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout

import torch  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer  # noqa: E402

import envs  # noqa: E402
from gchgg.run import replay_log  # noqa: E402
from gchgg.run.builders import make_metric, make_sampler  # noqa: E402
from gchgg.run.config import CurriculumConfig, GraphConfig  # noqa: E402

STATS = ("own goal", "reward 0", "reward 0 (own goal)", "goal > 2 cm up", "goal > 10 cm up", "reward 0, goal > 2 cm up",
         "goal to target")


def load_buffer(run: Path, iteration: int, capacity: int) -> LazyTensorStorage:
    """The replay storage after ``iteration``: every replay file up to it, written in order."""
    files = sorted((run / "replay").glob("iteration-*.pt"))
    files = [f for f in files if int(f.stem.split("-")[1]) <= iteration]
    if not files or int(files[-1].stem.split("-")[1]) != iteration:
        raise SystemExit(f"{run / 'replay'} has no file for iteration {iteration} "
                         f"(it holds {len(files)} files up to it)")
    storage = LazyTensorStorage(capacity)
    for path in files:
        saved = replay_log.read(path)  # rows under today's key names
        storage.set(saved["index"], saved["rows"])
    return storage


def run_lambda(run: Path, iteration: int) -> float | None:
    """The run's λ at ``iteration`` (``metrics.csv``), ``None`` where it has none."""
    path = run / "metrics.csv"
    if not path.is_file():
        return None
    with path.open() as f:
        for row in csv.DictReader(f):
            if int(row["iteration"]) == iteration and row.get("lambda", ""):
                value = float(row["lambda"])
                return None if math.isnan(value) else value
    return None


def batch_stats(batch, start_height: float | None) -> dict[str, float]:
    """The statistics of one sampled batch (see the module docstring)."""
    own = (batch["desired_goal"] == batch["episode_goal"]).all(-1)
    success = batch["next", "reward"].reshape(-1) == 0
    stats = {
        "own goal": own.float().mean().item(),
        "reward 0": success.float().mean().item(),
        "reward 0 (own goal)": success[own].float().mean().item() if bool(own.any()) else math.nan,
        "goal to target": -batch["proximity"][0].item() / len(batch),
    }
    if start_height is not None:
        up = batch["desired_goal"][:, 2] - start_height
        stats["goal > 2 cm up"] = (up > 0.02).float().mean().item()
        stats["goal > 10 cm up"] = (up > 0.10).float().mean().item()
        stats["reward 0, goal > 2 cm up"] = (success & (up > 0.02)).float().mean().item()
    return stats


def curriculum_of(cfg):
    """The run's curriculum settings, or ``algo=gchgg``'s for a run without a curriculum (HER, HGG, G-HGG)."""
    if cfg.get("curriculum") is not None:
        return cfg.curriculum
    default = CurriculumConfig()
    return OmegaConf.create({"num_candidates": default.num_candidates, "proximity": default.proximity,
                             "diversity_of": default.diversity_of, "diversity_metric": cfg.algo.metric,
                             "scale": default.scale})


def draw(storage, cfg, metric, candidates: int, tradeoff: float, samples: int, seed: int, start_height,
         diversity_metric=None):
    """Mean and per-batch values of the statistics over ``samples`` batches of a sampler with ``candidates``
    (F_div under ``diversity_metric``, ``None``: ``metric``)."""
    c = curriculum_of(cfg)
    sampler = make_sampler(
        "curriculum", metric, tradeoff, num_candidates=candidates, proximity=c.proximity,
        diversity_of=c.diversity_of, diversity_metric=diversity_metric, scale=c.get("scale", "raw"), fast=True,
    )  # fmt: skip
    buffer = TensorDictReplayBuffer(
        storage=storage, sampler=sampler, batch_size=cfg.train.batch_size, generator=torch.Generator().manual_seed(seed)
    )
    rows = []
    decided = []
    for _ in range(samples):
        batch = buffer.sample()
        rows.append(batch_stats(batch, start_height))
        decided.append(batch["diversity_decided"][0].item())
    values = {key: torch.tensor([r[key] for r in rows if key in r]) for key in STATS if key in rows[0]}
    values["diversity decided"] = torch.tensor(decided)
    return values


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a run folder (config.yaml, metrics.csv, replay/)")
    parser.add_argument("--iterations", type=int, nargs="+", required=True)
    parser.add_argument("--tradeoff", type=float, help="λ (default: the run's `lambda` at each iteration)")
    parser.add_argument("--samples", type=int, default=200, help="batches per sampler and iteration (default 200)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, help="also write the table into this Markdown file")
    args = parser.parse_args()
    if args.samples < 2:
        parser.error(f"--samples must be >= 2, got {args.samples}")
    if args.tradeoff is not None and not (math.isfinite(args.tradeoff) and args.tradeoff >= 0):
        parser.error(f"--tradeoff must be a finite number >= 0, got {args.tradeoff}")
    cfg = OmegaConf.load(args.run / "config.yaml")
    geometry = envs.geometry(cfg.env.name)
    start_height = None if geometry.object_range is None else float(geometry.object_range.center[2])
    g = cfg.get("graph") or OmegaConf.structured(GraphConfig)  # a run with a Euclidean metric saved no graph

    def metric_of(kind: str):
        if kind != "graph":
            return make_metric(kind)
        return make_metric(kind, geometry.field, geometry.obstacles, n=tuple(g.n), margin=g.margin, snap=g.snap,
                           cache_dir=g.cache_dir)

    metric = metric_of(cfg.algo.metric)
    c = curriculum_of(cfg)
    diversity_metric = metric_of(c.diversity_metric) if c.diversity_metric != cfg.algo.metric else None
    capacity = cfg.buffer.episodes * (cfg.her.k + 1) * geometry.episode_length
    candidates = c.num_candidates
    best = torch.randn(100_000, candidates, generator=torch.Generator().manual_seed(0)).amax(1).mean().item()
    lines = [
        f"`{'/'.join(args.run.parts[-3:])}` ({cfg.env.name}, algo={cfg.algo.name}, metric={cfg.algo.metric}): "
        f"{args.samples} batches "
        f"of {cfg.train.batch_size} per sampler; curriculum = best of {candidates} "
        f"(the largest of {candidates} standard normal draws averages {best:.2f})",
        "",
        "| iteration | λ | statistic | EBP | EBP s.d. | curriculum | curriculum − EBP (± s.e.) |",
        "|---|---|---|---|---|---|---|",
    ]
    print("\n".join(lines), flush=True)
    for iteration in args.iterations:
        tradeoff = args.tradeoff if args.tradeoff is not None else run_lambda(args.run, iteration)
        if tradeoff is None:
            raise SystemExit(f"{args.run / 'metrics.csv'} has no lambda at iteration {iteration}: pass --tradeoff")
        storage = load_buffer(args.run, iteration, capacity)
        ebp = draw(storage, cfg, metric, 1, tradeoff, args.samples, args.seed, start_height, diversity_metric)
        chosen = draw(storage, cfg, metric, candidates, tradeoff, args.samples, args.seed + 1, start_height,
                      diversity_metric)
        for key in ebp:
            a, b = ebp[key][~ebp[key].isnan()], chosen[key][~chosen[key].isnan()]
            se = math.sqrt(a.var().item() / len(a) + b.var().item() / len(b))
            cells = [str(iteration), f"{tradeoff:.3g}", key, f"{a.mean():.3f}", f"{a.std():.3f}", f"{b.mean():.3f}",
                     f"{b.mean() - a.mean():+.3f} ± {se:.3f}"]  # fmt: skip
            lines.append("| " + " | ".join(cells) + " |")
            print(lines[-1], flush=True)
    if args.out:
        args.out.write_text("\n".join(lines) + "\n")
        print(f"wrote {args.out}", file=sys.stderr)


if __name__ == "__main__":
    main()
