"""Tests of gchgg.ddpg (networks, loss, agent) and gchgg.fast.small_batch: critic target, actor loss, target
updates, normalisers, exploration, checkpoints, errors, a small learning check and the one-row speed devices."""

from __future__ import annotations

import copy
import io
import math

import pytest
import torch
from tensordict import TensorDict

from gchgg.ddpg import DDPGAgent, HindsightDDPGLoss, RunningNormalizer, make_ddpg_networks

OBS, GOAL, ACT = 6, 3, 2


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def make_agent(seed: int = 0, **kwargs) -> DDPGAgent:
    kwargs.setdefault("hidden", (32, 32))
    return DDPGAgent(OBS, GOAL, ACT, generator=torch.Generator().manual_seed(seed), **kwargs)


def make_batch(size: int = 16, seed: int = 1, **overrides) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    batch = TensorDict(
        {
            "observation": torch.randn(size, OBS, generator=g),
            "desired_goal": torch.randn(size, GOAL, generator=g),
            "action": torch.rand(size, ACT, generator=g) * 2 - 1,
            "next": {
                "observation": torch.randn(size, OBS, generator=g),
                "reward": -(torch.rand(size, 1, generator=g) < 0.5).float(),
            },
        },
        [size],
    )
    for key, value in overrides.items():
        batch.set(key, value)
    return batch


def set_constant_output(net: torch.nn.Module, value: float) -> None:
    """Make an actor / critic MLP output the constant ``value`` (before the actor's tanh)."""
    last = net.mlp[-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.fill_(value)


def all_parameters(agent: DDPGAgent) -> dict[str, torch.Tensor]:
    return {k: v.clone() for k, v in agent.loss_module.state_dict().items()}


# -- critic target -------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("next_q", "clip_return", "bootstrap"),
    [
        (3.0, True, 0.0),  # positive Q' clipped to 0
        (-80.0, True, -50.0),  # below -1/(1-γ) = -50: clipped
        (-10.0, True, -10.0),  # inside the range: unchanged
        (3.0, False, 3.0),  # no clipping when clip_return=False
    ],
)
def test_critic_target_is_clipped_bootstrap_without_done_mask(next_q, clip_return, bootstrap):
    agent = make_agent(clip_return=clip_return)
    loss = agent.loss_module
    set_constant_output(loss.target_critic, next_q)  # Q'(s', g, π'(s', g)) = next_q for every input
    set_constant_output(loss.critic, -2.0)  # Q(s, g, a) = -2
    batch = make_batch()
    # a done flag must not mask the bootstrap: the tasks only time out
    batch.set(("next", "done"), torch.ones(16, 1, dtype=torch.bool))
    batch.set(("next", "terminated"), torch.ones(16, 1, dtype=torch.bool))
    reward = batch["next", "reward"]
    expected_target = reward + 0.98 * bootstrap
    out = loss(batch)
    torch.testing.assert_close(out["target_value"], expected_target.mean())
    torch.testing.assert_close(out["loss_value"], (-2.0 - expected_target).square().mean())
    _, _, target_value = loss.critic_loss(*loss.inputs(batch))
    torch.testing.assert_close(target_value, expected_target)


def test_critic_target_uses_target_networks_and_the_transition_goal():
    agent = make_agent()
    loss = agent.loss_module
    with torch.no_grad():
        for p in loss.target_critic.parameters():  # target differs from the online critic
            p.add_(0.1)
    batch = make_batch()
    obs2, goal = batch["next", "observation"], batch["desired_goal"]
    with torch.no_grad():
        q_next = loss.target_critic(obs2, goal, loss.target_actor(obs2, goal)).clamp(-50.0, 0.0)
        q_online = loss.critic(obs2, goal, loss.actor(obs2, goal)).clamp(-50.0, 0.0)
    out = loss(batch)
    expected = (batch["next", "reward"] + 0.98 * q_next).mean()
    torch.testing.assert_close(out["target_value"], expected)
    assert not torch.allclose(out["target_value"], (batch["next", "reward"] + 0.98 * q_online).mean())


# -- actor loss ----------------------------------------------------------------------------------


