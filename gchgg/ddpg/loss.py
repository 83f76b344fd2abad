"""The DDPG loss of HER and HGG, written once, and the learner's hyperparameters (:class:`DDPGConfig`).

For a batch of transitions ``(s, g, a, r, s')``, the goal ``g`` that of both ``s`` and ``s'`` (relabelled by
HER), :class:`HindsightDDPGLoss` computes::

    y          = r + γ·clip(Q'(s'‖g, π'(s'‖g)), −1/(1−γ), 0)      critic_target; no done mask (tasks only time out)
    loss_value = mean((Q(s‖g, a) − y)²)                          critic_objective
    loss_actor = −mean Q(s‖g, π(s‖g)) + action_l2·mean(π(s‖g)²)  actor_objective; the critic's weights constant
    θ'         ← polyak·θ' + (1 − polyak)·θ                       update_targets (the agent: every 20th update)

This is CleanRL's DDPG update (``ddpg_continuous_action.py``) with the original HER code's two additions: the
bootstrapped value clipped to the range of returns, and the action penalty. The networks are built in
:mod:`gchgg.ddpg.networks`; the optimisers, the target schedule and exploration are
:class:`gchgg.ddpg.agent.DDPGAgent`'s. Autograd differentiates this module. The hand-differentiated update
(:class:`gchgg.fast.fused_update.FusedDDPGUpdate`, the default) calls the same three formulas and writes out
only their derivatives; ``tests/test_fused_update.py`` holds its losses and gradients equal to autograd's on
this module, bit for bit.

:class:`DDPGConfig`, every hyperparameter of the learner, sits here beside the loss that reads most of them
(and :func:`check_gamma`, the discount's one rule).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn

from gchgg.common.validation import check_number
from gchgg.ddpg.networks import check_hidden

__all__ = ["DDPGConfig", "HindsightDDPGLoss", "check_gamma", "return_range"]


def check_gamma(gamma: Any, name: str = "gamma") -> float:
    """The discount's one rule: ``gamma`` if it is a number in (0, 1), else a ``ValueError`` naming ``name``
    (at 1 the range of returns, ``−1/(1−γ)``, is unbounded)."""
    return check_number(name, gamma, low=0, high=1, low_open=True, high_open=True)


def return_range(gamma: float) -> tuple[float, float]:
    """``(−1/(1−γ), 0)``: the range of discounted returns with rewards in {−1, 0}."""
    return -1.0 / (1.0 - gamma), 0.0


@dataclass(frozen=True)
class DDPGConfig:
    """The learner's hyperparameters, each declared once, here (defaults: the original code's, REFERENCE.md).

    The ``agent`` section of a run's config (:class:`gchgg.run.config.AgentConfig`, with these defaults) sets
    them by name (``agent.actor_lr=5e-4``); a :class:`~gchgg.ddpg.agent.DDPGAgent` logs them in ``hparams``
    and refuses a state saved with others.

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
        object.__setattr__(self, "hidden", check_hidden(self.hidden))
        for name in ("actor_lr", "critic_lr", "norm_std_min", "norm_clip"):
            check_number(name, getattr(self, name), low=0, low_open=True)
        check_gamma(self.gamma)
        check_number("polyak", self.polyak, low=0, high=1)
        check_number("target_update_every", self.target_update_every, integer=True, low=1)
        check_number("action_l2", self.action_l2, low=0)
        check_number("random_eps", self.random_eps, low=0, high=1)
        check_number("noise_std", self.noise_std, low=0)


class HindsightDDPGLoss(nn.Module):
    """The HER / HGG DDPG losses and target networks, as a plain :class:`torch.nn.Module`.

    - critic: ``mean((Q(s‖g, a) − y)²)`` with ``y = r + γ·clip(Q'(s'‖g, π'(s'‖g)), −1/(1−γ), 0)``
      (:meth:`critic_objective`, :meth:`critic_target`). There is no done mask (goal-conditioned episodes
      only time out, so every next state is bootstrapped) and the next state's goal is the transition's
      own goal (as written by the HER relabel transform); no ``("next", goal)`` entry is read.
    - actor: ``−mean Q(s‖g, π(s‖g)) + action_l2·mean(π²)`` (:meth:`actor_objective`); the critic's weights
      get no gradient from it, so one ``backward`` of the sum gives each network its own gradient.
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
        actor_network: deterministic actor from :func:`~gchgg.ddpg.networks.make_ddpg_networks`: it reads
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
        >>> from gchgg.ddpg.networks import make_ddpg_networks
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
        check_gamma(gamma)
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
        return return_range(self.gamma)

    # -- the three formulas, on tensors (the fused update calls them too) ---------------------

    @staticmethod
    def critic_target(reward: torch.Tensor, next_value: torch.Tensor, gamma: float, clip_return: bool) -> torch.Tensor:
        """``y = r + γ·Q'`` from ``next_value = Q'(s'‖g, π'(s'‖g))``, ``Q'`` clipped to ``[−1/(1−γ), 0]`` with
        ``clip_return``; no done mask."""
        if clip_return:
            next_value = next_value.clamp(*return_range(gamma))
        return reward + gamma * next_value

    @staticmethod
    def critic_objective(pred_value: torch.Tensor, target_value: torch.Tensor) -> torch.Tensor:
        """``mean((Q(s‖g, a) − y)²)``."""
        return (pred_value - target_value).square().mean()

    @staticmethod
    def actor_objective(policy_value: torch.Tensor, policy_action: torch.Tensor, action_l2: float) -> torch.Tensor:
        """``−mean Q(s‖g, π(s‖g)) + action_l2·mean(π(s‖g)²)`` from ``policy_value = Q(s‖g, π(s‖g))``."""
        loss_actor = -policy_value.mean()
        if action_l2:
            loss_actor = loss_actor + action_l2 * policy_action.square().mean()
        return loss_actor

    # -- the losses of a batch --------------------------------------------------------------

    def losses(
        self,
        observation: torch.Tensor,
        goal: torch.Tensor,
        action: torch.Tensor,
        next_observation: torch.Tensor,
        reward: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The two losses from plain tensors (what :meth:`forward` computes from a batch TensorDict).

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
            target_value = self.critic_target(reward, next_value, self.gamma, self.clip_return)
        pred_value = self.critic(observation, goal, action)
        if pred_value.shape != target_value.shape:
            raise ValueError(
                f"the reward must be [B, 1] like the critic's output {tuple(pred_value.shape)}, "
                f"got {tuple(reward.shape)}"
            )
        return self.critic_objective(pred_value, target_value), pred_value.detach(), target_value

    def actor_loss(self, observation, goal):
        """``−mean Q(s‖g, π(s‖g)) + action_l2·mean(π²)``; no gradient reaches the critic's weights."""
        policy_action = self.actor(observation, goal)
        critic_weights = list(self.critic.parameters())
        for weight in critic_weights:  # recorded as constants: gradient flows to the action only
            weight.requires_grad_(False)
        try:
            policy_value = self.critic(observation, goal, policy_action)
        finally:
            for weight in critic_weights:
                weight.requires_grad_(True)
        return self.actor_objective(policy_value, policy_action, self.action_l2)

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
