"""A fixed-seed tiny GC-HGG run on pick_obstacle reproduces its recorded metrics exactly, through the paths
``tests/test_same_numbers.py`` never reaches (issue 72 item 5).

That test's runs are push_new and reach, batch 16, with an HGG pool that stays empty on push_new and a stop
that never fires. This one runs GC-HGG on a pick task (pick_obstacle: the graph goes around the wall) with

* batches of 64 (``MIN_BATCH``: the wide layers' products go to oneDNN) and the default ``precision=auto``,
  ``gradients=auto``: bfloat16 products and the compiled update where the CPU has native bfloat16 products
  and a C++ compiler is found (the machine the recording was made on resolved them to
  ``bfloat16`` / ``onednn`` / ``compiled``);
* an HGG pool of 2 trajectories (``hgg.pool_size=2``) that fills in the first iteration and then drops its
  oldest (more trajectories are admitted than it holds);
* the intermediate goals taken from that pool in iteration 1: D_G > 0 and λ > 0 (eq. 20);
* HGG's stop firing in iteration 1 (``env.stop_threshold=0.0``: any intermediate goal within
  ``env.threshold`` of a target stops it; ``env.threshold=0.4``, since a 3-iteration run pushes the cube
  nowhere near a 5 cm target across the wall), so iteration 2 runs plain HER and plain sampling
  (``stop_curriculum``), with D_G and λ back at 0.

The test asserts each of these from the run itself (the pool, the agent's resolved settings) and from the
recorded rows (``stopped``, ``lambda``, ``d_g``), then that the rows (timing columns aside) equal the recording.

Recordings: ``tests/data/same_numbers_paths/<vendor>/pick_obstacle-gchgg-<precision>-<matmul>-<gradients>.csv``,
by the CPU vendor (``gchgg.fast.linear.cpu_vendor()``) and the settings the agent resolved, since the
products' roundings differ between vendors' kernels and between those settings (see test_same_numbers.py).
Held now: ``AuthenticAMD/pick_obstacle-gchgg-bfloat16-onednn-compiled.csv``, recorded on an AMD EPYC CPU
(AVX-512 with avx512_bf16, g++ found) with ``python tests/test_same_numbers_paths.py`` from the working tree
on top of commit 39116ac; the same rows came from that commit's files exported alone (``git archive``) with an
empty TorchInductor cache. The rows pin the bfloat16 products and the compiled update: the same run with
``precision=float32`` has other losses in every row (iteration 1's loss_value 0.678 against 0.647), and
with ``gradients=fused`` they differ from the 7th digit on.
A machine without a recording for its vendor and settings skips the test, naming the file it lacks and the
command that records it; a change meant to alter learning re-records with that command and says why.
"""

from __future__ import annotations

import csv
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
from test_train import config, tiny  # noqa: E402

from gchgg import train  # noqa: E402
from gchgg.ddpg.agent import DDPGAgent  # noqa: E402
from gchgg.fast.linear import cpu_vendor  # noqa: E402

RECORDED = Path(__file__).parent / "data" / "same_numbers_paths"
RECORD_COMMAND = "python tests/test_same_numbers_paths.py"
TASK, ALGO, POOL = "pick_obstacle", "gchgg", 2
OVERRIDES = [f"env={TASK}", f"algo={ALGO}", "train.episodes=4", "train.chunks=2", "train.updates=4",
             "train.batch_size=64", "train.warmup_steps=400", f"hgg.pool_size={POOL}", "env.stop_threshold=0.0",
             "env.threshold=0.4", "seed=0"]
ITERATIONS = 3


def resolved_settings(agent) -> dict[str, str]:
    """How ``agent`` resolved the settings whose ``auto`` depends on the machine."""
    return {name: getattr(agent, name) for name in ("matmul", "precision", "gradients", "subnormals")}


def expected_settings() -> dict[str, str]:
    """The settings ``precision``, ``matmul``, ``gradients`` and ``subnormals`` at ``auto`` resolve to on this
    machine, as a run's agent resolves them (one built here, small; nothing is compiled until it updates)."""
    agent = DDPGAgent(25, 3, 4, hidden=[16, 16], matmul="auto", precision="auto", gradients="auto")
    return resolved_settings(agent)