@pytest.mark.parametrize("action_l2", [1.0, 0.25, 0.0])
def test_actor_loss_is_minus_q_plus_action_l2(action_l2):
    agent = make_agent(action_l2=action_l2)
    loss = agent.loss_module
    set_constant_output(loss.critic, -3.0)  # Q ≡ -3 whatever the action
    batch = make_batch()
    with torch.no_grad():
        pi = loss.actor(batch["observation"], batch["desired_goal"])
    assert pi.square().mean() > 0.01  # the penalty term is not trivially zero
    out = loss(batch)
    torch.testing.assert_close(out["loss_actor"], 3.0 + action_l2 * pi.square().mean())


def test_actor_loss_does_not_train_the_critic_and_critic_loss_does_not_train_the_actor():
    agent = make_agent()
    loss = agent.loss_module
    out = loss(make_batch())
    out["loss_actor"].backward()
    assert all(p.grad is None for p in loss.critic.parameters())
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in loss.actor.mlp.parameters())
    for p in loss.actor.parameters():
        p.grad = None
    loss(make_batch())["loss_value"].backward()
    assert all(p.grad is None for p in loss.actor.parameters())


# -- target updates ------------------------------------------------------------------------------


def _weights(network) -> dict:
    return {k: v.detach().clone() for k, v in network.named_parameters()}


def test_targets_start_equal_and_move_by_polyak_only_every_20th_update():
    agent = make_agent()
    loss = agent.loss_module

    def online():
        critic = {"v." + k: v for k, v in _weights(loss.critic).items()}
        return _weights(loss.actor) | critic

    def target():
        return _weights(loss.target_actor) | {"v." + k: v for k, v in _weights(loss.target_critic).items()}

    before = target()
    for key, value in online().items():
        torch.testing.assert_close(before[key], value, rtol=0, atol=0)
    moved = 0
    for step in range(1, 41):
        target_before = target()
        agent.update(make_batch(seed=step))
        online_after, target_after = online(), target()
        if step % 20:
            for key in online_after:
                torch.testing.assert_close(target_after[key], target_before[key], rtol=0, atol=0)
        else:
            moved += 1
            for key in online_after:
                expected = 0.95 * target_before[key] + 0.05 * online_after[key]
                torch.testing.assert_close(target_after[key], expected)
                assert not torch.allclose(target_after[key], target_before[key])
    assert moved == 2 and agent.num_updates == 40


# -- normalisers ---------------------------------------------------------------------------------


def test_running_normalizer_statistics_floor_and_clip():
    g = torch.Generator().manual_seed(0)
    a = torch.randn(100, 3, generator=g) * torch.tensor([2.0, 0.5, 0.0]) + torch.tensor([1.0, -3.0, 7.0])
    b = torch.randn(37, 3, generator=g) * torch.tensor([2.0, 0.5, 0.0]) + torch.tensor([1.0, -3.0, 7.0])
    norm = RunningNormalizer(3)
    torch.testing.assert_close(norm(torch.tensor([[1.0, -2.0, 9.0]])), torch.tensor([[1.0, -2.0, 5.0]]))  # identity
    norm.update(a)
    norm.update(b[None])  # any leading shape
    data = torch.cat([a, b]).double()
    torch.testing.assert_close(norm.loc, data.mean(0).float())
    std = data.std(0, unbiased=False).clamp_min(1e-2).float()
    torch.testing.assert_close(norm.scale, std)
    assert norm.scale[2] == pytest.approx(1e-2)  # constant feature: std floored
    x = torch.stack([data.mean(0).float() + std, torch.tensor([1e3, -1e3, 7.0])])
    torch.testing.assert_close(norm(x), torch.tensor([[1.0, 1.0, 1.0], [5.0, -5.0, 0.0]]), rtol=0, atol=1e-4)


def test_update_normalizer_reaches_online_and_target_networks():
    agent = make_agent()
    loss = agent.loss_module
    batch = make_batch()
    obs, goal = batch["observation"], batch["desired_goal"]
    before = loss.target_actor(obs, goal)
    agent.update_normalizer(obs * 3 + 1, goal - 2)
    after_online, after_target = loss.actor(obs, goal), loss.target_actor(obs, goal)
    torch.testing.assert_close(after_target, after_online)  # targets use the new statistics too
    assert not torch.allclose(after_target, before)
    torch.testing.assert_close(agent.goal_normalizer.loc, (goal - 2).mean(0))


