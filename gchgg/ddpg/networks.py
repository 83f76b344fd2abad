"""The learner's networks: the input normaliser, the actor ``π(s‖g)`` and the critic ``Q(s‖g, a)``.

As in the reference implementation (``REFERENCE.md``, "Training"): 3 × 256 ReLU MLPs
(:class:`torchrl.modules.MLP`) with Xavier-uniform weights and zero biases, tanh on the actor's output; the
observation and goal normalised *inside* both networks by running statistics (std floored at 1e-2,
normalised values clipped to ±5), two normalisers shared by the actor, the critic and their target copies
(:class:`gchgg.ddpg.loss.HindsightDDPGLoss`). :func:`make_ddpg_networks` builds the pair as TorchRL modules;
:func:`load_policy` rebuilds an actor from what :meth:`gchgg.ddpg.agent.DDPGAgent.policy_state` saved.

:meth:`GoalConditionedActor.forward` is the actor's one definition. The rollout's small batches take a speed
device that computes it without ``nn.Module`` calls (:class:`gchgg.fast.small_batch.SmallBatchActor`, the same
actions bit for bit, ``tests/test_agent.py``).
"""

from __future__ import annotations

import numbers
from collections.abc import Sequence
from typing import Any

import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.modules import MLP

from gchgg.common.validation import check_number
from gchgg.fast.linear import use_onednn

__all__ = ["GoalConditionedActor", "GoalConditionedCritic", "RunningNormalizer", "check_hidden", "load_policy",
           "make_ddpg_networks"]


