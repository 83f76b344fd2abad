"""gchgg's HER transform and curriculum sampler in a plain TorchRL pipeline on a 2-D point maze (no gchgg env).

A point in the 2 m × 2 m square ``[-1, 1]²`` moves ``0.1 · action`` per step; a wall from x = -1 to
0.4 along y = 0 blocks it. Each episode starts at a random free point with a random free goal and
lasts ``MAX_STEPS`` steps (truncated, never terminated); reward −1 until the point is within 0.1 m of
the goal, 0 there. Everything but the two gchgg parts is TorchRL's own: an ``EnvBase``, its
``Collector``, ``split_trajectories`` (the collector's batches cut episodes: padded fragments with a
mask), ``DDPGLoss`` with ``SoftUpdate``, and a ``TensorDictReplayBuffer``. gchgg adds:

* :class:`~gchgg.transforms.HindsightRelabel` on the padded fragments (it reads their mask);
* :class:`~gchgg.samplers.GraphCurriculumSampler` with a user metric (:class:`WallDetour`, the
  straight line, or the detour around the wall's free end where the line crosses it) and a
  :class:`~gchgg.samplers.FixedTradeoff`, since there is no goal generator here.

Run ``python examples/reuse_point_maze.py`` (``--frames`` to change the budget); it prints the
success rate of the greedy policy on 64 fresh episodes. ``tests/test_reuse.py`` runs it briefly
and checks it learns.
"""

from __future__ import annotations

import argparse
import time

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.collectors.utils import split_trajectories
from torchrl.data import Bounded, Composite, LazyTensorStorage, TensorDictReplayBuffer, Unbounded
from torchrl.envs import EnvBase
from torchrl.objectives import DDPGLoss, SoftUpdate, ValueEstimators

from gchgg.samplers import FixedTradeoff, GraphCurriculumSampler
from gchgg.transforms import GoalToNext, HindsightRelabel

FIELD = 1.0  # metres: the square is [-FIELD, FIELD]²
WALL_LOW, WALL_HIGH = torch.tensor([-1.0, -0.05]), torch.tensor([0.4, 0.05])  # metres: the wall's corners
WALL_END = torch.tensor([0.5, 0.0])  # metres: a point past the wall's free end, where detours turn
STEP = 0.1  # metres moved per unit action per step
SUCCESS = 0.1  # metres: the goal is reached within this distance
MAX_STEPS = 25  # steps per episode