def recording(settings: dict[str, str]) -> Path:
    name = f"{TASK}-{ALGO}-{settings['precision']}-{settings['matmul']}-{settings['gradients']}.csv"
    return RECORDED / (cpu_vendor() or "unknown-vendor") / name


def run(folder: Path) -> tuple[list[dict[str, str]], dict]:
    """Metrics rows (timing columns dropped) of the run, and what it reached: its agent's resolved settings,
    the pool's length and capacity, and how many trajectories the pool admitted in all."""
    cfg = config([*tiny(folder, iterations=ITERATIONS), *OVERRIDES])
    (folder / "run").mkdir(parents=True)
    trainer = train.Trainer(cfg, folder / "run")
    pool = trainer.goal_generator.pool
    admitted, add = [], pool.add

    def counting_add(achieved, observations):  # counts, changes nothing
        mask = add(achieved, observations)
        admitted.append(int(mask.sum()))
        return mask

    pool.add = counting_add
    trainer.train()
    with open(folder / "run" / "metrics.csv", newline="") as f:
        rows = [{k: v for k, v in row.items() if not k.startswith("seconds_")} for row in csv.DictReader(f)]
    reached = {"settings": resolved_settings(trainer.agent), "pool": len(pool), "capacity": pool.capacity,
               "admitted": sum(admitted), "stopped": trainer.goal_generator.stopped}
    return rows, reached


def check_paths(rows: list[dict[str, str]]) -> None:
    """The rows show each path reached: iteration 0 with an empty pool (no D_G, no λ), iteration 1 with goals
    from the pool (D_G > 0, λ > 0) where the stop fires, iteration 2 stopped (plain HER: D_G and λ 0)."""
    assert [int(r["iteration"]) for r in rows] == list(range(ITERATIONS))
    stopped = [float(r["stopped"]) for r in rows]
    d_g = [float(r["d_g"]) for r in rows]
    lam = [float(r["lambda"]) for r in rows]
    assert stopped == [0.0, 1.0, 1.0], stopped
    assert d_g[0] == 0.0 and d_g[1] > 0.3 and d_g[2] == 0.0, d_g
    assert lam[0] == 0.0 and lam[1] > 0.1 and lam[2] == 0.0, lam
    assert float(rows[0]["warmup"]) == 1.0 and float(rows[1]["warmup"]) == 0.0
    assert all(float(r["object_moved"]) > 0 for r in rows)  # the pick task's cube moved every iteration


def test_recorded_rows_reach_the_paths():
    """Every recording held reaches the paths (so a re-recording that stopped reaching them is caught here)."""
    files = sorted(RECORDED.glob(f"*/{TASK}-{ALGO}-*.csv"))
    assert files, f"no recording under {RECORDED}"
    for path in files:
        with open(path, newline="") as f:
            check_paths(list(csv.DictReader(f)))


def test_tiny_pick_run_through_pool_stop_and_bfloat16_reproduces_the_recording(tmp_path):
    settings = expected_settings()
    path = recording(settings)
    if not path.exists():
        pytest.skip(f"no recording for this CPU (vendor {cpu_vendor() or 'unknown'!r}, settings {settings}): "
                    f"{path.relative_to(ROOT)} is missing; record it with `{RECORD_COMMAND}`")
    with open(path, newline="") as f:
        recorded = list(csv.DictReader(f))
    rows, reached = run(tmp_path)
    assert reached["settings"] == settings  # e.g. a compiled update that fell back to eager would differ
    assert reached["pool"] == reached["capacity"] == POOL and reached["admitted"] > POOL  # filled, then FIFO
    assert reached["stopped"]
    check_paths(rows)
    assert rows == recorded


if __name__ == "__main__":  # record this machine's rows
    import os
    import tempfile

    os.environ.setdefault("MUJOCO_GL", "disable")
    with tempfile.TemporaryDirectory() as tmp:
        rows, reached = run(Path(tmp))
    check_paths(rows)
    path = recording(reached["settings"])
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    print(f"recorded {path} ({len(rows)} rows; {reached})")
