"""A run forked from another run's checkpoint (``init_from``, gchgg/run/fork.py).

A fork that changes nothing but its length continues exactly as ``resume=true`` would; a G-HGG →
GC-HGG fork with a fresh seed logs the settings it changes and starts at the source's iteration; a
setting that shapes the carried state is refused by name (one the source's config predates, with a
hint); a fork resumes from its own checkpoint, without the source's folder, and only as a fork of
the source it records.
"""

from __future__ import annotations

import csv
import logging
import shutil
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
from test_train import config, tiny  # noqa: E402

from gchgg import train  # noqa: E402
from gchgg.fast.linear import resolve_precision  # noqa: E402
from gchgg.run import checkpoint, fork  # noqa: E402

SOURCE_ITERATIONS = 3  # the forks start at iteration 3, after warm-up (2 iterations) and one of updates


def overrides(graphs: Path, algo: str, *extra: str) -> list[str]:
    """A tiny reach run (HGG's pool fills from the first iteration); one graph cache for all runs, so
    that ``graph.cache_dir`` is the same setting in the sources and the forks."""
    return [
        "env=reach", f"algo={algo}", *tiny(graphs, iterations=SOURCE_ITERATIONS),
        "train.warmup_steps=200", "buffer.episodes=6",  # the buffer wraps before the fork point
        *extra,
    ]  # fmt: skip


def metrics(run_dir: Path) -> list[dict[str, str]]:
    with open(run_dir / "metrics.csv", newline="") as f:
        return [{k: v for k, v in row.items() if not k.startswith("seconds_")} for row in csv.DictReader(f)]


@pytest.fixture(scope="module")
def graphs(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("fork")


@pytest.fixture(scope="module")
def sources(graphs) -> dict[str, Path]:
    """Source runs of 3 iterations: G-HGG, GC-HGG, and G-HGG whose HGG stop fired (iteration 2)."""
    runs = {"ghgg": (), "gchgg": (), "ghgg-stopped": ("env.stop_threshold=0.5",)}
    for name, extra in runs.items():
        train.run(config(overrides(graphs, name.split("-")[0], *extra)), graphs / name)
    assert checkpoint.load(graphs / "ghgg-stopped" / "checkpoint.pt")["goal_generator"]["stopped"]
    return {name: graphs / name for name in runs}


@pytest.fixture(scope="module")
def curriculum_fork(graphs, sources) -> Path:
    """G-HGG's source forked as GC-HGG with seed 7, to iteration 5."""
    run_dir = graphs / "fork-gchgg-7"
    train.run(config(overrides(graphs, "gchgg", "seed=7", "train.iterations=5", f"init_from={sources['ghgg']}")),
              run_dir)  # fmt: skip
    return run_dir


@pytest.mark.parametrize("algo", ["ghgg", "gchgg"])
def test_a_fork_that_changes_nothing_continues_as_a_resume_would(graphs, sources, tmp_path, algo):
    source = sources[algo]
    resumed = tmp_path / "resumed"
    shutil.copytree(source, resumed)
    train.run(config(overrides(graphs, algo, "train.iterations=5", "resume=true")), resumed)
    forked = tmp_path / "forked"
    train.run(config(overrides(graphs, algo, "train.iterations=5", f"init_from={source}")), forked)

    assert metrics(forked) == metrics(resumed)  # the rows after the fork point, and the source's before it
    assert [int(row["iteration"]) for row in metrics(forked)] == [0, 1, 2, 3, 4]
    assert metrics(forked)[:SOURCE_ITERATIONS] == metrics(source)
    record = OmegaConf.to_container(OmegaConf.load(forked / "fork.yaml"))
    assert record["source"] == str(source) and record["source_iteration"] == SOURCE_ITERATIONS
    assert record["changed"] == {"train.iterations": {"source": SOURCE_ITERATIONS, "fork": 5}}
    assert record["random_streams"].startswith("carried over") and record["sampler"].startswith("carried over")


def test_a_ghgg_checkpoint_forked_as_gchgg_logs_the_changes_and_starts_at_the_sources_iteration(
    graphs, sources, curriculum_fork, caplog
):
    source, rows = sources["ghgg"], metrics(curriculum_fork)
    record = OmegaConf.to_container(OmegaConf.load(curriculum_fork / "fork.yaml"))
    assert record["source_iteration"] == SOURCE_ITERATIONS
    changed = dict(record["changed"])
    assert {key: changed.pop(key) for key in ("seed", "train.iterations", "algo.name", "algo.sampler")} == {
        "seed": {"source": 0, "fork": 7},
        "train.iterations": {"source": SOURCE_ITERATIONS, "fork": 5},
        "algo.name": {"source": "ghgg", "fork": "gchgg"},
        "algo.sampler": {"source": "ebp", "fork": "curriculum"},
    }
    # G-HGG reads no curriculum and no λ: its config holds neither; the fork's sections are new
    assert changed.pop("curriculum") == changed.pop("tradeoff") == {"source": None, "fork": "<absent>"}
    assert changed.pop("curriculum.num_candidates") == {"source": "<absent>", "fork": 8}
    assert all(key.startswith(("curriculum.", "tradeoff.")) and value["source"] == "<absent>"
               for key, value in changed.items())
    assert record["random_streams"] == "new, from seed 7" and record["sampler"] == "new"
    assert [int(row["iteration"]) for row in rows] == [0, 1, 2, 3, 4]
    filled = [{k: v for k, v in row.items() if v} for row in rows]  # columns the source lacks are empty there
    assert filled[:SOURCE_ITERATIONS] == [{k: v for k, v in row.items() if v} for row in metrics(source)]
    assert all(row["lambda"] and row["diversity_decided"] for row in rows[SOURCE_ITERATIONS:])  # the curriculum's
    assert not any(row["lambda"] for row in rows[:SOURCE_ITERATIONS])
    assert checkpoint.load(curriculum_fork / "checkpoint.pt")["run"] == {
        "env": "reach", "algo": "gchgg", "seed": 7, "precision": resolve_precision("auto")}

    # its pair: the same checkpoint and seed as G-HGG: the same targets and goals at the fork point
    pair = graphs / "fork-ghgg-7"
    with caplog.at_level(logging.INFO, logger="gchgg.run.fork"):
        train.run(config(overrides(graphs, "ghgg", "seed=7", "train.iterations=4", f"init_from={source}")), pair)
    out = caplog.text
    assert f"forked from {source} after iteration 2: this run starts at iteration 3" in out
    assert "changed settings: seed: 0 -> 7, train.iterations: 3 -> 4;" in out
    assert metrics(pair)[SOURCE_ITERATIONS]["d_g"] == rows[SOURCE_ITERATIONS]["d_g"]


def test_a_new_curriculum_behind_a_stopped_hgg_starts_stopped(graphs, sources, tmp_path):
    cfg = config(overrides(graphs, "gchgg", "env.stop_threshold=0.5", "train.iterations=4",
                           f"init_from={sources['ghgg-stopped']}"))  # fmt: skip
    source = fork.prepare(cfg, tmp_path, train.CHECKPOINT)
    trainer = train.Trainer(cfg, tmp_path)
    assert trainer.sampler.num_candidates == 8
    fork.start(source, trainer)
    assert trainer.goal_generator.stopped and trainer.sampler.num_candidates == 1


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("env=push_new", r"env.name: 'reach' in the source, 'push_new' here \(the task"),
        ("agent.hidden=[8,8]", r"agent.hidden: \[16, 16\] in the source, \[8, 8\] here \(the networks"),
        ("buffer.episodes=7", r"buffer.episodes: 6 in the source, 7 here"),
        ("her.k=2", r"her.k: 1 in the source, 2 here"),
        ("algo=her", r"algo.goal_generator: 'hgg' in the source, 'none' here \(the HGG pool\)"),
    ],
)
def test_a_fork_that_changes_the_carried_state_is_refused_naming_the_setting(
    graphs, sources, tmp_path, override, message
):
    cfg = config([*overrides(graphs, "ghgg", "train.iterations=5", f"init_from={sources['ghgg']}"), override])
    with pytest.raises(ValueError, match=message) as error:
        train.run(cfg, tmp_path / "fork")
    assert "Settings a fork may change: seed, " in str(error.value)
    assert not (tmp_path / "fork" / "checkpoint.pt").exists()


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (("train.iterations=3",), "train.iterations must exceed the iteration the fork starts from \\(3"),
        (("init_from=/nonexistent/run",), "init_from must be a run folder holding config.yaml and checkpoint.pt"),
    ],
)
def test_a_fork_with_nothing_to_do_or_no_source_is_refused(graphs, sources, tmp_path, extra, message):
    with pytest.raises(ValueError, match=message):
        train.run(config(overrides(graphs, "ghgg", "train.iterations=5", f"init_from={sources['ghgg']}", *extra)),
                  tmp_path / "fork")  # fmt: skip


