"""Goal-conditioned DDPG (the HER / HGG learner) built from TorchRL parts.

The agent follows the reference implementation's defaults (``REFERENCE.md``, "Training"):

- actor ``π(s‖g)`` and critic ``Q(s‖g, a)``: 3 × 256 ReLU MLPs (:class:`torchrl.modules.MLP`), tanh on
  the actor's output, Xavier-uniform weights and zero biases as in the original code;
- observation and goal normalised *inside* both networks by running statistics (std floored at
  1e-2, normalised values clipped to ±5). The target networks share the online networks'
  statistics, so a relabelled goal is always normalised with the current statistics;
- critic target ``y = r + γ·clip(Q'(s'‖g, π'(s'‖g)), −1/(1−γ), 0)`` with no done mask (the tasks only
  time out), actor loss ``−mean Q(s‖g, π(s‖g)) + 1.0·mean(π²)``; both losses are computed from the
  same parameters and both networks step together (Adam, 1e-3);
- target networks ``θ' ← 0.95·θ' + 0.05·θ`` once every 20 updates;
- exploration (eq. 22): with probability 0.3 a uniform random action, otherwise ``π + N(0, 0.2²)``,
  clipped to [−1, 1]; every draw comes from a ``torch.Generator`` the caller passes in.

:class:`HindsightDDPGLoss` holds the losses and the target networks (a plain module: TorchRL's
``DDPGLoss`` has neither the clipped bootstrap nor the action penalty); :class:`DDPGAgent` adds the
optimisers, the target-update schedule, exploration, the value function HGG needs and a complete
``state_dict``. Its :meth:`DDPGAgent.update` reads the batch's tensors once and runs the loss's
tensor path, differentiated by autograd or by hand with the same result bit for bit
(:mod:`gchgg.fast.fused_update`, the default; ``benchmarks/agent_update.py`` times both). Its ``matmul``
argument picks who computes the wide layers' matrix products (:mod:`gchgg.fast.linear`: oneDNN where
measured faster); it changes speed, not the math. So does ``subnormals`` (:mod:`gchgg.fast.subnormal`), and
so does stepping the fused Adam optimisers through :func:`gchgg.fast.adam_step.adam_step`.
"""

from __future__ import annotations

import copy
import math
import numbers
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, fields, replace
from functools import partial
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.modules import MLP

from gchgg.common.validation import check_choice, check_number
from gchgg.fast.adam_step import adam_step
from gchgg.fast.fused_update import FusedDDPGUpdate, compiler_found, unsupported
from gchgg.fast.linear import MIN_BATCH, OneDNNLinear, products_in, resolve_matmul, resolve_precision, use_onednn
from gchgg.fast.subnormal import SUBNORMALS, flush_subnormals