def test_update_normalizer_rejects_bad_input():
    agent = make_agent()
    with pytest.raises(ValueError, match="NaN or inf"):
        agent.update_normalizer(torch.full((4, OBS), math.nan), torch.zeros(4, GOAL))
    with pytest.raises(ValueError, match=r"\[\.\.\., 6\]"):
        agent.update_normalizer(torch.zeros(4, OBS + 1), torch.zeros(4, GOAL))


# -- exploration ---------------------------------------------------------------------------------


def test_exploration_statistics_and_clipping():
    n = 100_000
    agent = make_agent()
    obs, goal = torch.zeros(n, OBS), torch.zeros(n, GOAL)
    set_constant_output(agent.actor, 0.0)  # π ≡ 0
    action = agent.act(obs, goal, explore=True, generator=torch.Generator().manual_seed(0))
    assert action.shape == (n, ACT) and action.abs().max() <= 1.0
    # |a| > 0.9 happens for a uniform action with probability 0.1, for N(0, 0.2²) with 7e-6
    eps_hat = (action.abs() > 0.9).float().mean().item() / 0.1
    assert eps_hat == pytest.approx(0.3, abs=0.02)
    # E[a²] = eps/3 + (1 - eps)·σ²
    sigma_hat = math.sqrt(((action.square().mean().item()) - 0.3 / 3) / 0.7)
    assert sigma_hat == pytest.approx(0.2, abs=0.01)

    # clipping: π ≡ tanh(atanh 0.9) = 0.9, so π + noise > 1 with probability P(z > 0.5) = 0.3085
    set_constant_output(agent.actor, math.atanh(0.9))
    action = agent.act(obs, goal, explore=True, generator=torch.Generator().manual_seed(1))
    assert action.max() == 1.0 and action.min() >= -1.0
    assert (action == 1.0).float().mean().item() == pytest.approx(0.7 * 0.3085, abs=0.01)


def test_act_is_deterministic_without_exploration_and_reproducible_with_a_generator():
    agent = make_agent()
    batch = make_batch(size=64)
    obs, goal = batch["observation"], batch["desired_goal"]
    greedy = agent.act(obs, goal)
    torch.testing.assert_close(greedy, agent.actor(obs, goal).detach())
    a1 = agent.act(obs, goal, explore=True, generator=torch.Generator().manual_seed(5))
    a2 = agent.act(obs, goal, explore=True, generator=torch.Generator().manual_seed(5))
    a3 = agent.act(obs, goal, explore=True, generator=torch.Generator().manual_seed(6))
    torch.testing.assert_close(a1, a2, rtol=0, atol=0)
    assert not torch.equal(a1, a3) and not torch.equal(a1, greedy)
    with pytest.raises(ValueError, match="generator"):
        agent.act(obs, goal, explore=True)
    random = agent.random_action(10_000, torch.Generator().manual_seed(0))
    assert random.shape == (10_000, ACT) and random.min() >= -1 and random.max() < 1
    assert random.mean().item() == pytest.approx(0.0, abs=0.02)


def test_policy_module_writes_actions_into_a_tensordict():
    agent = make_agent()
    td = make_batch(size=8).select("observation", "desired_goal")
    greedy = agent.policy()(td.clone())["action"]
    torch.testing.assert_close(greedy, agent.act(td["observation"], td["desired_goal"]))
    explored = agent.policy(explore=True, generator=torch.Generator().manual_seed(0))(td.clone())["action"]
    rng = torch.Generator().manual_seed(0)
    expected = agent.act(td["observation"], td["desired_goal"], explore=True, generator=rng)
    torch.testing.assert_close(explored, expected)
    random = agent.policy(random=True, generator=torch.Generator().manual_seed(0))(td.clone())["action"]
    torch.testing.assert_close(random, agent.random_action(8, torch.Generator().manual_seed(0)))


# -- value for HGG -------------------------------------------------------------------------------