def test_a_fork_resumes_from_its_own_checkpoint_without_its_source(graphs, sources, curriculum_fork, tmp_path, capsys):
    source = tmp_path / "source"
    shutil.copytree(sources["ghgg"], source)
    base = overrides(graphs, "gchgg", "seed=7", f"init_from={source}")
    forked = tmp_path / "forked"
    train.run(config([*base, "train.iterations=4"]), forked)  # "killed" after iteration 3
    with pytest.raises(FileExistsError, match="resume=true"):
        train.run(config([*base, "train.iterations=5"]), forked)
    shutil.rmtree(source)  # the fork holds (links to) the replay files it needs
    capsys.readouterr()
    train.run(config([*base, "train.iterations=5", "resume=true"]), forked)
    assert f"resumed {forked} after iteration 4" in capsys.readouterr().out
    assert metrics(forked) == metrics(curriculum_fork)


def test_a_resume_names_the_forks_own_source_or_none(graphs, sources, curriculum_fork):
    base = overrides(graphs, "gchgg", "seed=7", "train.iterations=5", "resume=true")
    with pytest.raises(ValueError, match=f"already holds a fork of {sources['ghgg']}; resume it with that init_from"):
        train.run(config([*base, f"init_from={sources['gchgg']}"]), curriculum_fork)
    with pytest.raises(ValueError, match="already holds a run that is not a fork"):
        train.run(config([*base, f"init_from={sources['ghgg']}"]), sources["gchgg"])  # a sweep's folders collided


def test_a_setting_added_since_the_source_ran_is_named_with_a_hint(graphs, sources, tmp_path):
    source = tmp_path / "older"
    shutil.copytree(sources["ghgg"], source)
    saved = OmegaConf.load(source / "config.yaml")
    for key in ("precision", "init_from"):  # added to the config after runs were made with it
        saved.pop(key)
    OmegaConf.save(saved, source / "config.yaml")
    cfg = config(overrides(graphs, "ghgg", "seed=7", "train.iterations=5", f"init_from={source}"))
    assert fork.prepare(cfg, tmp_path / "fork", train.CHECKPOINT).changes["precision"] == ("<absent>", "auto")

    saved.her.pop("strategy")
    OmegaConf.save(saved, source / "config.yaml")
    with pytest.raises(ValueError, match=r"her.strategy: '<absent>' in the source, 'future' here .*~her.strategy"):
        fork.prepare(cfg, tmp_path / "fork", train.CHECKPOINT)