__all__ = [
    "GRADIENTS",
    "DDPGAgent",
    "DDPGConfig",
    "GoalConditionedActor",
    "GoalConditionedCritic",
    "HindsightDDPGLoss",
    "RunningNormalizer",
    "load_policy",
    "make_ddpg_networks",
]


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

    def extra_repr(self) -> str:
        return f"size={self.size}, std_min={self.std_min}, clip={self.clip}"


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
        >>> actor, critic = make_ddpg_networks(5, 3, 2, hidden=(16,))
        >>> td = critic(actor(TensorDict({"observation": torch.zeros(4, 5), "desired_goal": torch.zeros(4, 3)}, [4])))
        >>> td["action"].shape, td["state_action_value"].shape
        (torch.Size([4, 2]), torch.Size([4, 1]))
    """
    for name, value in (("obs_dim", obs_dim), ("goal_dim", goal_dim), ("action_dim", action_dim)):
        check_number(name, value, integer=True, low=1)
    hidden = tuple(hidden)
    if not hidden or not all(isinstance(h, numbers.Integral) and not isinstance(h, bool) and h >= 1 for h in hidden):
        raise ValueError(f"hidden must be a non-empty sequence of positive layer widths, got {hidden!r}")
    observation_normalizer = RunningNormalizer(obs_dim, norm_std_min, norm_clip)
    goal_normalizer = RunningNormalizer(goal_dim, norm_std_min, norm_clip)
    actor = GoalConditionedActor(observation_normalizer, goal_normalizer, action_dim, hidden, generator)
    critic = GoalConditionedCritic(observation_normalizer, goal_normalizer, action_dim, hidden, generator)
    return (
        TensorDictModule(actor, in_keys=[observation_key, goal_key], out_keys=[action_key]),
        TensorDictModule(critic, in_keys=[observation_key, goal_key, action_key], out_keys=["state_action_value"]),
    )


GRADIENTS = ("auto", "fused", "compiled", "autograd")
"""How :meth:`DDPGAgent.update` computes the gradients (the ``gradients`` setting): ``autograd`` differentiates
:class:`HindsightDDPGLoss`; ``fused`` computes the same losses and gradients by hand
(:class:`gchgg.fast.fused_update.FusedDDPGUpdate`: bit for bit autograd's, on torch's BLAS and on oneDNN in
float32 or bfloat16, faster by the autograd overhead and conversions it skips,
``benchmarks/agent_update.py``); ``compiled``: that update compiled by ``torch.compile`` (TorchInductor,
which needs a C++ compiler) for the batches whose products run on oneDNN, equal to it to float32 rounding and
faster by the Python and element-wise passes it removes; ``auto``: ``compiled`` where the products are
bfloat16 on oneDNN and a C++ compiler is found (:func:`gchgg.fast.fused_update.compiler_found`), else ``fused``
where it applies (the ReLU MLPs :func:`make_ddpg_networks` builds), else ``autograd``."""


@dataclass(frozen=True)
class DDPGConfig:
    """The learner's hyperparameters, each declared once, here (defaults: the original code's, REFERENCE.md).

    The ``agent`` section of a run's config (:class:`gchgg.run.config.AgentConfig`, with these defaults) sets
    them by name (``agent.actor_lr=5e-4``); a :class:`DDPGAgent` logs them in ``hparams`` and refuses a
    state saved with others.

    >>> DDPGConfig(actor_lr=0)
    Traceback (most recent call last):
    ...
    ValueError: actor_lr must be a number > 0, got 0
    """

    hidden: tuple[int, ...] = (256, 256, 256)  # hidden-layer widths of the actor and of the critic
    actor_lr: float = 1e-3  # Adam learning rate of the actor
    critic_lr: float = 1e-3  # Adam learning rate of the critic
    gamma: float = 0.98  # discount factor, in (0, 1)
    polyak: float = 0.95  # target networks move as θ' ← polyak·θ' + (1 − polyak)·θ
    target_update_every: int = 20  # the target networks move after every n-th update
    action_l2: float = 1.0  # weight of mean(π²) in the actor loss
    clip_return: bool = True  # clip the bootstrapped Q' to [−1/(1−γ), 0] in the critic target
    random_eps: float = 0.3  # probability of a uniform random action when exploring (eq. 22)
    noise_std: float = 0.2  # std of the Gaussian action noise when exploring (eq. 22)
    norm_std_min: float = 1e-2  # std floor of the observation / goal normalisers
    norm_clip: float = 5.0  # normalised observations and goals are clipped to ±norm_clip

    def __post_init__(self) -> None:
        hidden = tuple(self.hidden)
        if not hidden or not all(isinstance(h, numbers.Integral) and not isinstance(h, bool) and h >= 1
                                 for h in hidden):
            raise ValueError(f"hidden must be a non-empty sequence of positive layer widths, got {self.hidden!r}")
        object.__setattr__(self, "hidden", hidden)
        for name in ("actor_lr", "critic_lr", "norm_std_min", "norm_clip"):
            check_number(name, getattr(self, name), low=0, low_open=True)
        check_number("gamma", self.gamma, low=0, high=1, low_open=True, high_open=True)
        check_number("polyak", self.polyak, low=0, high=1)
        check_number("target_update_every", self.target_update_every, integer=True, low=1)
        check_number("action_l2", self.action_l2, low=0)
        check_number("random_eps", self.random_eps, low=0, high=1)
        check_number("noise_std", self.noise_std, low=0)


class HindsightDDPGLoss(nn.Module):
    """The HER / HGG DDPG losses and target networks, as a plain :class:`torch.nn.Module`.

    - critic: ``mean((Q(s‖g, a) − y)²)`` with ``y = r + γ·clip(Q'(s'‖g, π'(s'‖g)), −1/(1−γ), 0)``.
      There is no done mask (goal-conditioned episodes only time out, so every next state is
      bootstrapped) and the next state's goal is the transition's own goal (as written by the HER
      relabel transform); no ``("next", goal)`` entry is read.
    - actor: ``−mean Q(s‖g, π(s‖g)) + action_l2·mean(π²)``; the critic's weights get no gradient
      from it, so one ``backward`` of the sum gives each network its own gradient.
    - target networks ``θ' ← polyak·θ' + (1 − polyak)·θ`` by :meth:`update_targets`.

    It is not a :class:`torchrl.objectives.LossModule`: TorchRL's ``DDPGLoss`` has neither the
    clipped bootstrap nor the action penalty, and the normalisers' running statistics must be
    shared, not copied, by the target networks. It follows the loss-module conventions that a
    pipeline relies on: :meth:`forward` maps a batch TensorDict to a TensorDict of ``loss_*``
    entries (sum them and call ``backward``), and the networks are ordinary submodules.

    The target networks are copies of the online ones whose *parameters* are copied and whose
    *buffers* (the normalisers' statistics) are the online tensors themselves, so updating a
    normaliser updates all four networks, and a relabelled goal is always normalised with the
    current statistics.

    Args:
        actor_network: deterministic actor from :func:`make_ddpg_networks`: it reads
            ``[observation_key, goal_key]`` and writes the action key; its ``module`` is called as
            ``module(observation, goal)``.
        value_network: critic reading ``[observation_key, goal_key, action_key]``; its ``module``
            is called as ``module(observation, goal, action) -> Q [..., 1]``.

    Keyword Args:
        gamma: discount factor, in (0, 1).
        action_l2: weight of ``mean(π²)`` in the actor loss (>= 0).
        clip_return: clip the bootstrapped ``Q'`` to ``[−1/(1−γ), 0]`` (rewards in {−1, 0}).

    The reward is read from ``("next", "reward")`` (``[B, 1]``), the next observation from
    ``("next", observation_key)``. :meth:`forward` returns a TensorDict with ``loss_actor``,
    ``loss_value``, ``pred_value`` and ``target_value`` (batch means); :meth:`losses` computes the same
    from plain tensors.

    Examples:
        >>> actor, critic = make_ddpg_networks(5, 3, 2, hidden=(16,))
        >>> loss = HindsightDDPGLoss(actor, critic)
        >>> batch = TensorDict({
        ...     "observation": torch.randn(8, 5), "desired_goal": torch.randn(8, 3),
        ...     "action": torch.rand(8, 2) * 2 - 1,
        ...     "next": {"observation": torch.randn(8, 5), "reward": -torch.ones(8, 1)},
        ... }, [8])
        >>> out = loss(batch)
        >>> (out["loss_actor"] + out["loss_value"]).backward()
        >>> loss.update_targets(polyak=0.95)  # target <- 0.95 target + 0.05 online
        >>> sorted(out.keys())
        ['loss_actor', 'loss_value', 'pred_value', 'target_value']
    """

    def __init__(
        self,
        actor_network: TensorDictModule,
        value_network: TensorDictModule,
        *,
        gamma: float = DDPGConfig.gamma,
        action_l2: float = DDPGConfig.action_l2,
        clip_return: bool = DDPGConfig.clip_return,
    ) -> None:
        super().__init__()
        check_number("gamma", gamma, low=0, high=1, low_open=True, high_open=True)
        check_number("action_l2", action_l2, low=0)
        if len(actor_network.in_keys) != 2 or len(actor_network.out_keys) != 1:
            raise ValueError(
                "actor_network must read [observation_key, goal_key] and write one action key, got "
                f"in_keys={actor_network.in_keys}, out_keys={actor_network.out_keys}"
            )
        self.gamma = float(gamma)
        self.action_l2 = float(action_l2)
        self.clip_return = bool(clip_return)
        self.observation_key, self.goal_key = actor_network.in_keys
        self.action_key = actor_network.out_keys[0]
        self.reward_key = ("next", "reward")
        self.actor = actor_network.module
        self.critic = value_network.module
        self.target_actor = _target_copy(self.actor)
        self.target_critic = _target_copy(self.critic)

    @property
    def return_range(self) -> tuple[float, float]:
        """``(−1/(1−γ), 0)``: the range of returns with rewards in {−1, 0}."""
        return -1.0 / (1.0 - self.gamma), 0.0

    def losses(
        self,
        observation: torch.Tensor,
        goal: torch.Tensor,
        action: torch.Tensor,
        next_observation: torch.Tensor,
        reward: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The two losses from plain tensors (the fast path; same values as :meth:`forward`).

        Args:
            observation: ``[B, obs_dim]``.
            goal: ``[B, goal_dim]``, the goal of both ``s`` and ``s'``.
            action: ``[B, A]``.
            next_observation: ``[B, obs_dim]``.
            reward: ``[B, 1]``.

        Returns:
            ``(loss_actor, loss_value, pred_value [B, 1], target_value [B, 1])``; the last two are
            detached.
        """
        loss_value, pred_value, target_value = self.critic_loss(observation, goal, action, next_observation, reward)
        return self.actor_loss(observation, goal), loss_value, pred_value, target_value

    def critic_loss(self, observation, goal, action, next_observation, reward):
        """``(mean((Q − y)²), Q [B, 1], y [B, 1])``, the last two detached."""
        with torch.no_grad():
            next_value = self.target_critic(next_observation, goal, self.target_actor(next_observation, goal))
            if self.clip_return:
                next_value = next_value.clamp(*self.return_range)
            target_value = reward + self.gamma * next_value
        pred_value = self.critic(observation, goal, action)
        if pred_value.shape != target_value.shape:
            raise ValueError(
                f"the reward must be [B, 1] like the critic's output {tuple(pred_value.shape)}, "
                f"got {tuple(reward.shape)}"
            )
        loss_value = (pred_value - target_value).square().mean()
        return loss_value, pred_value.detach(), target_value

    def actor_loss(self, observation, goal):
        """``−mean Q(s‖g, π(s‖g)) + action_l2·mean(π²)``; no gradient reaches the critic's weights."""
        policy_action = self.actor(observation, goal)
        critic_weights = list(self.critic.parameters())
        for weight in critic_weights:  # recorded as constants: gradient flows to the action only
            weight.requires_grad_(False)
        try:
            loss_actor = -self.critic(observation, goal, policy_action).mean()
        finally:
            for weight in critic_weights:
                weight.requires_grad_(True)
        if self.action_l2:
            loss_actor = loss_actor + self.action_l2 * policy_action.square().mean()
        return loss_actor

    @torch.no_grad()
    def update_targets(self, polyak: float) -> None:
        """``θ' ← polyak·θ' + (1 − polyak)·θ`` for both target networks (in place)."""
        for online, target in ((self.actor, self.target_actor), (self.critic, self.target_critic)):
            for weight, target_weight in zip(online.parameters(), target.parameters(), strict=True):
                target_weight.lerp_(weight, 1 - polyak)

    @property
    def in_keys(self) -> list:
        """The batch entries :meth:`forward` reads: observation, goal, action, next observation, reward
        (TorchRL's loss-module convention)."""
        return [self.observation_key, self.goal_key, self.action_key, ("next", self.observation_key), self.reward_key]

    def inputs(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, ...]:
        """The tensors :meth:`losses` takes, read from a batch: observation, goal, action, next observation, reward."""
        return tuple(tensordict.get(key) for key in self.in_keys)

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        """Losses of a batch: ``loss_actor``, ``loss_value``, and the means of ``pred_value`` and ``target_value``."""
        loss_actor, loss_value, pred_value, target_value = self.losses(*self.inputs(tensordict))
        return TensorDict(
            {
                "loss_actor": loss_actor,
                "loss_value": loss_value,
                "pred_value": pred_value.mean(),
                "target_value": target_value.mean(),
            },
            batch_size=[],
        )

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # checkpoints written while this loss subclassed torchrl's DDPGLoss name the networks
        # "<name>_network_params.module.*"; read them under today's names
        for old, new in _LEGACY_NAMES.items():
            for key in [k for k in state_dict if k.startswith(prefix + old)]:
                state_dict[prefix + new + key[len(prefix + old):]] = state_dict.pop(key)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)


