"""Tests of the KUKA task suite: dm_control tasks, the batched TorchRL env, reward and geometry."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

import envs
from envs import kuka, scripted, task_seeds

TASKS = envs.TASKS
OBJECT_TASKS = [name for name in TASKS if envs.geometry(name).object_range is not None]


def _random_actions(env, steps: int, seed: int = 0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return torch.rand(steps, env.num_envs, env.action_dim, generator=generator) * 2 - 1


def _rollout(env, actions: torch.Tensor, reset_td=None) -> list[TensorDict]:
    td = env.reset(reset_td)
    steps = []
    for action in actions:
        td = env.step(td.set("action", action))
        steps.append(td.clone())
        td = td["next"]
    return steps


def _inside(points: torch.Tensor, box: envs.Box, tol: float = 1e-6) -> torch.Tensor:
    low, high = torch.tensor(box.low), torch.tensor(box.high)
    return ((points >= low - tol) & (points <= high + tol)).all(-1)


# -- reward ---------------------------------------------------------------------------------------


def test_reward_is_zero_within_threshold_and_minus_one_outside():
    goal = torch.zeros(3)
    achieved = torch.tensor([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [0.0, 0.0501, 0.0], [1.0, 1.0, 1.0]])
    r = envs.reward(achieved, goal)
    assert r.dtype == torch.float32
    assert r.tolist() == [0.0, 0.0, -1.0, -1.0]
    assert envs.reward(achieved, goal, threshold=2.0).tolist() == [0.0, 0.0, 0.0, 0.0]
    # Broadcasting over leading dimensions, and the same values on numpy input.
    batch = achieved.expand(2, 4, 3)
    assert envs.reward(batch, goal).shape == (2, 4)
    np.testing.assert_array_equal(envs.reward(achieved.numpy(), goal.numpy()), r.numpy())


# -- construction and bad input -------------------------------------------------------------------


def test_unknown_task_names_the_valid_ones():
    for factory in (envs.load, envs.make):
        with pytest.raises(ValueError, match="pick_obstacle") as info:
            factory("push")
        assert all(name in str(info.value) for name in TASKS)


def test_unknown_option_and_bad_threshold_are_errors():
    with pytest.raises(TypeError, match="threshold"):
        envs.make("reach", treshold=0.1)
    with pytest.raises(ValueError, match="threshold"):
        envs.load("reach", threshold=-1.0)
    with pytest.raises(ValueError, match="num_envs"):
        envs.make("reach", num_envs=0)


@pytest.mark.parametrize("name", TASKS)
def test_wrong_action_shape_is_an_error(name):
    env = envs.make(name, num_envs=2, seed=0)
    td = env.reset()
    with pytest.raises(ValueError, match=rf"action must have shape \[2, {env.action_dim}\]"):
        env.step(td.set("action", torch.zeros(2, env.action_dim + 1)))
    dm_env = envs.load(name, seed=0)
    dm_env.reset()
    with pytest.raises(ValueError, match="action must have shape"):
        dm_env.step(np.zeros(env.action_dim + 1))


@pytest.mark.parametrize("name", TASKS)
def test_bad_reset_inputs_name_the_key_and_shape(name):
    env = envs.make(name, num_envs=3, seed=0)
    keys = ["desired_goal"] + (["object_position"] if env.has_object else [])
    for key in keys:
        with pytest.raises(ValueError, match=rf"{key} at reset must have shape \[3, 3\]"):
            env.reset(TensorDict({key: torch.zeros(3, 2)}, [3]))
        bad = torch.full((3, 3), 0.8)
        bad[1, 2] = float("nan")
        with pytest.raises(ValueError, match=rf"{key} at reset must be finite.*\[1\]"):
            env.reset(TensorDict({key: bad}, [3]))
    if not env.has_object:
        with pytest.raises(ValueError, match="has no object"):
            env.reset(TensorDict({"object_position": torch.zeros(3, 3)}, [3]))


# -- specs, determinism, randomisation ------------------------------------------------------------


@pytest.mark.parametrize("num_envs", [1, 8])
@pytest.mark.parametrize("name", TASKS)
def test_check_env_specs(name, num_envs):
    check_env_specs(envs.make(name, num_envs=num_envs, seed=0))


@pytest.mark.parametrize("name", TASKS)
def test_observations_match_specs(name):
    env = envs.make(name, num_envs=4, seed=1)
    geom = envs.geometry(name)
    assert env.obs_dim == (25 if geom.object_range is not None else 10)
    assert env.action_dim == geom.action_dim
    layout = envs.observation_layout(name)
    td = env.reset()
    moved = False
    for action in [None, *_random_actions(env, 5)]:
        if action is not None:
            before = td["observation"][:, layout["grip_position"]].clone()
            td = env.step(td.set("action", action))["next"]
            moved |= bool((td["observation"][:, layout["grip_position"]] - before).abs().max() > 1e-3)
        for key, spec in env.observation_spec.items():
            assert td[key].dtype == spec.dtype and td[key].shape == spec.shape, key
        # each named part of the observation is the physics' own read-out of it (float32 rounding apart)
        for i, physics in enumerate(env.physics):
            observation = td["observation"][i].double().numpy()
            grip = physics.grip_position()
            parts = {"grip_position": grip, "finger_positions": physics.finger_positions(),
                     "grip_velocity": physics.grip_velocity() * kuka.CONTROL_TIMESTEP,
                     "finger_velocities": physics.finger_velocities() * kuka.CONTROL_TIMESTEP}
            if env.has_object:
                parts |= {"object_position": physics.object_position(),
                          "object_relative": physics.object_position() - grip}
            for part, value in parts.items():
                np.testing.assert_allclose(observation[layout[part]], value, atol=1e-6, err_msg=part)
            achieved = physics.object_position() if env.has_object else grip
            np.testing.assert_allclose(td["achieved_goal"][i].double().numpy(), achieved, atol=1e-6)
            np.testing.assert_allclose(td["desired_goal"][i].double().numpy(), physics.target_position(), atol=1e-6)
    assert moved  # the grip moved, so a part read from the wrong place or time would be told apart
    dm_env = envs.load(name, seed=1)
    observation = dm_env.reset().observation
    assert observation["observation"].shape == (env.obs_dim,)
    assert list(observation) == ["observation", "achieved_goal", "desired_goal", "is_success"]


@pytest.mark.parametrize("name", TASKS)
def test_same_seed_and_actions_give_the_same_trajectory(name):
    actions = _random_actions(envs.make(name, num_envs=2), 30, seed=5)
    first = _rollout(envs.make(name, num_envs=2, seed=3), actions)
    second = _rollout(envs.make(name, num_envs=2, seed=3), actions)
    for a, b in zip(first, second, strict=True):
        assert (a == b).all()
    other = envs.make(name, num_envs=2, seed=4).reset()
    assert not torch.equal(other["desired_goal"], first[0]["desired_goal"])


@pytest.mark.parametrize("name", TASKS)
def test_torchrl_env_reproduces_the_dm_control_env(name):
    env = envs.make(name, num_envs=2, seed=7)
    actions = _random_actions(env, 10, seed=1)
    steps = _rollout(env, actions)
    dm_env = envs.load(name, seed=task_seeds(7, 2)[1])
    time_step = dm_env.reset()
    np.testing.assert_allclose(time_step.observation["desired_goal"], steps[0]["desired_goal"][1], atol=1e-6)
    for action, step in zip(actions, steps, strict=True):
        time_step = dm_env.step(action[1].double().numpy())
        np.testing.assert_allclose(time_step.observation["observation"], step["next", "observation"][1], atol=1e-5)
        assert time_step.reward == step["next", "reward"][1].item()


@pytest.mark.parametrize("name", TASKS)
def test_initial_states_and_goals_are_random_and_inside_the_ranges(name):
    geom = envs.geometry(name)
    td = envs.make(name, num_envs=32, seed=11).reset()
    goals = td["desired_goal"]
    assert _inside(goals, geom.target_range).all()
    varying = torch.tensor(geom.target_range.half) > 0
    assert (goals.std(0)[varying] > 0.2 * torch.tensor(geom.target_range.half)[varying]).all()
    assert (goals.std(0)[~varying] == 0).all()
    start = torch.tensor(geom.gripper_start, dtype=torch.float32)
    torch.testing.assert_close(td["observation"][:, :3], start.expand(32, 3), atol=1e-4, rtol=0)
    if geom.object_range is None:
        torch.testing.assert_close(td["achieved_goal"], start.expand(32, 3), atol=1e-4, rtol=0)
    else:
        objects = td["achieved_goal"]
        assert _inside(objects, geom.object_range, tol=2e-3).all()
        assert objects[:, :2].std(0).min() > 0.2 * max(geom.object_range.half[:2]) or max(geom.object_range.half) == 0
    assert not td["is_success"].all()


# -- reward, success and goals in the env ---------------------------------------------------------


@pytest.mark.parametrize("name", TASKS)
def test_step_reward_is_the_reward_function_and_agrees_with_success(name):
    env = envs.make(name, num_envs=6, seed=2, threshold=0.05)
    rollout = env.rollout(env.geometry.episode_length, scripted.policy(name), break_when_any_done=False)
    achieved, goal = rollout["next", "achieved_goal"], rollout["desired_goal"]
    expected = envs.reward(achieved, goal, 0.05).unsqueeze(-1)
    assert torch.equal(rollout["next", "reward"], expected)
    assert torch.equal(rollout["next", "is_success"], expected == 0)
    assert torch.equal(rollout["next", "desired_goal"], goal)
    # The scripted controller makes the check meaningful: both rewards occur.
    assert (expected == 0).any() and (expected == -1).any()


@pytest.mark.parametrize("name", TASKS)
def test_goal_and_object_position_given_at_reset_are_used(name):
    geom = envs.geometry(name)
    env = envs.make(name, num_envs=3, seed=0)
    goals = torch.tensor([[0.7, 0.1, 1.1], [0.8, -0.1, 1.2], [0.6, 0.0, 1.3]])
    given = {"desired_goal": goals}
    if env.has_object:
        given["object_position"] = torch.tensor([[0.72, 0.22, 5.0], [0.8, 0.15, 5.0], [0.7, 0.3, 5.0]])
    td = env.reset(TensorDict(given, [3]))
    assert torch.equal(td["desired_goal"], goals)
    for i, physics in enumerate(env.physics):
        np.testing.assert_allclose(physics.target_position(), goals[i], atol=1e-6)
    if env.has_object:
        rest = geom.object_range.center[2]
        expected = torch.cat([given["object_position"][:, :2], torch.full((3, 1), rest)], -1)
        torch.testing.assert_close(td["achieved_goal"], expected, atol=1e-6, rtol=0)
    # The goal is kept for the whole episode and rewards are measured against it.
    step = _rollout(env, _random_actions(env, 3), TensorDict(given, [3]))[-1]
    assert torch.equal(step["next", "desired_goal"], goals)
    # A goal at the (given) start of the achieved goal is a success from the start.
    td = env.reset(TensorDict({**given, "desired_goal": td["achieved_goal"]}, [3]))
    assert td["is_success"].all()


@pytest.mark.parametrize("name", TASKS)
def test_threshold_option_sets_the_success_distance(name):
    strict = envs.make(name, num_envs=4, seed=0, threshold=0.05).reset()
    loose = envs.make(name, num_envs=4, seed=0, threshold=10.0).reset()
    assert loose["is_success"].all() and not strict["is_success"].all()


# -- episodes and partial resets ------------------------------------------------------------------


@pytest.mark.parametrize("name", TASKS)
def test_episodes_are_truncated_at_their_length(name):
    env = envs.make(name, num_envs=2, seed=0)
    length = env.geometry.episode_length
    rollout = env.rollout(length + 3, break_when_any_done=False)
    truncated = rollout["next", "truncated"][..., 0]
    expected = torch.zeros(length + 3, dtype=torch.bool)
    expected[length - 1] = True
    assert torch.equal(truncated, expected.expand(2, -1))
    assert torch.equal(rollout["next", "done"], rollout["next", "truncated"])
    assert not rollout["next", "terminated"].any()
    dm_env = envs.load(name, seed=0)
    dm_env.reset()
    last = [dm_env.step(np.zeros(env.action_dim)).last() for _ in range(length)]
    assert last == [False] * (length - 1) + [True]


@pytest.mark.parametrize("name", TASKS)
@pytest.mark.parametrize("num_envs", [1, 3])
def test_rollout_with_a_tensor_policy_equals_the_torchrl_rollout(name, num_envs):
    """The speed device: ``rollout_with`` returns env.rollout's TensorDict, value for value, and
    leaves the simulations where env.rollout leaves them."""
    noisy = lambda seed: torch.Generator().manual_seed(seed)  # noqa: E731

    def act_with(generator):  # a stateful policy: the same draws in the same order on both paths
        def act(observation, goal):
            scale = (observation[:, :1] - goal[:, :1]).tanh()
            return (torch.rand(len(observation), envs.make(name).action_dim, generator=generator) * 2 - 1) * scale
        return act

    def as_policy(act):  # env.rollout's policy: a function of one argument named td (TorchRL reads the signature)
        return lambda td: td.set("action", act(td["observation"], td["desired_goal"]))

    runs = []
    for fast in (False, True):
        env = envs.make(name, num_envs=num_envs, seed=4)
        goal = env.reset()["desired_goal"] + 0.01  # a reset given goals, as the trainer resets
        start = env.reset(TensorDict({"desired_goal": goal}, batch_size=[num_envs]))
        act, steps = act_with(noisy(7)), env.geometry.episode_length
        if fast:
            rollout = env.rollout_with(act, steps, start.clone())
        else:
            rollout = env.rollout(steps, as_policy(act), tensordict=start.clone(), auto_reset=False,
                                  break_when_any_done=False)
        after = env.step(TensorDict({"action": torch.zeros(num_envs, env.action_dim)}, [num_envs]))["next"]
        runs.append((rollout, after))
    (slow, slow_after), (fast, fast_after) = runs
    assert fast.batch_size == slow.batch_size == torch.Size([num_envs, envs.geometry(name).episode_length])
    assert set(fast.keys(True, True)) == set(slow.keys(True, True))
    for key in slow.keys(True, True):
        assert fast[key].dtype == slow[key].dtype, key
        assert torch.equal(fast[key], slow[key]), key
    assert fast["next", "truncated"][:, -1].all() and not fast["next", "truncated"][:, :-1].any()
    for key in slow_after.keys(True, True):
        assert torch.equal(fast_after[key], slow_after[key]), key


@pytest.mark.parametrize("name", TASKS)
def test_partial_reset_resets_only_the_marked_envs(name):
    env = envs.make(name, num_envs=3, seed=0)
    td = env.reset()
    for action in _random_actions(env, 4):
        td = env.step(td.set("action", action))["next"]
    before = td.clone()
    # As in a collector, the current TensorDict goes in with the mask; unmarked envs keep their entries.
    reset = env.reset(td.set("_reset", torch.tensor([[False], [True], [False]])))
    kept = torch.tensor([True, False, True])
    assert torch.equal(reset["observation"][kept], before["observation"][kept])
    start = torch.tensor(env.geometry.gripper_start)
    torch.testing.assert_close(reset["observation"][1, :3], start, atol=1e-4, rtol=0)
    assert not torch.allclose(before["observation"][1, :3], start, atol=1e-3)


# -- physics --------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", TASKS)
def test_long_random_rollouts_have_no_nan_and_no_mujoco_warning(name):
    env = envs.make(name, num_envs=20, seed=0)
    generator = torch.Generator().manual_seed(0)
    policy = lambda td: td.set("action", torch.rand(20, env.action_dim, generator=generator) * 2 - 1)  # noqa: E731
    rollout = env.rollout(100, policy, break_when_any_done=False)  # 2,000 random steps
    for key in ("observation", "achieved_goal", "reward"):
        assert torch.isfinite(rollout["next", key]).all(), key
    for physics in env.physics:
        assert not physics.data.warning.number.any(), physics.data.warning.number
    # Nothing is flung away: the grip stays in its workspace, the cube on the table or the floor nearby.
    grip = rollout["next", "observation"][..., :3]
    low, high = kuka.workspace(env.geometry)
    assert ((grip > torch.tensor(low) - 0.03) & (grip < torch.tensor(high) + 0.03)).all()
    if env.has_object:
        assert (rollout["next", "achieved_goal"].abs() < 2.0).all()


@pytest.mark.parametrize("name", TASKS)
def test_model_matches_the_task_geometry(name):
    geom = envs.geometry(name)
    physics = envs.load(name).physics
    names = [physics.model.geom(i).name for i in range(physics.model.ngeom)]
    if geom.table_height is not None:
        table = physics.named.model
        top = table.geom_pos["table", 2] + table.geom_size["table", 2]
        assert top == pytest.approx(geom.table_height)
    walls = [n for n in names if n.startswith("wall")]
    assert len(walls) == len(geom.obstacles)
    for wall, box in zip(walls, geom.obstacles, strict=True):
        np.testing.assert_allclose(physics.named.model.geom_pos[wall], box.center)
        np.testing.assert_allclose(physics.named.model.geom_size[wall], box.half)


@pytest.mark.parametrize("name", TASKS)
def test_start_pose_puts_the_grip_at_its_start_pointing_down(name):
    env = envs.load(name, seed=0)
    env.reset()
    physics = env.physics
    np.testing.assert_allclose(physics.grip_position(), envs.geometry(name).gripper_start, atol=1e-6)
    hand_z = physics.named.data.xmat["hand"].reshape(3, 3)[:, 2]
    np.testing.assert_allclose(hand_z, [0, 0, -1], atol=1e-6)
    limits = physics.model.jnt_range[:7]
    qpos = physics.data.qpos[:7]
    assert ((qpos > limits[:, 0] + 0.2) & (qpos < limits[:, 1] - 0.2)).all()


# The authors' tips (REFERENCE.md, "Start states of the original tasks") and finger openings.
ORIGINAL_STARTS = {
    "push_new": ((0.674, 0.160, 0.974), 0.0),
    "pick_no_obstacle": ((0.745, 0.203, 1.019), 0.026),
    "pick_obstacle": ((0.748, 0.204, 1.041), 0.0),
}


@pytest.mark.parametrize("name", sorted(ORIGINAL_STARTS))
def test_tasks_start_at_the_authors_tip_with_their_finger_opening(name):
    tip, fingers = ORIGINAL_STARTS[name]
    env = envs.make(name, num_envs=2, seed=0)
    env.reset()
    for physics in env.physics:
        np.testing.assert_allclose(physics.grip_position(), tip, atol=1e-6)
        np.testing.assert_allclose(physics.finger_positions(), [fingers, fingers], atol=1e-9)


def test_the_pick_tasks_keep_their_former_start_as_an_option():
    env = envs.load("pick_obstacle", seed=0, start="above")
    env.reset()
    np.testing.assert_allclose(env.physics.grip_position(), (0.75, 0.1, 1.2), atol=1e-6)
    assert envs.make("pick_no_obstacle", num_envs=1, seed=0, start="above").geometry.finger_start == 0.0
    with pytest.raises(ValueError, match="'above' exists for the pick tasks"):
        envs.load("push_new", start="above")
    with pytest.raises(ValueError, match="start='low'"):
        envs.make("pick_obstacle", start="low")


def test_a_grasped_cube_stays_in_the_gripper_at_full_speed():
    # from above the cube (start="above"): no start with a finger in the cube's place, so every env grasps
    env = envs.make("pick_no_obstacle", num_envs=8, seed=1, start="above")
    td = env.reset()
    policy = scripted.policy("pick_no_obstacle")
    for _ in range(30):  # grasp, lift to 1.25 m
        goal = td["achieved_goal"].clone()
        goal[:, 2] = 1.25
        td = env.step(policy(td.set("desired_goal", goal)))["next"]
    assert (td["achieved_goal"][:, 2] > 1.2).all()
    generator = torch.Generator().manual_seed(0)
    offsets = []
    for t in range(60):  # full speed (|a| = 1 on every axis), a new direction every 10 steps
        if t % 10 == 0:
            direction = torch.randint(0, 2, (8, 3), generator=generator).float() * 2 - 1
        up = td["observation"][:, 2] < 1.12
        direction[:, 2] = torch.where(up, 1.0, direction[:, 2])
        action = torch.cat([direction, -torch.ones(8, 1)], -1)
        td = env.step(td.set("action", action))["next"]
        offsets.append(td["observation"][:, 6:9].norm(dim=-1))
    assert torch.stack(offsets).max() < 0.02


# -- scripted controllers -------------------------------------------------------------------------


@pytest.mark.parametrize("name", TASKS)
def test_scripted_controller_solves_the_task(name):
    # 20 episodes here; `python -m envs.scripted --episodes 100` gives the 100-episode figure.
    assert scripted.success_rate(name, episodes=20, num_envs=20, seed=123) >= 0.9


def test_kuka_task_rejects_a_non_finite_action():
    env = envs.load("reach", seed=0)
    env.reset()
    with pytest.raises(ValueError, match="finite"):
        env.step(np.array([np.nan, 0.0, 0.0]))
    assert isinstance(env.physics, kuka.Physics)


@pytest.mark.parametrize("name", envs.TASKS)
def test_named_observation_slices_match_the_physics_read_outs(name):
    env = envs.make(name, num_envs=2, seed=3)
    td = env.reset()
    for _ in range(5):  # moving, so that velocities are not zero
        td = env.rand_step(td)["next"]
    physics, observation = env.physics[1], td["observation"][1].double().numpy()
    layout = envs.observation_layout(name)
    assert sorted(s.start for s in layout.values()) == [s.start for s in sorted(layout.values(), key=lambda s: s.start)]
    assert sum(s.stop - s.start for s in layout.values()) == env.obs_dim  # the slices tile the vector
    dt = kuka.CONTROL_TIMESTEP
    expected = {
        "grip_position": physics.grip_position(),
        "finger_positions": physics.finger_positions(),
        "grip_velocity": physics.grip_velocity() * dt,
        "finger_velocities": physics.finger_velocities() * dt,
    }
    if env.has_object:
        linear, angular = physics.object_velocity()
        expected.update(
            object_position=physics.object_position(),
            object_relative=physics.object_position() - physics.grip_position(),
            object_velocity=linear * dt - physics.grip_velocity() * dt,
            object_angular_velocity=angular * dt,
        )
    assert set(expected) <= set(layout)
    for part, value in expected.items():
        np.testing.assert_allclose(observation[layout[part]], value, atol=1e-5, err_msg=part)
    np.testing.assert_allclose(td["achieved_goal"][1].numpy(),
                               expected.get("object_position", expected["grip_position"]), atol=1e-5)