def test_value_is_clipped_q_of_the_policy_action():
    agent = make_agent()
    batch = make_batch(size=32)
    obs, goal = batch["observation"], batch["desired_goal"]
    with torch.no_grad():
        bias = agent.critic.mlp[-1].bias
        bias -= agent.critic(obs, goal, agent.actor(obs, goal)).mean() + 1.0  # Q(s, π(s)) ≈ -1 on average
        expected = agent.critic(obs, goal, agent.actor(obs, goal)).squeeze(-1).clamp(-50.0, 0.0)
    value = agent.value(obs, goal)
    assert value.shape == (32,) and not value.requires_grad
    assert (value < 0).any()
    torch.testing.assert_close(value, expected)
    value.mul_(2.0)  # an ordinary tensor: callers may modify it in place
    set_constant_output(agent.critic, 7.0)
    assert torch.equal(agent.value(obs, goal), torch.zeros(32))
    set_constant_output(agent.critic, -1e3)
    assert torch.equal(agent.value(obs, goal), torch.full((32,), -50.0))


# -- checkpoints ---------------------------------------------------------------------------------


def test_state_dict_round_trip_gives_identical_subsequent_updates():
    agent = make_agent(seed=0)
    agent.update_normalizer(make_batch(64, seed=100)["observation"], make_batch(64, seed=100)["desired_goal"])
    for step in range(25):  # past one target update
        agent.update(make_batch(seed=step))
    buffer = io.BytesIO()
    torch.save(agent.state_dict(), buffer)
    buffer.seek(0)

    resumed = make_agent(seed=123)  # different initial weights, overwritten by the checkpoint
    resumed.load_state_dict(torch.load(buffer, weights_only=False))
    assert resumed.num_updates == 25
    for step in range(25, 50):  # crosses the next target update (at 40)
        batch = make_batch(seed=step)
        assert agent.update(batch) == resumed.update(batch)
        norm_batch = make_batch(8, seed=1000 + step)
        agent.update_normalizer(norm_batch["observation"], norm_batch["desired_goal"])
        resumed.update_normalizer(norm_batch["observation"], norm_batch["desired_goal"])
    for (key, a), b in zip(all_parameters(agent).items(), all_parameters(resumed).values(), strict=True):
        assert torch.equal(a, b), key
    batch = make_batch()
    assert torch.equal(agent.value(batch["observation"], batch["desired_goal"]),
                       resumed.value(batch["observation"], batch["desired_goal"]))  # fmt: skip
    # the resumed target networks share the online normalisers' statistics (loaded in place)
    loss = resumed.loss_module
    assert (loss.target_critic.observation_normalizer.mean.data_ptr()
            == loss.actor.observation_normalizer.mean.data_ptr())


def test_agent_loads_checkpoints_written_while_the_loss_subclassed_ddpg_loss():
    agent = make_agent(seed=0)
    for step in range(21):  # past one target update: targets differ from the online networks
        agent.update(make_batch(seed=step))
    state = agent.state_dict()
    old_prefixes = {"actor.": "actor_network_params.module.", "critic.": "value_network_params.module.",
                    "target_actor.": "target_actor_network_params.module.",
                    "target_critic.": "target_value_network_params.module."}  # fmt: skip
    old_networks = {}
    for key, value in state["networks"].items():
        prefix = next(p for p in sorted(old_prefixes, key=len, reverse=True) if key.startswith(p))
        old_networks[old_prefixes[prefix] + key[len(prefix):]] = value
    resumed = make_agent(seed=5)
    resumed.load_state_dict(state | {"networks": old_networks})
    for (key, a), b in zip(all_parameters(agent).items(), all_parameters(resumed).values(), strict=True):
        assert torch.equal(a, b), key


def test_load_state_dict_rejects_other_settings_and_incomplete_states():
    state = copy.deepcopy(make_agent(hidden=(32, 32)).state_dict())
    with pytest.raises(ValueError, match="hidden"):
        make_agent(hidden=(16, 16)).load_state_dict(state)
    del state["actor_optimizer"]
    with pytest.raises(KeyError, match="actor_optimizer"):
        make_agent().load_state_dict(state)


# -- errors --------------------------------------------------------------------------------------


