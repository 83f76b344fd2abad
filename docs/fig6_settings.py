"""What each Fig. 6 setting does to Algorithm 1's choice, before any Fig. 6 run: its λ and the picks diversity decides.

    python docs/fig6_settings.py RUN_DIR --iteration N [--distance D] [--samples 200] [--out FILE]

Rebuilds a run's replay buffer as it stood after iteration N (``docs/curriculum_choice.py``'s
``load_buffer``: every replay file of the run up to N, so N must be recent enough that no file a
batch could hold was pruned: the run's last iterations), takes D = the run's ``d_g`` at N (or
``--distance``), and for each setting of the four ``fig6_*`` sweeps (``conf/experiment/``) prints:

* **λ**: eq. 20, η · exp(−D / σ²), with the setting's η and σ (the default η = 1000, σ = 0.3; the
  η sweep 500, 5000; the σ sweep 0.37, 0.4); the trade-off sweep's ``exponential`` is eq. 4 at
  iteration N, λ_0 · (1 + τ)^N; the metric sweep's ``euclidean`` uses the default λ;
* **diversity decided**: the share of ``--samples`` curriculum batches (K = 8, the run's batch size,
  the default ``algo=gchgg`` sampler: EBP candidates, eq. 15 proximity to T*, eq. 19 diversity of
  the hindsight goals) whose chosen candidate is not the one with the best F_prox, i.e. the picks
  that diversity changed;
* **shift**: how far the chosen batches' mean goal-to-target distance (−F_prox / B under the
  setting's metric) lies from EBP's (one candidate), in standard deviations of EBP's batches.

Beside them, for comparison, ``curriculum.scale=standardized`` (F_div and F_prox each divided by its
spread across the K candidates) at λ = 0.1, 1 and 10. Then how far Algorithm 1 can move a batch at
all: the same shift at K = 8, 64 and 512 for the default λ and for pure proximity (λ = 10⁹), beside
the mean of the largest of K standard normal draws (what choosing the best of K i.i.d. candidates
on that very statistic would give).

No training: the question is what each setting would choose from the same buffer. Any run's folder
serves (``config.yaml``, ``metrics.csv``, ``replay/``), whatever algorithm it trained with.
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
sys.path[:0] = [str(Path(__file__).resolve().parents[1]), str(Path(__file__).resolve().parent)]  # a checkout

import torch  # noqa: E402
from curriculum_choice import load_buffer  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402
from torchrl.data import TensorDictReplayBuffer  # noqa: E402

import envs  # noqa: E402
from gchgg.run.builders import make_metric, make_sampler, make_tradeoff  # noqa: E402
from gchgg.run.config import CurriculumConfig, GraphConfig  # noqa: E402

DEFAULT = {"eta": 1000.0, "sigma": 0.3}
SETTINGS = (  # (sweep, value, η, σ, metric); the default of every sweep first
    ("default", "η 1000, σ 0.3", 1000.0, 0.3, "graph"),
    ("eta", "500", 500.0, 0.3, "graph"),
    ("eta", "5000", 5000.0, 0.3, "graph"),
    ("sigma", "0.37", 1000.0, 0.37, "graph"),
    ("sigma", "0.4", 1000.0, 0.4, "graph"),
    ("tradeoff", "exponential", None, None, "graph"),
    ("metric", "euclidean", 1000.0, 0.3, "euclidean"),
)
STANDARDIZED = (0.1, 1.0, 10.0)  # λ with curriculum.scale=standardized (each term over its spread): not a Fig. 6 sweep
PURE_PROXIMITY = 1e9


def run_value(run: Path, iteration: int, column: str) -> float | None:
    """``column`` of the run's ``metrics.csv`` row for ``iteration`` (``None`` if absent or empty)."""
    path = run / "metrics.csv"
    if not path.is_file():
        return None
    with path.open() as f:
        for row in csv.DictReader(f):
            if int(row["iteration"]) == iteration and row.get(column, ""):
                return float(row[column])
    return None


