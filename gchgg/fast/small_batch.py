"""The actor's forward and eq. 22's exploration on the rollout's small batches, without ``nn.Module`` calls.

The per-episode loop acts on one observation 5,000 times an iteration, where each module call and each
tensor operation counts. The devices here compute what the plain path computes, from its own tensors, in
fewer operations; ``tests/test_agent.py`` holds them equal, bit for bit and draw for draw, and
``python benchmarks/agent_update.py`` times each against the statement it stands beside:

- :class:`SmallBatchActor`: the actor's forward (:meth:`gchgg.ddpg.networks.GoalConditionedActor.forward`,
  the one definition) for batches below :data:`~gchgg.fast.linear.MIN_BATCH` rows;
- :class:`OneRowExploration`: eq. 22 (:meth:`gchgg.ddpg.agent.DDPGAgent.explore_actions`) on one row;
- :func:`one_row_policy`: both for one rollout's steps, with the per-call checks made once.

Each reads the plain path's objects through the few attributes declared below (:class:`Actor`,
:class:`ExplorationSettings`), so nothing here imports the algorithm.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Protocol

import torch
from torch import nn

from gchgg.fast.linear import MIN_BATCH

__all__ = ["Actor", "ExplorationSettings", "Normalizer", "OneRowExploration", "SmallBatchActor", "one_row_policy"]

Policy = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


class Normalizer(Protocol):
    """What is read of a normaliser (:class:`gchgg.ddpg.networks.RunningNormalizer`), whose forward is
    ``clamp((x − loc) / scale, −clip, clip)``."""

    loc: torch.Tensor
    scale: torch.Tensor
    clip: float


class Actor(Protocol):
    """What is read of the actor (:class:`gchgg.ddpg.networks.GoalConditionedActor`), whose forward is
    ``tanh(mlp([observation_normalizer(s), goal_normalizer(g)]))``, ``mlp`` a ``Linear, ReLU, …, Linear``
    sequence."""

    observation_normalizer: Normalizer
    goal_normalizer: Normalizer
    mlp: nn.Module


class ExplorationSettings(Protocol):
    """eq. 22's settings (:class:`gchgg.ddpg.agent.DDPGAgent`'s), read at every call: a setting changed is followed."""

    random_eps: float
    noise_std: float
    action_dim: int


class SmallBatchActor:
    """The actor's forward for batches below :data:`~gchgg.fast.linear.MIN_BATCH` rows, without ``nn.Module`` calls.

    The same operations on the same tensors as the actor module (the normalisers' clipped
    standardisation, ``F.linear`` — what its layers compute on such batches — ReLU, tanh), so the same
    actions bit for bit, at about half the cost per call; the standardisation runs once on the
    observation and goal joined (their statistics joined once per change), the same elementwise
    subtraction, division and clip as each normaliser's. It holds the actor's parameters and statistics
    themselves, which optimisers and ``load_state_dict`` change in place.
    """

    def __init__(self, actor: Actor) -> None:
        self.observation_normalizer, self.goal_normalizer = actor.observation_normalizer, actor.goal_normalizer
        modules = list(actor.mlp)
        self.layers = [(m.weight, m.bias) for m in modules if isinstance(m, nn.Linear)]
        expected = [nn.Linear, nn.ReLU] * (len(self.layers) - 1) + [nn.Linear]
        # an MLP of another shape (a subclass, other activations) keeps the module path
        self.usable = len(modules) == len(expected) and all(type(m) is t or (t is nn.Linear and isinstance(m, t))
                                                            for m, t in zip(modules, expected, strict=True))
        self._joined: tuple | None = None  # (the statistics' versions, _statistics()'s value for them)

    def takes(self, observation: torch.Tensor, goal: torch.Tensor) -> bool:
        """Whether this path gives the module's result: a 2-D float32 CPU batch below ``MIN_BATCH`` rows."""
        return (self.usable and observation.dim() == 2 and observation.shape[0] < MIN_BATCH
                and observation.dtype == goal.dtype == torch.float32 and observation.device.type == "cpu")

    def __call__(self, observation: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
        statistics = self._statistics()
        if statistics is not None:  # the same elementwise operations on the joined input: 4 operations instead of 7
            return self.joined_forward(observation, goal, *statistics)
        o, g = self.observation_normalizer, self.goal_normalizer
        return self._layers(torch.cat([((observation - o.loc) / o.scale).clamp(-o.clip, o.clip),
                                       ((goal - g.loc) / g.scale).clamp(-g.clip, g.clip)], -1))

    def joined_forward(self, observation: torch.Tensor, goal: torch.Tensor, loc: torch.Tensor, scale: torch.Tensor,
                       clip: float) -> torch.Tensor:
        """The forward with the statistics :meth:`_statistics` joined (``loc``, ``scale``, ``clip``)."""
        return self._layers(torch.cat([observation, goal], -1).sub_(loc).div_(scale).clamp_(-clip, clip))

    def _layers(self, x: torch.Tensor) -> torch.Tensor:
        last = len(self.layers) - 1
        for i, (weight, bias) in enumerate(self.layers):
            x = nn.functional.linear(x, weight, bias)
            if i < last:
                x.relu_()  # in place on the product's fresh output: the same values
        return x.tanh_()

    def stamp(self) -> tuple:
        """The normalisers' statistics as they are now: each tensor's storage and version (``update`` and
        ``load_state_dict`` change them in place, which bumps the version) and the two clips. Joined
        statistics (:meth:`_statistics`) hold while it is unchanged."""
        o, g = self.observation_normalizer, self.goal_normalizer
        return (*((t.data_ptr(), t._version) for t in (o.loc, o.scale, g.loc, g.scale)), o.clip, g.clip)

    def _statistics(self) -> tuple[torch.Tensor, torch.Tensor, float] | None:
        """The two normalisers' ``loc`` and ``scale`` joined, and their clip, joined again after either changed
        (``update`` and ``load_state_dict`` change them in place, which bumps their versions, or a clip was
        set); ``None`` where the joined form would not compute the same values (clips that differ,
        statistics not float32)."""
        o, g = self.observation_normalizer, self.goal_normalizer
        parts = (o.loc, o.scale, g.loc, g.scale)
        stamp = self.stamp()
        if self._joined is None or self._joined[0] != stamp:
            usable = o.clip == g.clip and all(t.dtype == torch.float32 for t in parts)
            joined = (torch.cat([o.loc, g.loc]), torch.cat([o.scale, g.scale]), o.clip) if usable else None
            self._joined = (stamp, joined)
        return self._joined[1]


class OneRowExploration:
    """eq. 22 for an ``action`` of one row ``[1, A]``, as :meth:`gchgg.ddpg.agent.DDPGAgent.explore_actions`
    computes it for any rows: the same draws in the same order (one uniform, ``A`` uniforms, ``A`` normals)
    and the same values, with a branch on the one row's coin instead of both outcomes computed and
    ``torch.where`` choosing. About half the tensor operations.

    The coin is compared with ``random_eps`` rounded to float32, as ``tensor < random_eps`` compares;
    :attr:`random_eps32` holds ``(random_eps, it rounded)``, rounded again when the setting changes.
    """

    def __init__(self, settings: ExplorationSettings) -> None:
        self.settings = settings
        self.random_eps32 = (math.nan, math.nan)

    def __call__(self, action: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        settings = self.settings
        coin = torch.rand(1, generator=generator, device=action.device)
        uniform = torch.rand((1, settings.action_dim), generator=generator)  # what random_action(1) draws
        normal = torch.randn(action.shape, generator=generator, device=action.device)
        if self.random_eps32[0] != settings.random_eps:  # a public setting: follow a change
            self.random_eps32 = (settings.random_eps, float(torch.tensor(settings.random_eps, dtype=torch.float32)))
        if float(coin) < self.random_eps32[1]:
            return uniform.mul_(2.0).sub_(1.0)
        return action.add_(normal.mul_(settings.noise_std)).clamp_(-1.0, 1.0)


def one_row_policy(actor: SmallBatchActor, explore: OneRowExploration, general: Policy, generator: torch.Generator,
                   obs_dim: int, goal_dim: int) -> Policy:
    """``general`` (acting with exploration, ``act(..., explore=True, generator=generator)``) for the steps of one
    rollout: the same actions and the same draws, call for call.

    A call on one float32 CPU row, with gradients off and the normalisers' statistics as they were when the
    policy was made, goes straight to ``actor``'s joined forward and ``explore`` (their statistics joined once,
    here); any other call (other shapes or dtypes, gradients enabled, statistics changed in place since by
    ``update_normalizer`` or ``load_state_dict``, or a changed clip) goes to ``general``. Returns ``general``
    itself where ``actor`` cannot join the statistics.
    """
    statistics = actor._statistics() if actor.usable else None
    if statistics is None:
        return general
    loc, scale, clip = statistics
    stamp, joined_at = actor.stamp, actor.stamp()  # the statistics' state they were joined in
    one_observation, one_goal = torch.Size([1, obs_dim]), torch.Size([1, goal_dim])
    forward, float32 = actor.joined_forward, torch.float32

    def policy(observation: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
        if (observation.shape != one_observation or goal.shape != one_goal or observation.dtype != float32
                or goal.dtype != float32 or not (observation.is_cpu and goal.is_cpu) or torch.is_grad_enabled()
                or stamp() != joined_at):
            return general(observation, goal)
        return explore(forward(observation, goal, loc, scale, clip), generator)

    return policy