def test_non_finite_loss_raises_and_leaves_parameters_unchanged():
    agent = make_agent()
    before = all_parameters(agent)
    batch = make_batch()
    batch["next", "reward"][3] = math.nan
    with pytest.raises(FloatingPointError, match="not finite"):
        agent.update(batch)
    assert agent.num_updates == 0
    for key, value in all_parameters(agent).items():
        assert torch.equal(value, before[key]), key


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"gamma": 1.0}, "gamma"),
        ({"polyak": 1.5}, "polyak"),
        ({"target_update_every": 0}, "target_update_every"),
        ({"actor_lr": 0.0}, "actor_lr"),
        ({"critic_lr": -1e-3}, "critic_lr"),
        ({"action_l2": -1.0}, "action_l2"),
        ({"random_eps": 1.3}, "random_eps"),
        ({"noise_std": -0.1}, "noise_std"),
        ({"hidden": ()}, "hidden"),
        ({"norm_std_min": 0.0}, "std_min"),
    ],
)
def test_bad_settings_name_the_setting(kwargs, name):
    with pytest.raises(ValueError, match=name):
        make_agent(**kwargs)


def test_bad_shapes_are_reported():
    agent = make_agent()
    with pytest.raises(ValueError, match="observation"):
        agent.act(torch.zeros(4, OBS + 1), torch.zeros(4, GOAL))
    with pytest.raises(ValueError, match="leading shape"):
        agent.value(torch.zeros(4, OBS), torch.zeros(5, GOAL))
    with pytest.raises(ValueError, match="reward"):
        agent.update(make_batch().set(("next", "reward"), torch.zeros(16, 2)))


def test_loss_module_works_on_its_own_on_a_tensordict_batch():
    actor, critic = make_ddpg_networks(OBS, GOAL, ACT, hidden=(16,))
    loss = HindsightDDPGLoss(actor, critic, gamma=0.9, action_l2=0.5)
    batch = make_batch()
    out = loss(batch)
    loss_actor, loss_value, _, target = loss.losses(*loss.inputs(batch))
    torch.testing.assert_close(out["loss_actor"], loss_actor)
    torch.testing.assert_close(out["loss_value"], loss_value)
    assert loss.return_range == pytest.approx((-10.0, 0.0))
    assert (target <= 0.0).all()  # rewards in {-1, 0}, bootstrap clipped to <= 0
    sum(v for k, v in out.items() if k.startswith("loss_")).backward()
    assert all(p.grad is not None for p in actor.parameters()) and all(p.grad is not None for p in critic.parameters())
    assert all(p.grad is None for p in loss.target_actor.parameters())
    assert all(p.requires_grad for p in critic.parameters())  # the actor loss left the critic trainable
    # the loss's networks are the modules it was given; its targets are its own parameters
    assert loss.actor is actor.module and loss.critic is critic.module
    assert {id(p) for p in loss.parameters()} >= {id(p) for p in actor.parameters()}


# -- learning ------------------------------------------------------------------------------------

_STEP, _TOLERANCE = 0.5, 0.1  # 1-D toy: x' = clip(x + 0.5·a, -1, 1); success when |x' - g| <= 0.1