_LEGACY_NAMES = {
    "target_actor_network_params.module.": "target_actor.",
    "target_value_network_params.module.": "target_critic.",
    "actor_network_params.module.": "actor.",
    "value_network_params.module.": "critic.",
}


def _target_copy(network: nn.Module) -> nn.Module:
    """A copy of ``network`` with its own parameters (no gradient) and the *same* buffer tensors."""
    target = copy.deepcopy(network, memo={id(buffer): buffer for buffer in network.buffers()})
    return target.requires_grad_(False)


class DDPGAgent:
    """Goal-conditioned DDPG with the reference hyperparameters: act, learn, value, checkpoint.

    Args:
        obs_dim: observation size.
        goal_dim: goal size (3 for every task here).
        action_dim: action size.
        config: the hyperparameters (:class:`DDPGConfig`; default: the original code's).
        generator: draws the initial weights (``None``: torch's global generator).
        matmul: who computes the wide layers' products, one of :data:`gchgg.fast.linear.MATMUL_BACKENDS`
            (``"auto"``: oneDNN where this torch has it and the products are bfloat16 or the CPU is one of
            :data:`gchgg.fast.linear.ONEDNN_FASTER`, else torch's BLAS; resolved into :attr:`matmul`, the
            backend its layers use, which a process acting with its policy passes to :func:`load_policy`
            to act alike). Speed only: it is not a hyperparameter, is not saved, and a state loads under
            any backend.
        precision: the dtype of those products in :meth:`update`, one of :data:`gchgg.fast.linear.PRECISIONS`:
            ``"float32"`` (default: the math as written), ``"bfloat16"`` (oneDNN's native bfloat16
            products on CPUs with AVX-512 BF16 or AMX; ``benchmarks/agent_update.py`` times it) or
            ``"auto"`` (bfloat16 where that is native, what training uses by default; resolved into
            :attr:`precision` by :func:`gchgg.fast.linear.resolve_precision`). Unlike ``matmul`` it changes
            the numbers (rounding), so runs record it; acting stays float32.
        gradients: how :meth:`update` computes the gradients, one of :data:`GRADIENTS` (``"auto"``: by
            hand where that applies; resolved into :attr:`gradients`). Speed only, like ``matmul``:
            the gradients are autograd's.
        subnormals: ``"flush"`` (default) runs :meth:`update` with subnormal floats flushed to zero
            (:mod:`gchgg.fast.subnormal`: Adam's moments of units that stopped firing decay into that slow
            range; flushed, the networks come out the same bit for bit), ``"keep"`` with IEEE arithmetic.
        **overrides: fields of :class:`DDPGConfig` to change (``hidden=(32,)``).

    The batch given to :meth:`update` holds ``observation [B, obs_dim]``, ``desired_goal [B, goal_dim]``,
    ``action [B, A]``, ``("next", "observation")`` and ``("next", "reward") [B, 1]``; other keys are
    ignored (in particular ``done``: there is no done mask).

    Examples:
        >>> init = torch.Generator().manual_seed(0)
        >>> agent = DDPGAgent(obs_dim=5, goal_dim=3, action_dim=2, hidden=(32,), generator=init)
        >>> rng = torch.Generator().manual_seed(1)
        >>> obs, goal = torch.randn(4, 5), torch.randn(4, 3)
        >>> agent.update_normalizer(obs, goal)
        >>> agent.act(obs, goal, explore=True, generator=rng).shape
        torch.Size([4, 2])
        >>> batch = TensorDict({
        ...     "observation": obs, "desired_goal": goal, "action": agent.random_action(4, rng),
        ...     "next": {"observation": obs + 0.1, "reward": -torch.ones(4, 1)},
        ... }, [4])
        >>> sorted(agent.update(batch))
        ['loss_actor', 'loss_value', 'pred_value', 'target_value']
        >>> agent.value(obs, goal).shape
        torch.Size([4])
    """

    def __init__(
        self,
        obs_dim: int,
        goal_dim: int,
        action_dim: int,
        config: DDPGConfig | None = None,
        *,
        generator: torch.Generator | None = None,
        matmul: str = "auto",
        precision: str = "float32",
        gradients: str = "auto",
        subnormals: str = "flush",
        **overrides: Any,
    ) -> None:
        unknown = set(overrides) - {f.name for f in fields(DDPGConfig)}
        if unknown:
            raise TypeError(f"unknown DDPGAgent settings {sorted(unknown)}; the settings are DDPGConfig's fields")
        config = replace(config or DDPGConfig(), **overrides)
        self.config = config
        check_choice("subnormals", subnormals, SUBNORMALS)
        self.subnormals = subnormals
        self.obs_dim, self.goal_dim, self.action_dim = int(obs_dim), int(goal_dim), int(action_dim)
        self.gamma = float(config.gamma)
        self.polyak = float(config.polyak)
        self.target_update_every = int(config.target_update_every)
        self.random_eps = float(config.random_eps)
        self.noise_std = float(config.noise_std)
        self._random_eps32 = (math.nan, math.nan)  # random_eps and it rounded to float32 (_explore_one_row)
        self.hparams = dict(obs_dim=obs_dim, goal_dim=goal_dim, action_dim=action_dim, **asdict(config))

        actor, critic = make_ddpg_networks(
            obs_dim, goal_dim, action_dim, config.hidden,
            norm_std_min=config.norm_std_min, norm_clip=config.norm_clip, generator=generator,
        )  # fmt: skip
        self.loss_module = HindsightDDPGLoss(
            actor, critic, gamma=config.gamma, action_l2=config.action_l2, clip_return=config.clip_return
        )
        self.precision = resolve_precision(precision, matmul)  # "auto" -> what this machine does well
        self.matmul = resolve_matmul(matmul, self.precision)  # the backend the layers got: "onednn" or "default"
        use_onednn(self.loss_module, self.matmul)  # the online and the target networks
        # fused Adam: one kernel per step instead of several per parameter (stepped by gchgg.fast.adam_step)
        self.actor_optimizer = torch.optim.Adam(self.actor.parameters(), lr=config.actor_lr, fused=True)
        self.critic_optimizer = torch.optim.Adam(self.critic.parameters(), lr=config.critic_lr, fused=True)
        self.observation_normalizer: RunningNormalizer = self.loss_module.actor.observation_normalizer
        self.goal_normalizer: RunningNormalizer = self.loss_module.actor.goal_normalizer
        self._small_batch_actor = SmallBatchActor(self.actor)  # the rollout's one-episode steps
        self._fused = self._fused_update(gradients)
        self.num_updates = 0

    def _fused_update(self, gradients: str) -> FusedDDPGUpdate | None:
        """The hand-differentiated update ``gradients`` selects, or ``None`` for autograd's."""
        if gradients not in GRADIENTS:
            raise ValueError(f"gradients must be one of {list(GRADIENTS)}, got {gradients!r}")
        if gradients == "autograd":
            return None
        reason = unsupported(self.loss_module)
        if reason is None:
            on_onednn = any(type(layer) is OneDNNLinear for layer in self.loss_module.modules())
            compiled = gradients == "compiled" or (
                gradients == "auto" and self.precision == "bfloat16" and on_onednn and compiler_found()
            )
            return FusedDDPGUpdate(self.loss_module, precision=self.precision, compiled=compiled,
                                   fall_back=gradients == "auto")  # fmt: skip
        if gradients in ("fused", "compiled"):
            raise ValueError(f"gradients={gradients!r} differentiates ReLU MLPs of float32 linear layers, but "
                             f"{reason}; use gradients=auto or autograd")
        return None

    @property
    def gradients(self) -> str:
        """The ``gradients`` setting resolved: ``"compiled"``, ``"fused"`` or ``"autograd"`` (``"fused"`` once a
        compiled update that could not be built fell back to running eagerly)."""
        if self._fused is None:
            return "autograd"
        return "compiled" if self._fused.compiled else "fused"

    # -- acting ---------------------------------------------------------------------------------

    @property
    def actor(self) -> nn.Module:
        """The online actor: ``actor(observation, goal) -> action`` (normalisation included)."""
        return self.loss_module.actor

    @property
    def critic(self) -> nn.Module:
        """The online critic: ``critic(observation, goal, action) -> Q [..., 1]``."""
        return self.loss_module.critic

    @torch.no_grad()
    def act(
        self,
        observation: torch.Tensor,
        goal: torch.Tensor,
        explore: bool = False,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """Actions for a batch of observations and goals.

        Args:
            observation: ``[N, obs_dim]`` (any leading shape).
            goal: ``[N, goal_dim]``, same leading shape.
            explore: ``False``: the deterministic ``π(s‖g)``. ``True``: eq. 22 — per row, with
                probability ``random_eps`` a uniform action, otherwise ``π + N(0, noise_std²)``,
                clipped to [−1, 1].
            generator: the source of the exploration draws; required when ``explore``. Each call
                draws a fixed amount from it (N uniforms, then N·A uniforms, then N·A normals).

        Returns:
            float32 ``[N, action_dim]`` in [−1, 1].
        """
        self._check_inputs(observation, goal)
        small = self._small_batch_actor
        action = small(observation, goal) if small.takes(observation, goal) else self.actor(observation, goal)
        if not explore:
            return action
        if generator is None:
            raise ValueError("act(explore=True) needs a torch.Generator: pass generator=...")
        if action.shape[:-1] == (1,):  # the per-episode loop's one row: the speed device beside eq. 22
            return self._explore_one_row(action, generator)
        return self.explore_actions(action, generator)

    def rollout_policy(self, generator: torch.Generator) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
        """``act(observation, goal, explore=True, generator=generator)`` for the steps of one rollout: the same
        actions and the same draws, call for call.

        The per-episode loop acts on one row 5,000 times an iteration, between physics steps; this path
        reaches :class:`SmallBatchActor` and the one-row branch of eq. 22 without ``act``'s per-call
        checks and dispatch, with the normalisers' joined statistics read once, when it is made
        (``python benchmarks/iteration.py`` prints the rollout both ways). Any other call goes to ``act``:
        other shapes or dtypes, gradients enabled, or statistics changed in place since (``update_normalizer``,
        ``load_state_dict``) or a changed clip. Make one per rollout, as the trainer does per chunk.
        """
        if generator is None:
            raise ValueError("rollout_policy needs a torch.Generator for eq. 22's draws: pass generator=...")
        general = partial(self.act, explore=True, generator=generator)
        small = self._small_batch_actor
        statistics = small._statistics() if small.usable else None
        if statistics is None:
            return general
        loc, scale, clip = statistics
        stamp, joined_at = small.stamp, small.stamp()  # the statistics' state they were joined in
        one_observation, one_goal = torch.Size([1, self.obs_dim]), torch.Size([1, self.goal_dim])
        forward, explore, float32 = small.joined_forward, self._explore_one_row, torch.float32

        def policy(observation: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
            if (observation.shape != one_observation or goal.shape != one_goal or observation.dtype != float32
                    or goal.dtype != float32 or not (observation.is_cpu and goal.is_cpu) or torch.is_grad_enabled()
                    or stamp() != joined_at):
                return general(observation, goal)
            return explore(forward(observation, goal, loc, scale, clip), generator)

        return policy

    def explore_actions(self, action: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """Eq. 22 on the deterministic actions ``action`` ``[..., A]`` (changed in place): per row, with
        probability ``random_eps`` a uniform action, otherwise ``action + N(0, noise_std²)`` clipped to
        [−1, 1]. Draws N uniforms, then N·A uniforms, then N·A normals from ``generator``."""
        lead = action.shape[:-1]
        take_random = torch.rand(lead, generator=generator, device=action.device) < self.random_eps
        random_action = self.random_action(lead, generator)
        noise = torch.randn(action.shape, generator=generator, device=action.device).mul_(self.noise_std)
        action = action.add_(noise).clamp_(-1.0, 1.0)
        return torch.where(take_random.unsqueeze(-1), random_action, action)

    def _explore_one_row(self, action: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """Eq. 22 for an ``action`` of one row ``[1, A]``, as :meth:`explore_actions` computes it for any rows:
        the same draws in the same order (one uniform, ``A`` uniforms, ``A`` normals) and the same values,
        with a branch on the one row's coin instead of both outcomes computed and ``torch.where`` choosing.

        The per-episode loop acts on one row 5,000 times an iteration; this takes about half the tensor
        operations (``python benchmarks/agent_update.py`` prints the time of both). The coin is compared
        with ``random_eps`` rounded to float32, as ``tensor < random_eps`` compares.
        """
        coin = torch.rand(1, generator=generator, device=action.device)
        uniform = torch.rand((1, self.action_dim), generator=generator)  # what random_action(1) draws
        normal = torch.randn(action.shape, generator=generator, device=action.device)
        if self._random_eps32[0] != self.random_eps:  # random_eps is a public setting: follow a change
            self._random_eps32 = (self.random_eps, float(torch.tensor(self.random_eps, dtype=torch.float32)))
        if float(coin) < self._random_eps32[1]:
            return uniform.mul_(2.0).sub_(1.0)
        return action.add_(normal.mul_(self.noise_std)).clamp_(-1.0, 1.0)

    def random_action(self, batch_size: int | Sequence[int], generator: torch.Generator) -> torch.Tensor:
        """Uniform random actions ``[*batch_size, action_dim]`` in [−1, 1) (warm-up, ε-exploration)."""
        lead = (batch_size,) if isinstance(batch_size, numbers.Integral) else tuple(batch_size)
        return torch.rand((*lead, self.action_dim), generator=generator).mul_(2.0).sub_(1.0)

    def policy(
        self, explore: bool = False, *, random: bool = False, generator: torch.Generator | None = None
    ) -> TensorDictModule:
        """A TorchRL policy for ``env.rollout``: reads ``observation`` and ``desired_goal``, writes ``action``.

        Args:
            explore: act with eq. 22's exploration (see :meth:`act`).
            random: ignore the actor and act uniformly at random (the warm-up).
            generator: the source of the random draws; required when ``explore`` or ``random``.

        Returns:
            a :class:`~tensordict.nn.TensorDictModule` calling :meth:`act` (or :meth:`random_action`).
        """
        if (explore or random) and generator is None:
            raise ValueError("policy(explore=True) and policy(random=True) need a torch.Generator: pass generator=...")
        return TensorDictModule(
            _AgentPolicy(self, explore=explore, random=random, generator=generator),
            in_keys=["observation", "desired_goal"],
            out_keys=["action"],
        )

    @torch.inference_mode()
    def _value(self, observation: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
        value = self.critic(observation, goal, self.actor(observation, goal)).squeeze(-1)
        return value.clamp_(*self.loss_module.return_range)

    def value(self, observation: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
        """``V(s‖g) = Q(s‖g, π(s‖g))`` clipped to ``[−1/(1−γ), 0]``, computed under inference mode.

        Args:
            observation: ``[B, obs_dim]``.
            goal: ``[B, goal_dim]``.

        Returns:
            float32 ``[B]`` (an ordinary tensor: it may be modified in place).
        """
        self._check_inputs(observation, goal)
        return self._value(observation, goal).clone()

    # -- learning -------------------------------------------------------------------------------

    def update_normalizer(self, observation: torch.Tensor, goal: torch.Tensor) -> None:
        """Add data to the running statistics of the networks' input normalisers.

        Args:
            observation: observations ``[..., obs_dim]`` (e.g. a rollout's, ``[N, T, obs_dim]``).
            goal: goals ``[..., goal_dim]`` (e.g. the relabelled goals); its leading shape may differ.
        """
        self.observation_normalizer.update(observation)
        self.goal_normalizer.update(goal)

    @torch.no_grad()
    def clipped_fraction(self, observation: torch.Tensor, goal: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Fractions of the normalised observation and goal entries at the normalisers' clip (±clip).

        A large fraction means the statistics do not cover the data the networks train on (e.g. an
        object far outside the positions the normaliser has seen).

        Returns:
            two float32 scalar tensors, observation then goal.
        """
        return tuple(
            (norm(x).abs() >= norm.clip).float().mean()
            for norm, x in ((self.observation_normalizer, observation), (self.goal_normalizer, goal))
        )

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        """One gradient step of the actor and the critic on ``batch``; the target networks move every
        ``target_update_every``-th call.

        Args:
            batch: ``[B]`` TensorDict with ``observation``, ``desired_goal``, ``action``,
                ``("next", "observation")`` and ``("next", "reward")`` (``[B, 1]``).

        Returns:
            ``{"loss_actor", "loss_value", "pred_value", "target_value"}`` as floats (the last two
            are batch means of ``Q(s‖g, a)`` and of the critic target).

        Raises:
            FloatingPointError: a loss is NaN or inf; no parameter is changed.
        """
        with products_in(self.precision), flush_subnormals(self.subnormals == "flush"):
            return self._update(batch)

    def _update(self, batch: TensorDictBase) -> dict[str, float]:
        inputs = self.loss_module.inputs(batch)
        losses = self.loss_module.losses if self._fused is None else self._fused.forward
        loss_actor, loss_value, pred_value, target_value = losses(*inputs)
        values = torch.stack([loss_actor.detach(), loss_value.detach(), pred_value.mean(), target_value.mean()])
        values = values.tolist()
        if not all(math.isfinite(v) for v in values[:2]):
            raise FloatingPointError(
                f"DDPG update {self.num_updates + 1}: loss_actor={values[0]}, loss_value={values[1]} is not "
                "finite; check the batch for NaN/inf (observations, goals, rewards) and the learning rates"
            )
        if self._fused is not None:
            self._fused.backward()  # replaces every .grad
        else:
            self.actor_optimizer.zero_grad(set_to_none=True)
            self.critic_optimizer.zero_grad(set_to_none=True)
            # the actor loss sees the critic's weights detached and the critic loss does not involve
            # the online actor: one backward gives each network its own gradient
            (loss_actor + loss_value).backward()
        adam_step(self.actor_optimizer)  # = optimizer.step(), bit for bit, without its per-call bookkeeping
        adam_step(self.critic_optimizer)
        self.num_updates += 1
        if self.num_updates % self.target_update_every == 0:
            self.loss_module.update_targets(self.polyak)
        return dict(zip(("loss_actor", "loss_value", "pred_value", "target_value"), values, strict=True))

    # -- checkpointing --------------------------------------------------------------------------

    def policy_state(self) -> dict[str, Any]:
        """What acting needs, and nothing else: the sizes and the online actor's weights and
        normalisers (a copy). :func:`load_policy` turns it back into an actor."""
        hparams = {k: self.hparams[k]
                   for k in ("obs_dim", "goal_dim", "action_dim", "hidden", "norm_std_min", "norm_clip")}
        return {"hparams": hparams, "actor": {k: v.detach().clone() for k, v in self.actor.state_dict().items()}}

    def state_dict(self) -> dict[str, Any]:
        """Everything an exact resume needs: networks, target networks, normalisers, optimisers and
        the update counter. Like :meth:`torch.nn.Module.state_dict`, tensors are references: copy
        (or ``torch.save``) before training on."""
        return {
            "hparams": dict(self.hparams),
            "networks": self.loss_module.state_dict(),
            "actor_optimizer": self.actor_optimizer.state_dict(),
            "critic_optimizer": self.critic_optimizer.state_dict(),
            "num_updates": self.num_updates,
        }

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """Restore a :meth:`state_dict` (in place).

        Raises:
            KeyError: an entry is missing.
            ValueError: the state was saved by an agent with different sizes or hyperparameters.
        """
        missing = {"hparams", "networks", "actor_optimizer", "critic_optimizer", "num_updates"} - set(state_dict)
        if missing:
            raise KeyError(f"agent state_dict is missing {sorted(missing)}; was it written by DDPGAgent.state_dict()?")
        saved = dict(state_dict["hparams"])
        saved["hidden"] = tuple(saved["hidden"])
        differing = {k: (saved.get(k), v) for k, v in self.hparams.items() if saved.get(k) != v}
        if differing:
            details = ", ".join(f"{k}: saved {s!r}, this agent {c!r}" for k, (s, c) in differing.items())
            raise ValueError(f"agent state_dict was saved with different settings ({details})")
        self.loss_module.load_state_dict(state_dict["networks"])
        self.actor_optimizer.load_state_dict(state_dict["actor_optimizer"])
        self.critic_optimizer.load_state_dict(state_dict["critic_optimizer"])
        self.num_updates = int(state_dict["num_updates"])

    # -- helpers --------------------------------------------------------------------------------

    def _check_inputs(self, observation: torch.Tensor, goal: torch.Tensor) -> None:
        if observation.shape[-1:] != (self.obs_dim,) or goal.shape[-1:] != (self.goal_dim,):
            raise ValueError(
                f"expected observation [..., {self.obs_dim}] and goal [..., {self.goal_dim}], "
                f"got {tuple(observation.shape)} and {tuple(goal.shape)}"
            )
        if observation.shape[:-1] != goal.shape[:-1]:
            raise ValueError(
                f"observation and goal must share their leading shape, got {tuple(observation.shape)} "
                f"and {tuple(goal.shape)}"
            )


class SmallBatchActor:
    """The actor's forward for batches below :data:`~gchgg.fast.linear.MIN_BATCH` rows, without ``nn.Module`` calls.

    The same operations on the same tensors as :class:`GoalConditionedActor` (the normalisers' clipped
    standardisation, ``F.linear`` — what its layers compute on such batches — ReLU, tanh), so the same
    actions bit for bit, at about half the cost per call; the standardisation runs once on the
    observation and goal joined (their statistics joined once per change), the same elementwise
    subtraction, division and clip as each normaliser's. The per-episode loop acts on one
    observation 5,000 times an iteration (``benchmarks/agent_update.py`` prints both). It holds the
    actor's parameters and statistics themselves, which optimisers and ``load_state_dict`` change in
    place.
    """

    def __init__(self, actor: GoalConditionedActor) -> None:
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


def load_policy(state: dict[str, Any], matmul: str = "auto") -> GoalConditionedActor:
    """The deterministic actor ``actor(observation, goal) -> action`` of a :meth:`DDPGAgent.policy_state`
    (normalisation included), in eval mode; ``matmul`` as for :class:`DDPGAgent`.

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
    module = use_onednn(actor.module, matmul)
    module.load_state_dict(state["actor"])
    return module.eval()


class _AgentPolicy(nn.Module):
    """``(observation, goal) -> action`` through :meth:`DDPGAgent.act` (or random), for TensorDictModule."""

    def __init__(self, agent: DDPGAgent, explore: bool, random: bool, generator: torch.Generator | None) -> None:
        super().__init__()
        self.__dict__["agent"] = agent  # not a submodule: the agent owns its networks
        self.explore, self.random, self.generator = explore, random, generator

    def forward(self, observation: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
        if self.random:
            return self.agent.random_action(observation.shape[:-1], self.generator)
        return self.agent.act(observation, goal, explore=self.explore, generator=self.generator)
