"""HindsightRelabel and EpisodeEnergy: where relabelled goals come from, rewards, layout, memory, energy values."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.transforms import Compose

from gchgg.transforms import EpisodeEnergy, GoalToNext, HerStrategy, HindsightRelabel, trajectory_energy

THRESHOLD = 0.05  # metres


def reward(achieved_goal: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
    """Eq. 23: 0 within the threshold, else -1 (a local copy; the tasks' own lives in envs)."""
    distance = torch.linalg.vector_norm(achieved_goal - goal, dim=-1)
    return torch.where(distance > THRESHOLD, -1.0, 0.0)


def episodes(num: int = 3, steps: int = 10, obs_dim: int = 25, action_dim: int = 3, seed: int = 0) -> TensorDict:
    """Rollout-shaped episodes whose next achieved goals encode (episode, step): ag_next[n, u] = (n, u, 0.5)."""
    g = torch.Generator().manual_seed(seed)
    n = torch.arange(num, dtype=torch.float32).view(num, 1).expand(num, steps)
    u = torch.arange(steps, dtype=torch.float32).view(1, steps).expand(num, steps)
    achieved_next = torch.stack([n, u, torch.full_like(n, 0.5)], -1)
    achieved = torch.cat([torch.stack([n[:, :1], -torch.ones(num, 1), torch.full((num, 1), 0.5)], -1),
                          achieved_next[:, :-1]], 1)
    desired = (torch.rand(num, 1, 3, generator=g) * 10 + 20).expand(num, steps, 3)
    done = torch.zeros(num, steps, 1, dtype=torch.bool)
    done[:, -1] = True
    return TensorDict(
        {
            "observation": torch.randn(num, steps, obs_dim, generator=g),
            "action": torch.rand(num, steps, action_dim, generator=g),
            "achieved_goal": achieved,
            "desired_goal": desired,
            "is_success": torch.zeros(num, steps, 1, dtype=torch.bool),
            "done": torch.zeros(num, steps, 1, dtype=torch.bool),
            "terminated": torch.zeros(num, steps, 1, dtype=torch.bool),
            "truncated": torch.zeros(num, steps, 1, dtype=torch.bool),
            "next": {
                "observation": torch.randn(num, steps, obs_dim, generator=g),
                "achieved_goal": achieved_next,
                "desired_goal": desired,
                "reward": -torch.ones(num, steps, 1),
                "is_success": torch.zeros(num, steps, 1, dtype=torch.bool),
                "done": done,
                "terminated": torch.zeros(num, steps, 1, dtype=torch.bool),
                "truncated": done.clone(),
            },
        },
        [num, steps],
    )


def relabel(strategy="future", k=4, seed=0, **kwargs) -> HindsightRelabel:
    return HindsightRelabel(reward, k=k, strategy=strategy, generator=torch.Generator().manual_seed(seed), **kwargs)


def sources(out: TensorDict, num: int, k: int, steps: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(episode, step u) encoded in each relabelled goal, as [N, k, T] tensors."""
    goals = out["desired_goal"].view(num, k + 1, steps, 3)[:, 1:]
    return goals[..., 0].long(), goals[..., 1].long()


def test_future_goals_come_from_later_steps_of_the_same_episode():
    num, k, steps = 40, 4, 10
    out = relabel("future", k)(episodes(num, steps))
    episode, step = sources(out, num, k, steps)
    assert (episode == torch.arange(num).view(num, 1, 1)).all()
    t = torch.arange(steps)
    assert (step >= t).all() and (step <= steps - 1).all()  # next achieved goal of u in [t, T-1]
    assert (step[..., -1] == steps - 1).all()  # the last step can only use the final goal
    # u is uniform on {t, ..., T-1}: at t = 0 every step is used, each about 1/T of the time.
    counts = torch.bincount(step[..., 0].flatten(), minlength=steps).float()
    assert (counts > 0).all()
    expected = num * k / steps
    assert ((counts - expected).abs() < 4 * expected**0.5 + 1).all(), counts


def test_final_goal_is_the_last_achieved_goal():
    num, k, steps = 3, 2, 7
    data = episodes(num, steps)
    out = relabel("final", k)(data)
    goals = out["desired_goal"].view(num, k + 1, steps, 3)[:, 1:]
    assert torch.equal(goals, data["next", "achieved_goal"][:, None, -1:].expand(num, k, steps, 3))


def test_episode_strategy_uses_earlier_steps_too():
    num, k, steps = 30, 4, 10
    out = relabel(HerStrategy.EPISODE, k)(episodes(num, steps))
    episode, step = sources(out, num, k, steps)
    assert (episode == torch.arange(num).view(num, 1, 1)).all()
    assert (step < torch.arange(steps)).any()  # unlike "future"
    assert step.min() == 0 and step.max() == steps - 1


def test_rewards_targets_and_originals():
    num, k, steps = 4, 4, 12
    data = episodes(num, steps)
    out = relabel("future", k)(data)
    achieved_next = out["next", "achieved_goal"]
    assert out["next", "reward"].shape == (num * (k + 1) * steps, 1)
    assert out["next", "reward"].dtype == data["next", "reward"].dtype
    assert torch.equal(out["next", "reward"].squeeze(-1), reward(achieved_next, out["desired_goal"]))
    assert (out["next", "reward"] == 0).any() and (out["next", "reward"] == -1).any()
    # every copy keeps the goal its episode was collected for, which is its task's goal here (no task_goal
    # in the episode); copy 0 is the original transition
    view = out.view(num, k + 1, steps)
    assert torch.equal(view["episode_goal"], data["desired_goal"][:, None].expand(num, k + 1, steps, 3))
    assert torch.equal(view["task_goal"], view["episode_goal"])
    assert torch.equal(view[:, 0]["desired_goal"], data["desired_goal"])
    for key in ("observation", "action", ("next", "observation"), ("next", "done"), ("next", "truncated")):
        assert torch.equal(view[key], data[key][:, None].expand_as(view[key])), key


def test_an_episode_collected_for_an_intermediate_goal_keeps_its_task_goal():
    """HGG collects an episode for an intermediate goal and names its target task's goal T* under task_goal:
    every transition, relabelled or not, keeps both; desired_goal is relabelled."""
    num, k, steps = 3, 2, 6
    data = episodes(num, steps)
    task = torch.arange(num * 3, dtype=torch.float32).view(num, 1, 3).expand(num, steps, 3)
    data.set("task_goal", task.clone())
    view = relabel("future", k)(data).view(num, k + 1, steps)
    assert torch.equal(view["task_goal"], task[:, None].expand(num, k + 1, steps, 3))
    assert torch.equal(view["episode_goal"], data["desired_goal"][:, None].expand(num, k + 1, steps, 3))
    assert not torch.equal(view[:, 1:]["desired_goal"], view[:, 1:]["episode_goal"])


def test_layout_flatten_and_dropped_keys():
    num, k, steps = 2, 3, 5
    data = episodes(num, steps)
    before = data.clone()
    flat = relabel("future", k)(data)
    assert flat.batch_size == (num * (k + 1) * steps,)
    nested = relabel("future", k, flatten=False)(data)
    assert nested.batch_size == (num, k + 1, steps)
    assert torch.equal(flat["desired_goal"], nested["desired_goal"].reshape(-1, 3))  # row = (n·(k+1) + c)·T + t
    assert (data == before).all()  # the input is untouched
    keys = set(flat.keys(True, True))
    for dropped in ("is_success", ("next", "is_success"), ("next", "desired_goal"), "done", "terminated"):
        assert dropped not in keys
    assert {"episode_goal", "task_goal", "achieved_goal", ("next", "achieved_goal"), ("next", "terminated")} <= keys
    restored = GoalToNext()(flat.clone())
    assert torch.equal(restored["next", "desired_goal"], flat["desired_goal"])


def test_kept_next_goal_is_relabelled_too():
    out = relabel("final", 2, drop_keys=())(episodes(2, 5))
    assert torch.equal(out["next", "desired_goal"], out["desired_goal"])


def test_k_zero_keeps_originals_with_recomputed_reward():
    data = episodes(2, 6)
    data["next", "achieved_goal"][0, 3] = data["desired_goal"][0, 3]  # one success
    out = relabel("future", 0)(data)
    assert out.batch_size == (12,)
    assert out["next", "reward"].view(2, 6)[0, 3] == 0 and out["next", "reward"].sum() == -11


def test_same_generator_seed_same_goals():
    data = episodes(3, 8)
    a, b, c = relabel(seed=1)(data), relabel(seed=1)(data), relabel(seed=2)(data)
    assert torch.equal(a["desired_goal"], b["desired_goal"])
    assert not torch.equal(a["desired_goal"], c["desired_goal"])


def test_bad_settings_are_named():
    with pytest.raises(ValueError, match="strategy must be one of 'future', 'final', 'episode', got 'later'"):
        HindsightRelabel(reward, strategy="later")
    with pytest.raises(ValueError, match="k .* integer >= 0, got -1"):
        HindsightRelabel(reward, k=-1)
    with pytest.raises(TypeError, match="reward_fn"):
        HindsightRelabel(None)
    with pytest.raises(KeyError, match="achieved_goal"):
        relabel()(episodes(1, 3).exclude(("next", "achieved_goal")))
    with pytest.raises(ValueError, match="reward_fn must map"):
        HindsightRelabel(lambda a, g: torch.zeros(3), generator=torch.Generator())(episodes(1, 3))


def test_stored_transition_fits_the_memory_budget():
    """10,000 push_new episodes (T = 100, obs 25, action 3) with 4 copies each must fit in 2 GB."""
    out = Compose(EpisodeEnergy(), relabel("future", 4))(episodes(2, 100, obs_dim=25, action_dim=3))
    per_transition = out.bytes() / out.numel()
    total = per_transition * 10_000 * 5 * 100
    print(f"one stored transition: {per_transition:.0f} bytes; 10,000 push_new episodes: {total / 1e9:.2f} GB")
    assert per_transition == 283  # 2 × obs 100 + action 12 + 5 goals 60 + next ag 12 + reward, energy 8 + 3 flags
    assert total <= 2e9


def test_trajectory_energy_values():
    dt, g = 0.05, 9.81
    still = torch.zeros(6, 3)
    slide = torch.tensor([[0.01 * t, 0.0, 0.0] for t in range(6)])  # constant 0.2 m/s
    lift = torch.tensor([[0.0, 0.0, 0.01 * t] for t in range(6)])
    drop = torch.tensor([[0.0, 0.0, -0.01 * t] for t in range(6)])
    fast = torch.tensor([[0.5 * t, 0.0, 0.0] for t in range(6)])  # 10 m/s: clipped per step
    energy = trajectory_energy(torch.stack([still, slide, lift, drop, fast]), dt=dt)
    # a drop loses more potential energy per step than its speed adds: every increase is clipped to 0
    expected = torch.tensor([0.0, 0.5 * 0.2**2, 5 * g * 0.01 + 0.5 * 0.2**2, 0.0, 0.5])
    torch.testing.assert_close(energy, expected)
    with pytest.raises(ValueError, match="dt must be a number > 0"):
        trajectory_energy(still, dt=0.0)


def test_episode_energy_is_written_per_step():
    data = episodes(3, 5)
    data["next", "achieved_goal"][1] = data["achieved_goal"][1]  # episode 1 never moves (first step aside)
    out = EpisodeEnergy()(data.clone())
    positions = torch.cat([data["achieved_goal"], data["next", "achieved_goal"][:, -1:]], 1)
    expected = trajectory_energy(positions)
    assert out["energy"].shape == (3, 5)
    torch.testing.assert_close(out["energy"], expected[:, None].expand(3, 5))
    assert out["energy"][0, 0] > 0


def test_future_goals_are_uniform_over_the_remaining_steps_at_every_step():
    # Chi-square per step t: the hindsight goal of a copy of step t is the next achieved goal of a
    # step u uniform in {t, ..., T-1}; a draw that under-samples the last steps fails here.
    from scipy.stats import chisquare

    steps, episodes, k = 12, 3000, 4
    index = torch.arange(steps, dtype=torch.float32)
    achieved_next = torch.stack([index, torch.zeros(steps), torch.zeros(steps)], -1).expand(episodes, steps, 3)
    data = TensorDict({
        "observation": torch.zeros(episodes, steps, 2), "action": torch.zeros(episodes, steps, 1),
        "achieved_goal": achieved_next - torch.tensor([1.0, 0.0, 0.0]), "desired_goal": torch.ones(episodes, steps, 3),
        "next": {"observation": torch.zeros(episodes, steps, 2), "achieved_goal": achieved_next,
                 "reward": -torch.ones(episodes, steps, 1)},
    }, [episodes, steps])  # fmt: skip
    her = HindsightRelabel(lambda a, g: -(torch.linalg.vector_norm(a - g, dim=-1) > 0.05).float(), k=k,
                           generator=torch.Generator().manual_seed(0), flatten=False)
    source = her(data)["desired_goal"][:, 1:, :, 0].long()  # [N, k, T]: u of each copy
    for t in range(steps):
        drawn = source[:, :, t].reshape(-1)
        assert int(drawn.min()) >= t
        counts = torch.bincount(drawn - t, minlength=steps - t).numpy()
        if steps - t > 1:
            assert chisquare(counts).pvalue > 1e-4, (t, counts)