def _toy_step(x: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    return (x + _STEP * a).clamp(-1.0, 1.0)


def _toy_reward(x: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    return -((x - g).abs() > _TOLERANCE).float()


def _train_toy(updates: int, hidden, seed: int = 0) -> tuple[DDPGAgent, torch.Generator]:
    """DDPG on uniformly random transitions of a 1-D goal-reaching task (reference hyperparameters)."""
    g = torch.Generator().manual_seed(seed)
    agent = DDPGAgent(1, 1, 1, hidden=hidden, generator=g)
    n = 20_000
    x, goal, a = (torch.rand(n, 1, generator=g) * 2 - 1 for _ in range(3))
    x2 = _toy_step(x, a)
    data = TensorDict(
        {
            "observation": x,
            "desired_goal": goal,
            "action": a,
            "next": {"observation": x2, "reward": _toy_reward(x2, goal)},
        },
        [n],
    )
    agent.update_normalizer(x, goal)
    for _ in range(updates):
        agent.update(data[torch.randint(n, (256,), generator=g)])
    return agent, g


def _toy_success(agent: DDPGAgent, g: torch.Generator, policy=None) -> float:
    x, goal = torch.rand(2000, 1, generator=g) * 2 - 1, torch.rand(2000, 1, generator=g) * 2 - 1
    for _ in range(4):  # the farthest goal (distance 2) needs 4 steps of 0.5
        action = agent.act(x, goal) if policy is None else policy(x, goal)
        x = _toy_step(x, action)
    return ((x - goal).abs() <= _TOLERANCE).float().mean().item()


def test_ddpg_learns_a_1d_goal_reaching_toy():
    agent, g = _train_toy(updates=2000, hidden=(64, 64))
    untrained = DDPGAgent(1, 1, 1, hidden=(64, 64), generator=torch.Generator().manual_seed(0))
    assert _toy_success(agent, g) >= 0.85 > _toy_success(untrained, g) + 0.4
    # the critic knows that far goals are worth less than goals one step away
    x = torch.zeros(200, 1)
    near, far = torch.linspace(-0.5, 0.5, 200)[:, None], torch.linspace(0.75, 1.0, 200)[:, None]
    assert agent.value(x, near).mean() > agent.value(x, far).mean() + 0.5


@pytest.mark.slow
def test_ddpg_learns_the_toy_value_with_reference_networks():
    agent, g = _train_toy(updates=6000, hidden=(256, 256, 256))
    assert _toy_success(agent, g) >= 0.95
    # the optimal value: n = ceil((|x - g| - 0.1) / 0.5) steps, -(1 - γ^(n-1)) / (1 - γ)
    x, goal = torch.rand(2000, 1, generator=g) * 2 - 1, torch.rand(2000, 1, generator=g) * 2 - 1
    steps = torch.ceil(((x - goal).abs() - _TOLERANCE).clamp_min(0.0) / _STEP).squeeze(-1)
    v_star = -(1 - 0.98 ** (steps - 1).clamp_min(0)) / (1 - 0.98)
    assert (agent.value(x, goal) - v_star).abs().mean() <= 0.5


def test_small_batch_actor_acts_as_the_module_bit_for_bit_after_updates_and_loads():
    """act() on fewer than MIN_BATCH rows skips the modules (SmallBatchActor); same actions, always."""
    from gchgg.ddpg import DDPGAgent, DDPGConfig
    from gchgg.fast.linear import MIN_BATCH

    g = torch.Generator().manual_seed(0)
    agent = DDPGAgent(25, 3, 4, DDPGConfig(hidden=(64, 64)), generator=torch.Generator().manual_seed(1))
    other = DDPGAgent(25, 3, 4, DDPGConfig(hidden=(64, 64)), generator=torch.Generator().manual_seed(2))

    def check():
        for rows in (1, 7, MIN_BATCH - 1):
            observation, goal = torch.randn(rows, 25, generator=g), torch.randn(rows, 3, generator=g)
            assert agent._small_batch_actor.takes(observation, goal)
            with torch.no_grad():
                assert torch.equal(agent.act(observation, goal), agent.actor(observation, goal))

    check()
    batch = TensorDict({
        "observation": torch.randn(256, 25, generator=g), "desired_goal": torch.randn(256, 3, generator=g),
        "action": torch.rand(256, 4, generator=g) * 2 - 1,
        "next": {"observation": torch.randn(256, 25, generator=g), "reward": -torch.ones(256, 1)},
    }, [256])  # fmt: skip
    agent.update_normalizer(batch["observation"] * 3 + 1, batch["desired_goal"])
    agent.update(batch)  # weights and statistics move in place
    check()
    agent.load_state_dict(other.state_dict())
    check()
    assert not agent._small_batch_actor.takes(torch.randn(MIN_BATCH, 25), torch.randn(MIN_BATCH, 3))


def test_rollout_policy_acts_as_act_with_exploration_call_for_call():
    """The rollout's policy gives act(explore=True)'s actions and draws, also after the statistics or a clip
    changed under it, for other shapes, and raises what act raises."""
    from gchgg.ddpg import DDPGAgent, DDPGConfig

    agent = DDPGAgent(25, 3, 3, DDPGConfig(), generator=torch.Generator().manual_seed(0))
    data = torch.Generator().manual_seed(1)
    agent.update_normalizer(torch.randn(500, 25, generator=data) * 3, torch.randn(500, 3, generator=data))
    mine, theirs = torch.Generator().manual_seed(2), torch.Generator().manual_seed(2)
    policy = agent.rollout_policy(mine)

    def same(rows: int, times: int = 40) -> None:
        for _ in range(times):
            observation, goal = torch.randn(rows, 25, generator=data) * 4, torch.randn(rows, 3, generator=data)
            with torch.inference_mode():
                action = policy(observation, goal)
                expected = agent.act(observation, goal, explore=True, generator=theirs)
            assert torch.equal(action, expected)
            assert torch.equal(mine.get_state(), theirs.get_state())

    same(1)
    same(5, times=3)  # more rows: act's path
    agent.update_normalizer(torch.randn(500, 25, generator=data) + 2, torch.randn(500, 3, generator=data))
    same(1)  # statistics changed in place after the policy was made
    policy = agent.rollout_policy(mine)  # made anew: the joined statistics as they are now
    same(1)
    agent.observation_normalizer.clip = 0.5  # a clip changed after: most entries at it
    same(1)
    with pytest.raises(ValueError, match="observation"):
        policy(torch.randn(1, 24), torch.randn(1, 3))
    action = policy(torch.randn(1, 25, requires_grad=True), torch.randn(1, 3))  # gradients enabled: act's no_grad
    assert not action.requires_grad
    with pytest.raises(ValueError, match="generator"):
        agent.rollout_policy(None)


@pytest.mark.parametrize("random_eps", [0.3, 0.7, 0.0, 1.0])
def test_exploring_one_row_is_eq_22_with_the_same_draws(random_eps):
    """act(explore=True) on one row (the per-episode loop's branch) gives what eq. 22 gives, draw for draw,
    including where the coin equals random_eps rounded to float32 (0.7 rounds down)."""
    from gchgg.ddpg import DDPGAgent, DDPGConfig

    agent = DDPGAgent(25, 3, 4, DDPGConfig(hidden=(32, 32)), generator=torch.Generator().manual_seed(0))
    agent.random_eps = random_eps  # a setting changed after construction is followed
    g, draws = torch.Generator().manual_seed(1), torch.Generator().manual_seed(2)
    eps32 = torch.tensor(random_eps, dtype=torch.float32)
    for _ in range(300):
        observation, goal = torch.randn(1, 25, generator=g), torch.randn(1, 3, generator=g)
        state = draws.get_state()
        action = agent.act(observation, goal, explore=True, generator=draws)
        reference = torch.Generator()
        reference.set_state(state)  # eq. 22 written out, from the same state: coin, uniform action, noise
        coin = torch.rand(1, generator=reference)
        uniform = torch.rand(1, 4, generator=reference) * 2 - 1
        noisy = (agent.actor(observation, goal) + torch.randn(1, 4, generator=reference) * agent.noise_std).clamp(-1, 1)
        assert torch.equal(action, uniform if bool(coin < eps32) else noisy)
        assert torch.equal(draws.get_state(), reference.get_state())  # the same amount drawn
    # the coin at the boundary: a coin equal to float32(0.7) is not below it
    agent.random_eps = 0.7
    agent._explore_one_row(torch.zeros(1, 4), torch.Generator().manual_seed(0))  # rounds random_eps
    eps32 = agent._explore_one_row.random_eps32
    assert eps32 == (0.7, float(torch.tensor(0.7, dtype=torch.float32))) and eps32[1] < 0.7


def test_small_batch_actor_with_unlike_normalisers_keeps_their_own_standardisation():
    """Normalisers that clip differently are not joined; still the module's actions."""
    from gchgg.ddpg import DDPGAgent, DDPGConfig

    agent = DDPGAgent(25, 3, 3, DDPGConfig(hidden=(32, 32)), generator=torch.Generator().manual_seed(0))
    g = torch.Generator().manual_seed(1)
    agent.update_normalizer(torch.randn(100, 25, generator=g) * 4, torch.randn(100, 3, generator=g))
    observation, goal = torch.randn(5, 25, generator=g) * 30, torch.randn(5, 3, generator=g) * 30
    with torch.no_grad():
        assert agent._small_batch_actor._statistics() is not None
        assert torch.equal(agent.act(observation, goal), agent.actor(observation, goal))
        agent.goal_normalizer.clip = 2.0
        assert agent._small_batch_actor._statistics() is None  # a changed clip is seen
        assert torch.equal(agent.act(observation, goal), agent.actor(observation, goal))
