"""The training loop's wiring: what each algo builds, chunked collection, warm-up, normalisers, λ and early stop.

A smoke run only shows that numbers are finite; these tests check that the trainer hands each part
what the paper (or the authors' loop) says it should.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from hydra.errors import ConfigCompositionException
from test_train import config, tiny

from gchgg import train
from gchgg.graph import EuclideanMetric, GoalGraph
from gchgg.hgg import HGGGoalGenerator
from gchgg.run import evaluator, metrics
from gchgg.samplers import AdaptiveTradeoff, CherSampler, EnergySampler, ExponentialTradeoff, GraphCurriculumSampler

WIRING = {  # algo -> (metric, sampler, goal generator?)
    "her": (EuclideanMetric, EnergySampler, False),
    "hgg": (EuclideanMetric, EnergySampler, True),
    "ghgg": (GoalGraph, EnergySampler, True),
    "cher": (EuclideanMetric, CherSampler, False),
    "gchgg": (GoalGraph, GraphCurriculumSampler, True),
    "gchgg_code": (GoalGraph, GraphCurriculumSampler, True),
}


def trainer(tmp_path: Path, *overrides: str, task: str = "push_new", algo: str = "gchgg") -> train.Trainer:
    return train.Trainer(config([f"env={task}", f"algo={algo}", *tiny(tmp_path), *overrides]), tmp_path / "run")


@pytest.mark.parametrize("algo", WIRING)
def test_each_algo_builds_its_metric_sampler_and_goal_generator(algo, tmp_path):
    metric, sampler, generator = WIRING[algo]
    t = trainer(tmp_path, algo=algo)
    assert type(t.parts.metric) is metric
    assert type(t.sampler) is sampler
    assert t.buffer.sampler is t.sampler
    assert (t.goal_generator is not None) == generator
    if generator:
        assert isinstance(t.goal_generator, HGGGoalGenerator) and t.goal_generator.metric is t.parts.metric
    if algo in ("her", "hgg", "ghgg"):
        assert t.tradeoff is None  # no λ where nothing reads one
    if algo == "cher":
        assert isinstance(t.tradeoff, ExponentialTradeoff) and t.sampler.tradeoff is t.tradeoff


def test_gchgg_scores_as_the_paper_and_gchgg_code_as_the_authors_code(tmp_path):
    paper = trainer(tmp_path, algo="gchgg").sampler
    assert (paper.goal_key, paper.target_key, paper.diversity_key) == ("desired_goal", "task_goal", "desired_goal")
    assert paper.diversity_metric is paper.metric and paper.scale == "raw"
    assert isinstance(paper.tradeoff, AdaptiveTradeoff) and paper.tradeoff.update_every == "iteration"

    code = trainer(tmp_path, algo="gchgg_code").sampler
    assert (code.goal_key, code.target_key, code.diversity_key) == ("achieved_goal", "desired_goal", "achieved_goal")
    assert isinstance(code.metric, GoalGraph) and isinstance(code.diversity_metric, EuclideanMetric)
    assert code.tradeoff.update_every == "episode"

    standardized = trainer(tmp_path, "curriculum.scale=standardized", algo="gchgg").sampler
    assert standardized.scale == "standardized"


def record_resets_and_generations(t: train.Trainer) -> tuple[list, list]:
    """Wraps the trainer's env reset and goal generation to record what they receive and return."""
    resets, generations = [], []
    reset, generate = t.env.reset, t.goal_generator.generate

    def recording_reset(tensordict=None, **kwargs):
        out = reset(tensordict, **kwargs)
        if tensordict is not None:
            resets.append((t.iteration, out["desired_goal"].clone()))
        return out

    def recording_generate(starts, targets, value):
        result = generate(starts, targets, value)
        generations.append((t.iteration, targets.clone(), result))
        return result

    t.env.reset, t.goal_generator.generate = recording_reset, recording_generate
    return resets, generations