def reward(achieved_goal: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
    """−1 until within ``SUCCESS`` of the goal, 0 there (the sparse reward HER recomputes), ``[...]``."""
    return torch.where(torch.linalg.vector_norm(achieved_goal - goal, dim=-1) > SUCCESS, -1.0, 0.0)


def in_wall(points: torch.Tensor) -> torch.Tensor:
    return ((points >= WALL_LOW) & (points <= WALL_HIGH)).all(-1)


class WallDetour:
    """A user metric: the straight line, or, where it crosses the wall's line left of its free end, the
    detour through ``WALL_END``. Never shorter than the straight line, so the sampler's shortlist stays exact."""

    lattice = None  # works on goals directly

    def distance(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        a, b = torch.broadcast_tensors(torch.as_tensor(a), torch.as_tensor(b))
        straight = torch.linalg.vector_norm(a - b, dim=-1)
        sides = a[..., 1] * b[..., 1] < 0  # on opposite sides of y = 0
        t = a[..., 1] / (a[..., 1] - b[..., 1]).where(sides, torch.ones_like(straight))
        crossing_x = a[..., 0] + t * (b[..., 0] - a[..., 0])
        blocked = sides & (crossing_x < WALL_HIGH[0])
        detour = torch.linalg.vector_norm(a - WALL_END, dim=-1) + torch.linalg.vector_norm(b - WALL_END, dim=-1)
        return torch.where(blocked, detour, straight)


class PointMaze(EnvBase):
    """``num_envs`` point masses in the maze, stepped together (batch ``[num_envs]``).

    Keys: ``observation`` (the position), ``achieved_goal`` (the position), ``desired_goal``,
    ``("next", "reward")``, ``done``/``terminated``/``truncated``.
    """

    def __init__(self, num_envs: int = 16, seed: int = 0) -> None:
        super().__init__(batch_size=torch.Size([num_envs]))
        shape = (num_envs, 2)
        self.observation_spec = Composite(
            observation=Unbounded(shape), achieved_goal=Unbounded(shape), desired_goal=Unbounded(shape),
            shape=(num_envs,),
        )
        self.action_spec = Bounded(-1.0, 1.0, shape)
        self.reward_spec = Unbounded((num_envs, 1))
        self.rng = torch.Generator().manual_seed(seed)
        self.position, self.goal = torch.zeros(shape), torch.zeros(shape)
        self.steps = torch.zeros(num_envs, dtype=torch.long)

    def _free_points(self, count: int) -> torch.Tensor:
        """``count`` points uniform in the square outside the wall (rejection, vectorised)."""
        points = torch.rand(count * 4, 2, generator=self.rng) * 2 * FIELD - FIELD
        return points[~in_wall(points)][:count]

    def _observe(self) -> TensorDict:
        return TensorDict({"observation": self.position.clone(), "achieved_goal": self.position.clone(),
                           "desired_goal": self.goal.clone()}, self.batch_size)

    def _reset(self, tensordict: TensorDictBase | None) -> TensorDictBase:
        reset = torch.ones(self.batch_size, dtype=torch.bool)
        if tensordict is not None and "_reset" in tensordict.keys():
            reset = tensordict["_reset"].reshape(self.batch_size)
        count = int(reset.sum())
        self.position[reset], self.goal[reset], self.steps[reset] = (
            self._free_points(count), self._free_points(count), 0
        )
        out = self._observe()
        out.update(self.full_done_spec.zero())
        return out

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        moved = (self.position + STEP * tensordict["action"].clamp(-1.0, 1.0)).clamp(-FIELD, FIELD)
        self.position = torch.where(in_wall(moved).unsqueeze(-1), self.position, moved)  # the wall stops it
        self.steps += 1
        out = self._observe()
        out["reward"] = reward(self.position, self.goal).unsqueeze(-1)
        out["truncated"] = (self.steps >= MAX_STEPS).unsqueeze(-1)
        out["terminated"] = torch.zeros_like(out["truncated"])
        out["done"] = out["truncated"].clone()
        return out

    def _set_seed(self, seed: int | None) -> None:
        if seed is not None:
            self.rng.manual_seed(seed)


class GoalMLP(nn.Module):
    """An MLP on the concatenated inputs; ``tanh`` on the output for the actor."""

    def __init__(self, inputs: int, outputs: int, squash: bool, hidden: int = 64) -> None:
        super().__init__()
        layers = [nn.Linear(inputs, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                  nn.Linear(hidden, outputs)]
        self.net = nn.Sequential(*layers, *([nn.Tanh()] if squash else []))

    def forward(self, *parts: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat(parts, -1))


class Explore(nn.Module):
    """The actor's action plus Gaussian noise (σ), or a uniform random action with probability ε."""

    def __init__(self, actor: nn.Module, generator: torch.Generator, sigma: float = 0.2, epsilon: float = 0.2) -> None:
        super().__init__()
        self.actor, self.generator, self.sigma, self.epsilon = actor, generator, sigma, epsilon

    def forward(self, observation: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            action = self.actor(observation, goal)
        noise = torch.randn(action.shape, generator=self.generator) * self.sigma
        uniform = torch.rand(action.shape, generator=self.generator) * 2 - 1
        random = torch.rand(action.shape[:-1] + (1,), generator=self.generator) < self.epsilon
        return torch.where(random, uniform, (action + noise).clamp(-1.0, 1.0))


def success_rate(env: PointMaze, actor: TensorDictModule, episodes: int = 64) -> float:
    """Share of ``episodes`` fresh episodes whose point ends within ``SUCCESS`` of its goal (greedy actor)."""
    successes = 0
    for _ in range(-(-episodes // env.batch_size[0])):
        with torch.no_grad():
            rollout = env.rollout(MAX_STEPS, actor, break_when_any_done=False)
        successes += int((rollout["next", "reward"][:, -1] == 0).sum())
    return successes / (-(-episodes // env.batch_size[0]) * env.batch_size[0])


def train(frames: int = 16_000, seed: int = 0, updates_per_frame: float = 0.25, verbose: bool = True) -> float:
    """Train DDPG + HER with the curriculum sampler for ``frames`` env steps; the greedy success rate."""
    torch.manual_seed(seed)  # the networks' initialisation
    num_envs = 16
    actor_net, critic_net = GoalMLP(4, 2, squash=True), GoalMLP(6, 1, squash=False)
    actor = TensorDictModule(actor_net, in_keys=["observation", "desired_goal"], out_keys=["action"])
    critic = TensorDictModule(critic_net, in_keys=["observation", "desired_goal", "action"],
                              out_keys=["state_action_value"])
    explore = TensorDictModule(Explore(actor_net, torch.Generator().manual_seed(seed + 1)),
                               in_keys=["observation", "desired_goal"], out_keys=["action"])
    loss = DDPGLoss(actor, critic, delay_actor=True, delay_value=True)
    loss.make_value_estimator(ValueEstimators.TD0, gamma=0.9)
    target_update = SoftUpdate(loss, tau=0.05)
    optim_actor = torch.optim.Adam(loss.actor_network_params.values(True, True), lr=1e-3)
    optim_critic = torch.optim.Adam(loss.value_network_params.values(True, True), lr=1e-3)

    relabel = HindsightRelabel(reward, k=4, strategy="future", generator=torch.Generator().manual_seed(seed + 2))
    sampler = GraphCurriculumSampler(WallDetour(), num_candidates=4, tradeoff=FixedTradeoff(1.0), scale="standardized")
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(100_000), sampler=sampler, transform=GoalToNext(),
                                    batch_size=128, generator=torch.Generator().manual_seed(seed + 3))
    env = PointMaze(num_envs, seed=seed)
    collector = Collector(env, explore, frames_per_batch=num_envs * 20, total_frames=frames,  # 20 steps: cuts episodes
                          auto_register_policy_transforms=False)  # the policy needs no env transform
    start, done_updates = time.perf_counter(), 0.0
    for i, batch in enumerate(collector):
        buffer.extend(relabel(split_trajectories(batch)))  # padded fragments [N', T'] with ("collector", "mask")
        done_updates += updates_per_frame * batch.numel()
        while done_updates >= 1:
            done_updates -= 1
            sample = buffer.sample()
            losses = loss(sample)
            optim_critic.zero_grad()
            optim_actor.zero_grad()
            (losses["loss_value"] + losses["loss_actor"]).backward()  # the actor loss reads detached critic weights
            optim_critic.step()
            optim_actor.step()
            target_update.step()
        if verbose and i % 25 == 0:
            print(f"{(i + 1) * batch.numel()} frames, {time.perf_counter() - start:.0f} s, buffer {len(buffer)}")
    collector.shutdown()
    rate = success_rate(PointMaze(num_envs, seed=seed + 100), actor)
    if verbose:
        print(f"greedy success rate {rate:.2f} after {frames} frames ({time.perf_counter() - start:.0f} s)")
    return rate


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=16_000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    train(args.frames, args.seed)
