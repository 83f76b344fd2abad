"""Batched TorchRL env: one ``EnvBase`` that steps N simulations of a KUKA task per call."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from dm_control.rl import control
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from envs import kuka, suite, task_seeds
from envs.geometry import geometry
from envs.reward import reward


class KukaEnv(EnvBase):
    """``num_envs`` simulations of one KUKA task behind a single TorchRL env (``batch_size=[num_envs]``).

    Every ``step`` applies one action per simulation, advances all of them by one control step
    (0.05 s) and returns one TensorDict; the policy therefore runs once per step for all of them.
    Keys (float32 unless noted): ``observation`` ``[N, obs_dim]`` (25 with an object, 10 in reach),
    ``achieved_goal`` ``[N, 3]``, ``desired_goal`` ``[N, 3]``, ``is_success`` ``[N, 1]`` bool,
    ``action`` ``[N, A]`` in [-1, 1] (A = 3 or 4) and, after a step, ``reward`` ``[N, 1]`` (eq. 23,
    :func:`envs.reward` of the next achieved goal and the desired goal) and bool ``done`` /
    ``terminated`` / ``truncated`` ``[N, 1]``. Episodes only time out: ``truncated`` (and ``done``)
    turn True at the task's episode length T; ``terminated`` is always False.

    ``reset`` reads from its input TensorDict, per env: ``desired_goal`` ``[N, 3]`` (used instead of
    a sampled goal) and, for tasks with an object, ``object_position`` ``[N, 3]`` (the object is
    placed at rest at its x, y; z is the table's resting height). Both are declared in
    ``state_spec``, so wrappers such as ``TransformedEnv`` pass them through; a reset returns the
    object's start as ``object_position``, which a rollout carries along. ``_reset`` ``[N, 1]`` bool resets
    only the marked envs; the others keep their state.

    Args:
        name: one of :data:`envs.TASKS`.
        num_envs: number of simulations N, >= 1.
        seed: seed for the tasks' random states (see :func:`envs.task_seeds`).
        **options: ``threshold`` (success distance in metres, default 0.05) and ``start``
            (``"original"``, the authors' start state, or ``"above"`` for the pick tasks' start
            before December 2026; see :func:`envs.geometry.with_start`).

    >>> import torch
    >>> env = KukaEnv("reach", num_envs=2, seed=0)
    >>> td = env.reset()
    >>> td = env.rand_step(td)
    >>> td["next", "reward"].shape
    torch.Size([2, 1])
    """

    def __init__(self, name: str, num_envs: int = 1, seed: int | None = None, **options):
        geometry(name)  # a clear error listing the tasks for an unknown name
        if not isinstance(num_envs, int) or isinstance(num_envs, bool) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        suite.check_options(options)
        super().__init__(batch_size=torch.Size([num_envs]), device="cpu")
        self.task_name = name
        self.num_envs = num_envs
        dm_envs = [suite.SUITE[name](**options) for _ in range(num_envs)]
        self._physics = [env.physics for env in dm_envs]
        self._tasks = [env.task for env in dm_envs]
        self.geometry = self._tasks[0].geometry  # with the start the options chose
        self._n_sub_steps = control.compute_n_steps(dm_envs[0].control_timestep(), dm_envs[0].physics.timestep())
        task = self._tasks[0]
        self.threshold = task.threshold
        self.obs_dim, self.action_dim, self.has_object = task.obs_dim, task.action_dim, task.has_object
        self._steps = np.zeros(num_envs, dtype=np.int64)
        self._observation = np.zeros((num_envs, self.obs_dim), np.float32)
        self._achieved = np.zeros((num_envs, 3), np.float32)
        self._goal = np.zeros((num_envs, 3), np.float32)
        self._make_specs()
        self._set_seed(seed)

    def _make_specs(self) -> None:
        n = self.num_envs
        flag = lambda: Categorical(2, shape=(n, 1), dtype=torch.bool)  # noqa: E731
        self.observation_spec = Composite(
            observation=Unbounded((n, self.obs_dim), dtype=torch.float32),
            achieved_goal=Unbounded((n, 3), dtype=torch.float32),
            desired_goal=Unbounded((n, 3), dtype=torch.float32),
            is_success=flag(),
            shape=(n,),
        )
        self.action_spec = Bounded(-1.0, 1.0, shape=(n, self.action_dim), dtype=torch.float32)
        self.reward_spec = Bounded(-1.0, 0.0, shape=(n, 1), dtype=torch.float32)
        self.done_spec = Composite(done=flag(), terminated=flag(), truncated=flag(), shape=(n,))
        # Inputs a reset reads (per-env goals and object positions, as HGG hands them over): declared
        # as state, so that TorchRL passes them through wrappers (TransformedEnv keeps only declared keys).
        state = {"desired_goal": Unbounded((n, 3), dtype=torch.float32)}
        if self.has_object:
            state["object_position"] = Unbounded((n, 3), dtype=torch.float32)
        self.state_spec = Composite(state, shape=(n,))

    def _set_seed(self, seed: int | None) -> None:
        for task, task_seed in zip(self._tasks, task_seeds(seed, self.num_envs), strict=True):
            task.random.seed(task_seed)  # in place: the same stream as RandomState(task_seed)

    # -- reset ------------------------------------------------------------------------------------

    def _reset_input(self, tensordict: TensorDictBase | None, key: str) -> np.ndarray | None:
        """The per-env ``[N, 3]`` array under ``key`` of the reset input, validated, or ``None``."""
        if tensordict is None or key not in tensordict.keys():
            return None
        if key == "object_position" and not self.has_object:
            raise ValueError(f"object_position was given at reset, but task {self.task_name!r} has no object")
        value = torch.as_tensor(tensordict.get(key))
        expected = (self.num_envs, 3)
        if tuple(value.shape) != expected:
            raise ValueError(f"{key} at reset must have shape {list(expected)}, got {list(value.shape)}")
        value = value.detach().cpu().to(torch.float64).numpy()
        if not np.isfinite(value).all():
            raise ValueError(f"{key} at reset must be finite, got non-finite values in rows "
                             f"{np.flatnonzero(~np.isfinite(value).all(-1)).tolist()}")
        return value

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        goals = self._reset_input(tensordict, "desired_goal")
        positions = self._reset_input(tensordict, "object_position")
        mask = None if tensordict is None else tensordict.get("_reset", None)
        indices = range(self.num_envs) if mask is None else np.flatnonzero(mask.reshape(self.num_envs).cpu().numpy())
        for i in indices:
            physics, task = self._physics[i], self._tasks[i]
            with physics.reset_context():
                task.initialize_episode(physics)
                if goals is not None:
                    task.set_goal(physics, goals[i])
                if positions is not None:
                    task.set_object_position(physics, positions[i])
            self._goal[i] = physics.target_position()
            task.observe_into(physics, self._observation[i], self._achieved[i])
            self._steps[i] = 0
        out = self._output(self._truncated())
        if self.has_object:  # the state a reset can be given (see _make_specs), as the reset set it
            out["object_position"] = out["achieved_goal"].clone()
        return out

    # -- step -------------------------------------------------------------------------------------

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        self._advance(tensordict.get("action"))
        return self._output(self._truncated(), with_reward=True)

    def _advance(self, action: torch.Tensor) -> None:
        """One control step of every simulation under ``action`` ``[N, A]``; the observations and
        achieved goals are then in ``self._observation`` and ``self._achieved``."""
        if action.shape != (self.num_envs, self.action_dim):
            raise ValueError(f"action must have shape [{self.num_envs}, {self.action_dim}] "
                             f"(num_envs, action size of {self.task_name!r}), got {list(action.shape)}")
        actions = action.detach().cpu().numpy().astype(np.float64)
        for i, (physics, task) in enumerate(zip(self._physics, self._tasks, strict=True)):
            task.before_step(actions[i], physics)
            physics.step(self._n_sub_steps)
            task.observe_into(physics, self._observation[i], self._achieved[i])
        np.add(self._steps, 1, out=self._steps)  # in place: assigning an attribute of an EnvBase is slow

    def _truncated(self) -> torch.Tensor:
        """``[N, 1]`` bool: the episode has reached the task's length T."""
        return torch.from_numpy(self._at_length()).unsqueeze(-1)

    def _at_length(self, out: np.ndarray | None = None) -> np.ndarray:
        """``[N]`` bool (into ``out`` if given): the episode has reached the task's length T."""
        return np.greater_equal(self._steps, self.geometry.episode_length, out=out)

    # -- the speed device beside the TorchRL loop ---------------------------------------------------

    def rollout_with(self, act: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], steps: int,
                     start: TensorDictBase) -> TensorDict:
        """``steps`` steps of every simulation under a plain-tensor policy, without a TensorDict per step.

        Returns, value for value, what ``self.rollout(steps, policy, tensordict=start, auto_reset=False,
        break_when_any_done=False)`` returns for the policy that writes ``action = act(observation,
        desired_goal)``: ``[N, steps]``, time last, with the ``next`` entries, and ``start``'s other
        keys (e.g. ``object_position``) carried along (``tests/test_envs.py`` checks the equality).
        The per-episode loop (``train.chunks = train.episodes``) steps a one-simulation env 5,000 times
        an iteration; there ``env.rollout`` runs at about half the steps per second of raw dm_control
        and this method at 1.5–2× ``env.rollout`` (``python benchmarks/env_throughput.py`` prints all three).

        Args:
            act: ``act(observation [N, obs_dim], goal [N, 3]) -> action [N, A]``, once per step.
            steps: number of steps.
            start: the TensorDict ``reset`` returned (the state the simulations are in).
        """
        n, shape = self.num_envs, (steps + 1, self.num_envs)  # time first while stepping: contiguous rows
        observation = torch.empty(*shape, self.obs_dim)
        achieved, goal = torch.empty(*shape, 3), torch.empty(*shape, 3)
        truncated = torch.empty(*shape, 1, dtype=torch.bool)
        actions = []
        observation[0], achieved[0] = start.get("observation"), start.get("achieved_goal")
        goal[0], truncated[0] = start.get("desired_goal"), start.get("truncated")
        goal[1:] = torch.from_numpy(self._goal)  # set at reset, fixed while stepping
        # each step's results copied by numpy into the tensors' memory: a fraction of a tensor copy's cost
        observation_rows, achieved_rows, truncated_rows = observation.numpy(), achieved.numpy(), truncated.numpy()
        for t in range(steps):
            action = act(observation[t], goal[t])
            self._advance(action)
            actions.append(action)
            observation_rows[t + 1] = self._observation
            achieved_rows[t + 1] = self._achieved
            self._at_length(out=truncated_rows[t + 1, :, 0])
        rewards = reward(achieved[1:], goal[1:], self.threshold).unsqueeze(-1)

        def batch_first(x: torch.Tensor) -> torch.Tensor:  # [steps, N, ...] -> [N, steps, ...]
            return x.transpose(0, 1).contiguous()

        success = rewards == 0.0
        after = {
            "observation": observation[1:], "achieved_goal": achieved[1:], "desired_goal": goal[1:],
            "is_success": success, "reward": rewards, "done": truncated[1:],
            "terminated": torch.zeros_like(truncated[1:]), "truncated": truncated[1:],
        }  # fmt: skip
        before = {
            "observation": observation[:-1], "achieved_goal": achieved[:-1], "desired_goal": goal[:-1],
            "is_success": torch.cat([start.get("is_success").unsqueeze(0), success[:-1]]),
            "done": torch.cat([start.get("done").unsqueeze(0), truncated[1:-1]]),
            "terminated": torch.cat([start.get("terminated").unsqueeze(0), after["terminated"][:-1]]),
            "truncated": truncated[:-1], "action": torch.stack(actions),
        }  # fmt: skip
        out = TensorDict({k: batch_first(v) for k, v in before.items()}, [n, steps], device=self.device)
        out["next"] = TensorDict({k: batch_first(v) for k, v in after.items()}, [n, steps], device=self.device)
        for key, value in start.items():  # state carried along unchanged (the object's start)
            if key not in out.keys():
                out[key] = value.unsqueeze(1).expand(n, steps, *value.shape[1:]).clone()
        return out

    def _output(self, truncated: torch.Tensor, with_reward: bool = False) -> TensorDict:
        achieved = torch.from_numpy(self._achieved.copy())
        goal = torch.from_numpy(self._goal.copy())
        rewards = reward(achieved, goal, self.threshold).unsqueeze(-1)
        out = {
            "observation": torch.from_numpy(self._observation.copy()),
            "achieved_goal": achieved,
            "desired_goal": goal,
            "is_success": rewards == 0.0,
            "done": truncated,
            "terminated": torch.zeros_like(truncated),
            "truncated": truncated.clone(),
        }
        if with_reward:
            out["reward"] = rewards
        return TensorDict(out, batch_size=self.batch_size)

    # -- access to the simulations -------------------------------------------------------------------

    def random_state(self) -> list[tuple]:
        """The N tasks' random states (goal and object draws), for checkpoints."""
        return [task.random.get_state() for task in self._tasks]

    def set_random_state(self, states: list[tuple]) -> None:
        """Restore :meth:`random_state`'s output, so the next resets draw what they would have drawn."""
        if len(states) != self.num_envs:
            raise ValueError(f"random state holds {len(states)} tasks' states, this env has num_envs={self.num_envs}")
        for task, state in zip(self._tasks, states, strict=True):
            task.random.set_state(state)

    @property
    def physics(self) -> list[kuka.Physics]:
        """The N dm_control ``Physics`` objects (e.g. ``env.physics[0].render(camera_id="front")``)."""
        return list(self._physics)