@pytest.mark.parametrize("noise", ["noise.object_std=0.0", "noise.object_std=0.01"])
def test_episodes_after_iteration_0_go_to_the_generators_goals_and_store_their_targets(noise, tmp_path):
    # reach: the achieved goal (the grip) always moves, so the pool fills after iteration 0. With
    # observation noise the env is wrapped in a TransformedEnv, which must still pass the goals.
    t = trainer(tmp_path, "train.episodes=4", "train.chunks=2", noise, task="reach", algo="ghgg")
    resets, generations = record_resets_and_generations(t)
    for _ in range(2):  # 8 episodes: the buffer (tiny: 8 episodes) is full, not wrapped
        t.iteration_step()
    for iteration, _, generation in generations:
        collected = torch.cat([goals for i, goals in resets if i == iteration])
        assert torch.allclose(collected, generation.goals.float(), atol=1e-6), iteration
    assert generations[0][2].from_pool is False and generations[1][2].from_pool is True
    # The last stored episode: its original copy (k = 1: the first T of its 2·T rows) trains on the
    # intermediate goal it was collected for; every copy keeps its target-task goal T* for eq. 15.
    _, targets, last = generations[-1]
    assert not torch.allclose(last.goals[-1].float(), targets[-1].float())
    steps = t.steps
    episode = t.buffer.storage[torch.arange(len(t.buffer) - 2 * steps, len(t.buffer))]
    assert torch.allclose(episode["desired_goal"][:steps], last.goals[-1].float().expand(steps, 3), atol=1e-6)
    assert torch.allclose(episode["episode_goal"], last.goals[-1].float().expand(2 * steps, 3), atol=1e-6)
    assert torch.allclose(episode["task_goal"], targets[-1].float().expand(2 * steps, 3), atol=1e-6)


def test_logged_lambda_follows_eq_20_under_gchgg_and_eq_4_under_cher(tmp_path):
    t = trainer(tmp_path, "train.iterations=3", task="reach", algo="gchgg")  # reach: the pool fills at once
    rows = t.train()
    eta, sigma = t.cfg.tradeoff.eta, t.cfg.tradeoff.sigma
    assert rows[0]["lambda"] == 0.0  # iteration 0: episodes go to the targets, λ = 0 as the original
    for row in rows[1:]:
        assert row["d_g"] > 0
        assert row["lambda"] == pytest.approx(eta * math.exp(-row["d_g"] / sigma**2), rel=1e-9)
        assert row["lambda_mean"] == pytest.approx(row["lambda"], rel=1e-5)  # one λ per iteration

    t = trainer(tmp_path / "cher", "train.iterations=3", "tradeoff.lambda_0=2.0", "tradeoff.tau=0.5", algo="cher")
    rows = t.train()
    assert [row["lambda"] for row in rows] == pytest.approx([2.0, 3.0, 4.5])

    rows = trainer(tmp_path / "her", "train.iterations=1", algo="her").train()
    assert "lambda" not in rows[0]


def test_gchgg_code_lambda_falls_within_the_iteration(tmp_path):
    t = trainer(tmp_path, "train.episodes=4", "train.chunks=4", "train.iterations=3", task="reach", algo="gchgg_code")
    seen = []
    after = t.tradeoff.after_episodes

    def recording_after(episodes):
        seen.append((t.iteration, episodes, after(episodes)))
        return seen[-1][2]

    t.tradeoff.after_episodes = recording_after
    rows = t.train()
    last = [value for iteration, _, value in seen if iteration == 2]
    assert last == sorted(last, reverse=True) and last[0] > last[-1]  # λ falls as S_i grows
    eta, sigma = t.cfg.tradeoff.eta, t.cfg.tradeoff.sigma
    assert last[-1] == pytest.approx(eta * math.exp(-rows[2]["d_g"] / sigma**2), rel=1e-5)


def actor_versions(t: train.Trainer) -> list[int]:
    """Records, for every exploring call of the policy, which version of the actor's weights acted."""
    versions, make = [], t.agent.rollout_policy  # the trainer explores through a rollout policy per chunk

    def recording_rollout_policy(generator):
        policy = make(generator)

        def recording_policy(observation, goal):
            versions.append(hash(tuple(p.sum().item() for p in t.agent.actor.parameters())))
            return policy(observation, goal)

        return recording_policy

    t.agent.rollout_policy = recording_rollout_policy
    return versions


def test_chunks_interleave_collection_and_updates(tmp_path):
    interleaved = trainer(tmp_path, "train.episodes=4", "train.chunks=4", "train.updates=8")  # 2 per chunk
    versions = actor_versions(interleaved)
    interleaved.iteration_step()
    steps = interleaved.steps
    per_chunk = [versions[i * steps] for i in range(4)]
    assert all(versions[i * steps : (i + 1) * steps] == [per_chunk[i]] * steps for i in range(4))
    assert len(set(per_chunk)) == 4  # chunk 2's policy differs from chunk 1's, and so on

    batched = trainer(tmp_path / "batched", "train.episodes=4", "train.chunks=1")
    versions = actor_versions(batched)
    batched.iteration_step()
    assert len(versions) == batched.steps and len(set(versions)) == 1