def draws(storage, metric, tradeoff: float, candidates: int, samples: int, batch: int, seed: int,
          scale: str = "raw"):
    """Goal-to-target means ``[samples]`` and diversity-decided flags of ``samples`` batches of the
    default GC-HGG curriculum sampler with ``candidates`` (1: EBP) at λ = ``tradeoff``."""
    default = CurriculumConfig()  # algo=gchgg's curriculum: eq. 15 proximity to T*, eq. 19 diversity of the goals
    sampler = make_sampler("curriculum", metric, tradeoff, num_candidates=candidates, proximity=default.proximity,
                           diversity_of=default.diversity_of, diversity_metric=None, scale=scale, fast=True)
    sampler.draw_ahead = max(1, min(sampler.draw_ahead, 4096 // candidates))  # bounded scratch at K = 512
    buffer = TensorDictReplayBuffer(storage=storage, sampler=sampler, batch_size=batch,
                                    generator=torch.Generator().manual_seed(seed))
    means, decided = [], []
    for _ in range(samples):
        sampled = buffer.sample()
        means.append(-sampled["proximity"][0].item() / batch)
        decided.append(sampled["diversity_decided"][0].item())
    return torch.tensor(means, dtype=torch.float64), torch.tensor(decided)


def shift(chosen: torch.Tensor, ebp: torch.Tensor) -> float:
    """Chosen minus EBP mean, in EBP's between-batch standard deviations (negative: nearer the targets)."""
    return (chosen.mean() - ebp.mean()).item() / ebp.std().item()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a run folder (config.yaml, metrics.csv, replay/)")
    parser.add_argument("--iteration", type=int, required=True, help="rebuild the buffer as it was after this one")
    parser.add_argument("--distance", type=float, help="D_G in metres (default: the run's d_g at --iteration)")
    parser.add_argument("--samples", type=int, default=200, help="batches per setting and sampler (default 200)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, help="also write the tables into this Markdown file")
    args = parser.parse_args()
    if args.samples < 2:
        parser.error(f"--samples must be >= 2, got {args.samples}")
    distance = args.distance if args.distance is not None else run_value(args.run, args.iteration, "d_g")
    if distance is None or not (math.isfinite(distance) and distance >= 0):
        parser.error(f"no usable d_g at iteration {args.iteration} in {args.run / 'metrics.csv'} "
                     f"(got {distance}): pass --distance D (metres, >= 0)")
    cfg = OmegaConf.load(args.run / "config.yaml")
    geometry = envs.geometry(cfg.env.name)
    g = cfg.get("graph") or OmegaConf.structured(GraphConfig)  # a run with a Euclidean metric saved no graph
    metrics = {"graph": make_metric("graph", geometry.field, geometry.obstacles, n=tuple(g.n), margin=g.margin,
                                    snap=g.snap, cache_dir=g.cache_dir),
               "euclidean": make_metric("euclidean")}
    capacity = cfg.buffer.episodes * (cfg.her.k + 1) * geometry.episode_length
    storage = load_buffer(args.run, args.iteration, capacity)
    batch = cfg.train.batch_size
    exponential = make_tradeoff("exponential", lambda_0=1.0, tau=0.005)
    for _ in range(args.iteration):
        exponential.update()
    lines = [
        f"`{'/'.join(args.run.parts[-2:])}` ({cfg.env.name}, trained with algo={cfg.algo.name}), buffer after "
        f"iteration {args.iteration} ({len(storage):,} transitions), D = {distance:.3f} m; {args.samples} batches of "
        f"{batch} per setting; curriculum K = 8 (the default GC-HGG sampler); shift = chosen − EBP mean "
        "goal-to-target distance in EBP batch standard deviations",
        "",
        "| sweep | setting | λ | diversity decided | shift (s.d.) |",
        "|---|---|---|---|---|",
    ]
    print("\n".join(lines), flush=True)
    ebp = {kind: draws(storage, metric, 0.0, 1, args.samples, batch, args.seed)[0] for kind, metric in metrics.items()}
    lines.insert(1, "EBP batches' mean goal-to-target distance: " + ", ".join(
        f"{kind} {values.mean().item():.3f} m (s.d. over batches {values.std().item():.4f} m)"
        for kind, values in ebp.items()))
    print(lines[1], flush=True)
    default_lambda = None
    for sweep, label, eta, sigma, kind in SETTINGS:
        if eta is None:
            tradeoff = float(exponential.value)
        else:
            tradeoff = eta * math.exp(-distance / sigma**2)  # eq. 20
        default_lambda = tradeoff if sweep == "default" else default_lambda
        chosen, decided = draws(storage, metrics[kind], tradeoff, 8, args.samples, batch, args.seed + 1)
        lines.append(f"| {sweep} | {label} | {tradeoff:.3g} | {decided.float().mean().item():.1%} | "
                     f"{shift(chosen, ebp[kind]):+.2f} |")
        print(lines[-1], flush=True)
    for tradeoff in STANDARDIZED:
        chosen, decided = draws(storage, metrics["graph"], tradeoff, 8, args.samples, batch, args.seed + 1,
                                scale="standardized")
        lines.append(f"| (not in Fig. 6) | curriculum.scale=standardized | {tradeoff:g} | "
                     f"{decided.float().mean().item():.1%} | {shift(chosen, ebp['graph']):+.2f} |")
        print(lines[-1], flush=True)
    lines += ["", "How far Algorithm 1 can move a batch (graph metric; shift in EBP batch standard deviations):", "",
              "| K | shift at the default λ | shift at pure proximity | largest of K standard normals |",
              "|---|---|---|---|"]
    print("\n".join(lines[-5:]), flush=True)
    normals = torch.Generator().manual_seed(0)
    for k in (8, 64, 512):
        samples = args.samples if k <= 64 else max(2, args.samples // 4)
        at_default = draws(storage, metrics["graph"], default_lambda, k, samples, batch, args.seed + 2)[0]
        pure = draws(storage, metrics["graph"], PURE_PROXIMITY, k, samples, batch, args.seed + 3)[0]
        best = torch.randn(20_000, k, generator=normals).amax(1).mean().item()
        lines.append(f"| {k} | {shift(at_default, ebp['graph']):+.2f} | {shift(pure, ebp['graph']):+.2f} | "
                     f"{-best:+.2f} |")
        print(lines[-1], flush=True)
    if args.out:
        args.out.write_text("\n".join(lines) + "\n")
        print(f"wrote {args.out}", file=sys.stderr)


if __name__ == "__main__":
    main()