class RunningNormalizer(nn.Module):
    """Running mean / standard deviation normaliser of a vector input.

    Statistics are accumulated in float64 over everything passed to :meth:`update` (Chan et al.'s
    parallel merge of count, mean and sum of squared deviations); :meth:`forward` computes
    ``clip((x − mean) / max(std, std_min), −clip, clip)`` in float32. Before the first update the
    normaliser is the identity (mean 0, std 1) up to the clip. All statistics are buffers updated in
    place, so modules that share them (the target networks) see every update.

    Args:
        size: number of features (the last dimension of the input).
        std_min: floor on the standard deviation (1e-2 in the reference).
        clip: normalised values are clipped to ``[-clip, clip]`` (5 in the reference).

    Examples:
        >>> norm = RunningNormalizer(2)
        >>> norm.update(torch.tensor([[0.0, 1.0], [2.0, 1.0]]))
        >>> norm(torch.tensor([[2.0, 1.0], [100.0, 1.0]]))
        tensor([[1., 0.],
                [5., 0.]])
    """

    def __init__(self, size: int, std_min: float = 1e-2, clip: float = 5.0) -> None:
        super().__init__()
        check_number("size", size, integer=True, low=1)
        check_number("std_min", std_min, low=0, low_open=True)
        check_number("clip", clip, low=0, low_open=True)
        self.size = int(size)
        self.std_min = float(std_min)
        self.clip = float(clip)
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))
        self.register_buffer("mean", torch.zeros(size, dtype=torch.float64))
        self.register_buffer("m2", torch.zeros(size, dtype=torch.float64))
        self.register_buffer("loc", torch.zeros(size))
        self.register_buffer("scale", torch.ones(size))

    @torch.no_grad()
    def update(self, x: torch.Tensor) -> None:
        """Add a batch ``x [..., size]`` to the statistics (in place).

        Raises:
            ValueError: ``x`` has the wrong last dimension or non-finite values.
        """
        if x.shape[-1:] != (self.size,):
            raise ValueError(f"normaliser expects inputs [..., {self.size}], got shape {tuple(x.shape)}")
        x = x.detach().reshape(-1, self.size).to(torch.float64)
        if x.shape[0] == 0:
            return
        if not torch.isfinite(x).all():
            raise ValueError("normaliser update got NaN or inf values; check the data handed to update_normalizer")
        n_b = x.shape[0]
        mean_b = x.mean(0)
        m2_b = (x - mean_b).square().sum(0)
        n_a = self.count.clone()
        n = n_a + n_b
        delta = mean_b - self.mean
        self.mean.add_(delta * (n_b / n))
        self.m2.add_(m2_b + delta.square() * (n_a * n_b / n))
        self.count.copy_(n)
        self.loc.copy_(self.mean)
        self.scale.copy_((self.m2 / n).sqrt().clamp_min(self.std_min))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Normalise ``x [..., size]``: float32, clipped to ``[-clip, clip]``."""
        return ((x - self.loc) / self.scale).clamp(-self.clip, self.clip)

    @torch.no_grad()
    def clipped_fraction(self, x: torch.Tensor) -> torch.Tensor:
        """The fraction of ``x``'s normalised entries at the clip (±clip), a float32 scalar tensor. A large one
        means the statistics do not cover the data the networks train on (e.g. an object far outside the
        positions the normaliser has seen)."""
        return (self(x).abs() >= self.clip).float().mean()

    def extra_repr(self) -> str:
        return f"size={self.size}, std_min={self.std_min}, clip={self.clip}"


def check_hidden(hidden: Any) -> tuple[int, ...]:
    """``hidden`` as a tuple of layer widths, or a ``ValueError``: a non-empty sequence of integers ≥ 1."""
    widths = tuple(hidden)
    if not widths or not all(isinstance(h, numbers.Integral) and not isinstance(h, bool) and h >= 1 for h in widths):
        raise ValueError(f"hidden must be a non-empty sequence of positive layer widths, got {hidden!r}")
    return widths


def _mlp(in_features: int, out_features: int, hidden: Sequence[int], generator: torch.Generator | None) -> MLP:
    """A ReLU :class:`~torchrl.modules.MLP` with Xavier-uniform weights and zero biases."""
    net = MLP(
        in_features=in_features,
        out_features=out_features,
        num_cells=list(hidden),
        activation_class=nn.ReLU,
    )
    for layer in net.modules():
        if isinstance(layer, nn.Linear):
            nn.init.xavier_uniform_(layer.weight, generator=generator)
            nn.init.zeros_(layer.bias)
    return net


class GoalConditionedActor(nn.Module):
    """Deterministic policy ``π(s‖g) = tanh(MLP([norm(s), norm(g)]))`` with actions in [−1, 1].

    Args:
        observation_normalizer: normaliser of the observation (shared with the critic).
        goal_normalizer: normaliser of the goal (shared with the critic).
        action_dim: number of action dimensions.
        hidden: widths of the hidden layers.
        generator: draws the initial weights (``None``: torch's global generator).
    """

    def __init__(
        self,
        observation_normalizer: RunningNormalizer,
        goal_normalizer: RunningNormalizer,
        action_dim: int,
        hidden: Sequence[int] = (256, 256, 256),
        generator: torch.Generator | None = None,
    ) -> None:
        super().__init__()
        self.observation_normalizer = observation_normalizer
        self.goal_normalizer = goal_normalizer
        in_features = observation_normalizer.size + goal_normalizer.size
        self.mlp = _mlp(in_features, action_dim, hidden, generator)

    def forward(self, observation: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
        """Action ``[..., action_dim]`` for ``observation [..., obs_dim]`` and ``goal [..., goal_dim]``."""
        x = torch.cat([self.observation_normalizer(observation), self.goal_normalizer(goal)], -1)
        return self.mlp(x).tanh()


class GoalConditionedCritic(nn.Module):
    """Action value ``Q(s‖g, a) = MLP([norm(s), norm(g), a])``; the action enters unnormalised.

    Args:
        observation_normalizer: normaliser of the observation (shared with the actor).
        goal_normalizer: normaliser of the goal (shared with the actor).
        action_dim: number of action dimensions.
        hidden: widths of the hidden layers.
        generator: draws the initial weights (``None``: torch's global generator).
    """

    def __init__(
        self,
        observation_normalizer: RunningNormalizer,
        goal_normalizer: RunningNormalizer,
        action_dim: int,
        hidden: Sequence[int] = (256, 256, 256),
        generator: torch.Generator | None = None,
    ) -> None:
        super().__init__()
        self.observation_normalizer = observation_normalizer
        self.goal_normalizer = goal_normalizer
        in_features = observation_normalizer.size + goal_normalizer.size + action_dim
        self.mlp = _mlp(in_features, 1, hidden, generator)

    def forward(self, observation: torch.Tensor, goal: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """``Q [..., 1]`` for ``observation [..., obs_dim]``, ``goal [..., goal_dim]``, ``action [..., A]``."""
        x = torch.cat([self.observation_normalizer(observation), self.goal_normalizer(goal), action], -1)
        return self.mlp(x)


def make_ddpg_networks(
    obs_dim: int,
    goal_dim: int,
    action_dim: int,
    hidden: Sequence[int] = (256, 256, 256),
    *,
    norm_std_min: float = 1e-2,
    norm_clip: float = 5.0,
    observation_key: str = "observation",
    goal_key: str = "desired_goal",
    action_key: str = "action",
    generator: torch.Generator | None = None,
) -> tuple[TensorDictModule, TensorDictModule]:
    """Build the actor and critic as :class:`~tensordict.nn.TensorDictModule` s sharing two normalisers.

    Args:
        obs_dim: observation size.
        goal_dim: goal size.
        action_dim: action size.
        hidden: widths of the hidden layers of both MLPs.
        norm_std_min: std floor of the normalisers.
        norm_clip: clip of the normalised values.
        observation_key: TensorDict key of the observation.
        goal_key: TensorDict key of the goal.
        action_key: TensorDict key of the action (written by the actor, read by the critic).
        generator: draws the initial weights.

    Returns:
        ``(actor, critic)``: the actor reads ``[observation_key, goal_key]`` and writes
        ``action_key``; the critic reads ``[observation_key, goal_key, action_key]`` and writes
        ``"state_action_value"`` (``[..., 1]``), TorchRL's name for it.

    Examples:
        >>> from tensordict import TensorDict
        >>> actor, critic = make_ddpg_networks(5, 3, 2, hidden=(16,))
        >>> td = critic(actor(TensorDict({"observation": torch.zeros(4, 5), "desired_goal": torch.zeros(4, 3)}, [4])))
        >>> td["action"].shape, td["state_action_value"].shape
        (torch.Size([4, 2]), torch.Size([4, 1]))
    """
    for name, value in (("obs_dim", obs_dim), ("goal_dim", goal_dim), ("action_dim", action_dim)):
        check_number(name, value, integer=True, low=1)
    hidden = check_hidden(tuple(hidden))
    observation_normalizer = RunningNormalizer(obs_dim, norm_std_min, norm_clip)
    goal_normalizer = RunningNormalizer(goal_dim, norm_std_min, norm_clip)
    actor = GoalConditionedActor(observation_normalizer, goal_normalizer, action_dim, hidden, generator)
    critic = GoalConditionedCritic(observation_normalizer, goal_normalizer, action_dim, hidden, generator)
    return (
        TensorDictModule(actor, in_keys=[observation_key, goal_key], out_keys=[action_key]),
        TensorDictModule(critic, in_keys=[observation_key, goal_key, action_key], out_keys=["state_action_value"]),
    )


def load_policy(state: dict[str, Any], matmul: str = "auto") -> GoalConditionedActor:
    """The deterministic actor ``actor(observation, goal) -> action`` of a
    :meth:`~gchgg.ddpg.agent.DDPGAgent.policy_state` (normalisation included), in eval mode; ``matmul`` as for
    :class:`~gchgg.ddpg.agent.DDPGAgent`.

    Raises:
        KeyError: the state lacks ``hparams`` or ``actor``.
    """
    missing = {"hparams", "actor"} - set(state)
    if missing:
        raise KeyError(f"policy state is missing {sorted(missing)}; was it written by DDPGAgent.policy_state()?")
    h = state["hparams"]
    actor, _ = make_ddpg_networks(
        h["obs_dim"], h["goal_dim"], h["action_dim"], tuple(h["hidden"]),
        norm_std_min=h["norm_std_min"], norm_clip=h["norm_clip"],
    )  # fmt: skip
    module = actor.module if matmul == "default" else use_onednn(actor.module, matmul)  # default: torch's own layers
    module.load_state_dict(state["actor"])
    return module.eval()