@pytest.mark.parametrize("algo", ["gchgg", "cher", "her"])
def test_updates_drawn_in_groups_equal_one_draw_before_each_update(algo, tmp_path):
    grouped, one_by_one = (trainer(tmp_path / name, algo=algo) for name in ("grouped", "one_by_one"))
    for t in (grouped, one_by_one):
        t.iteration_step()  # the same seed: the same buffer, networks and generators
    count = train.BATCHES_AHEAD + 5  # a whole group and part of another
    grouped_stats, reference_stats = metrics.IterationStats(), metrics.IterationStats()
    grouped.updates(count, grouped_stats)
    for _ in range(count):  # the reference order: draw, update, diagnostics, one update at a time
        batch = one_by_one.buffer.sample()
        reference_stats.add_update(one_by_one.agent.update(batch), batch, one_by_one.agent)
    assert grouped.agent.num_updates == one_by_one.agent.num_updates
    mine, theirs = grouped.agent.state_dict()["networks"], one_by_one.agent.state_dict()["networks"]
    assert mine.keys() == theirs.keys() and all(torch.equal(mine[key], theirs[key]) for key in mine)
    assert grouped_stats.losses == reference_stats.losses and len(grouped_stats.losses["loss_value"]) == count
    assert torch.equal(torch.stack(grouped_stats.clipped), torch.stack(reference_stats.clipped))
    assert grouped_stats.curriculum.keys() == reference_stats.curriculum.keys()
    for key, values in grouped_stats.curriculum.items():
        assert torch.equal(torch.stack(values), torch.stack(reference_stats.curriculum[key]))


def test_chunks_must_divide_the_episodes(tmp_path):
    with pytest.raises(ValueError, match="train.chunks must divide train.episodes"):
        trainer(tmp_path, "train.episodes=4", "train.chunks=3")


@pytest.mark.parametrize("during, expected", [(False, 3), (True, 6)])
def test_no_updates_before_warmup_ends_unless_asked(during, expected, tmp_path):
    # 2 chunks of 1 episode of 100 steps; warm-up ends with the second chunk, so only its share
    # (3 of 6 updates) runs, unless update_during_warmup.
    t = trainer(
        tmp_path, "train.episodes=2", "train.chunks=2", "train.updates=6", "train.warmup_steps=200",
        f"train.update_during_warmup={str(during).lower()}",
    )  # fmt: skip
    row = t.iteration_step()
    assert t.agent.num_updates == expected and row["warmup"] == 1.0
    t.iteration_step()
    assert t.agent.num_updates == expected + 6


@pytest.mark.parametrize("source, per_chunk", [("sampled", 16), ("collected", 2 * 100)])
def test_normalizer_source(source, per_chunk, tmp_path):
    # tiny(): batch 16, her.k = 1 (2 stored copies of every step); 2 chunks of 1 episode of 100 steps
    t = trainer(tmp_path, f"agent.normalizer_source={source}", "train.episodes=2", "train.chunks=2")
    t.iteration_step()
    assert int(t.agent.observation_normalizer.count) == 2 * per_chunk
    assert int(t.agent.goal_normalizer.count) == 2 * per_chunk


def test_training_stops_once_success_holds_for_the_patience(tmp_path, monkeypatch):
    t = trainer(tmp_path, "train.iterations=10", "train.stop_success=0.5", "train.stop_patience=2",
                task="reach", algo="her")
    rates = iter([0.6, 0.2, 0.7, 0.9, 0.1, 0.1])
    monkeypatch.setattr(evaluator, "evaluate", lambda *args: next(rates))
    rows = t.train()
    assert [row["success_rate"] for row in rows] == [0.6, 0.2, 0.7, 0.9]


