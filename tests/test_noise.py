"""Observation noise: its statistics on the chosen slices, nothing else touched, rewards from the true state."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import TransformedEnv

import envs
from gchgg.run.builders import make_observation_noise
from gchgg.transforms import ObservationNoise


def test_noise_statistics_on_the_chosen_slices_only():
    sigma, n = 0.01, 200_000
    layout = envs.observation_layout("push_new")
    noise = make_observation_noise(layout, True, sigma, torch.Generator().manual_seed(0))
    clean = torch.rand(n, 25)
    td = noise(TensorDict({"observation": clean.clone(), "achieved_goal": clean[:, 3:6].clone()}, [n]))
    delta = td["observation"] - clean
    eps = delta[:, layout["object_position"]]
    assert eps.mean(0).abs().max() < 4 * sigma / n**0.5  # mean 0 within 4 standard errors
    assert torch.allclose(eps.std(0), torch.full((3,), sigma), rtol=0.01)
    assert abs(float(torch.corrcoef(eps.T)[0, 1])) < 0.01  # independent axes
    assert torch.allclose(delta[:, layout["object_relative"]], eps, atol=1e-6)  # relative = noisy object - grip
    untouched = [s for name, s in layout.items() if name not in ("object_position", "object_relative")]
    assert all(torch.equal(delta[:, s], torch.zeros_like(delta[:, s])) for s in untouched)
    assert torch.allclose(td["achieved_goal"] - td["true_achieved_goal"], eps, atol=1e-6)
    assert torch.equal(td["true_achieved_goal"], clean[:, 3:6])


def test_noisy_env_keeps_reward_and_success_of_the_true_state():
    clean = envs.make("push_new", num_envs=8, seed=5)
    noisy = TransformedEnv(envs.make("push_new", num_envs=8, seed=5),
                           ObservationNoise(0.02, [slice(3, 6), slice(6, 9)],
                                            generator=torch.Generator().manual_seed(1)))
    actions = torch.rand(30, 8, 3, generator=torch.Generator().manual_seed(2)) * 2 - 1
    a, b = clean.reset(), noisy.reset()
    for action in actions:
        a = clean.step(a.set("action", action))
        b = noisy.step(b.set("action", action))
        for key in (("next", "reward"), ("next", "is_success"), ("next", "desired_goal")):
            assert torch.equal(a[key], b[key]), key
        assert torch.allclose(b["next", "true_achieved_goal"], a["next", "achieved_goal"])
        eps = b["next", "achieved_goal"] - a["next", "achieved_goal"]
        assert eps.abs().max() > 0
        assert torch.allclose(b["next", "observation"][:, 3:6] - a["next", "observation"][:, 3:6], eps, atol=1e-6)
        a, b = a["next"].exclude("reward", "done", "terminated", "truncated"), b["next"].exclude(
            "reward", "done", "terminated", "truncated")


def test_noise_rejects_bad_settings():
    with pytest.raises(ValueError, match=r"noise std \(metres\) must be a number >= 0"):
        ObservationNoise(-0.1, [slice(3, 6)])
    with pytest.raises(ValueError, match="position slice of length 3"):
        ObservationNoise(0.01, [slice(3, 5)])


@pytest.mark.parametrize("name", ["reach", "push_new"])
def test_a_noisy_env_still_takes_the_goals_and_object_positions_a_reset_is_given(name):
    # TransformedEnv passes only declared reset inputs: the KUKA envs declare them in state_spec.
    env = TransformedEnv(envs.make(name, num_envs=2, seed=0),
                         ObservationNoise(0.01, [slice(0, 3)], generator=torch.Generator().manual_seed(0)))
    goals = torch.tensor([[0.8, 0.2, 0.87], [0.7, 0.1, 0.87]]) if name == "push_new" else torch.tensor(
        [[0.7, 0.05, 1.25], [0.8, -0.05, 1.15]])
    reset = {"desired_goal": goals}
    if name == "push_new":
        reset["object_position"] = torch.tensor([[0.75, 0.2, 0.87], [0.7, 0.25, 0.87]])
    td = env.reset(TensorDict(reset, [2]))
    assert torch.allclose(td["desired_goal"], goals)
    if name == "push_new":
        assert torch.allclose(td["true_achieved_goal"][:, :2], reset["object_position"][:, :2], atol=1e-6)
    rollout = env.rollout(3, tensordict=td, auto_reset=False)
    assert torch.allclose(rollout["next", "desired_goal"][:, -1], goals)