def test_bad_loop_settings_name_themselves(tmp_path):
    with pytest.raises(ValueError, match="agent.normalizer_source must be one of 'sampled', 'collected', got 'batch'"):
        trainer(tmp_path, "agent.normalizer_source=batch")
    with pytest.raises(ValueError,
                       match=r"train.stop_success \(a success rate, or null\) must be a number in \[0, 1\], got 2"):
        trainer(tmp_path, "train.stop_success=2")
    with pytest.raises(ValueError, match="curriculum.scale must be one of 'raw', 'standardized', got 'z'"):
        trainer(tmp_path, "curriculum.scale=z")
    with pytest.raises(ValueError, match="curriculum.proximity must be one of"):
        trainer(tmp_path, "curriculum.proximity=target")
    # a schedule's section holds only its own settings: gchgg_code's update_every has no place in a fixed λ
    with pytest.raises(ConfigCompositionException, match="Key 'update_every' not in 'FixedTradeoffConfig'"):
        trainer(tmp_path, "tradeoff=fixed", algo="gchgg_code")
    for algo, unread in (("her", ("curriculum", "cher", "tradeoff")), ("gchgg", ("cher",)), ("cher", ("curriculum",))):
        assert all(config([f"algo={algo}"])[section] is None for section in unread)  # holds only what it reads


def test_hggs_stop_switches_the_curriculum_to_plain_sampling_and_survives_resume(tmp_path):
    # below any fraction: the first generation from the pool (iteration 1 on reach) stops HGG
    t = trainer(tmp_path, "train.iterations=3", task="reach", algo="gchgg")
    t.goal_generator.stop_threshold = -1.0
    rows = t.train()
    assert [row["stopped"] for row in rows] == [0.0, 1.0, 1.0]
    assert t.sampler.num_candidates == 1
    assert rows[2]["diversity_decided"] == 0.0 and rows[2]["diversity_spread"] == 0.0  # one candidate
    resumed = trainer(tmp_path, "train.iterations=3", task="reach", algo="gchgg")
    resumed.load_state_dict(t.state_dict())
    assert resumed.goal_generator.stopped and resumed.sampler.num_candidates == 1


def test_episode_diagnostics_count_the_objects_that_moved_rose_and_fell():
    """Four hand-made episodes of pick_no_obstacle (table top z = 1.0): one still, one pushed 2 cm, one
    lifted 5 cm, one lifted 12 cm and then dropped off the table; two of the four succeed."""
    from tensordict import TensorDict

    import envs
    from gchgg.run.metrics import IterationStats

    start = torch.tensor([0.75, 0.2, 1.015])
    path = torch.zeros(4, 4, 3)  # displacement of each episode's object at steps 0..3
    path[1, 2:, 1] = 0.02  # pushed along y
    path[2, 1:, 2] = 0.05  # lifted 5 cm
    path[3, 1, 2], path[3, 2, 2], path[3, 3, 2] = 0.12, 0.0, -0.1  # up 12 cm, back, down below the table top
    achieved = start + path
    goal = start + torch.tensor([0.0, 0.0, 0.05])
    rollout = TensorDict(
        {
            "achieved_goal": achieved[:, :-1],
            "desired_goal": goal.expand(4, 3, 3),
            "observation": torch.zeros(4, 3, 25),
            "next": {
                "achieved_goal": achieved[:, 1:],
                "is_success": torch.tensor([False, False, True, True]).view(4, 1, 1).expand(4, 3, 1),
            },
        },
        batch_size=[4, 3],
    )
    stats = IterationStats()
    stats.add_episodes(rollout, envs.geometry("pick_no_obstacle"))
    row = stats.row()
    assert row["object_moved"] == 0.75  # all but the still one: > 1 cm at some step
    assert row["object_rose_2cm"] == 0.5  # the 5 cm and the 12 cm lifts
    assert row["object_rose_10cm"] == 0.25
    assert row["object_off_table"] == 0.25  # the dropped one ends at z = 0.915 < 1.0
    assert row["train_success_rate"] == 0.5
    expected = torch.stack([(achieved[i, -1] - goal).norm() for i in range(4)]).mean()
    assert math.isclose(row["train_final_distance"], float(expected), rel_tol=1e-6)


def test_fractions_of_episodes_are_exact_ratios():
    """A success rate of 90 of 100 episodes is 0.9, not float32's 0.8999999762, so that it reaches
    train.stop_success=0.9 and the plot's "first ≥ 0.9"."""
    from gchgg.run.rollout import fraction

    mask = torch.arange(100) < 90
    assert fraction(mask) == 0.9 and mask.float().mean().item() < 0.9
    grid = torch.stack([torch.arange(100) < 90, torch.arange(100) < 30], dim=-1)  # [100, 2]
    assert fraction(grid, dim=0) == [0.9, 0.3]
