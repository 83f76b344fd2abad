"""The DDPG learner: acting with eq. 22's exploration, the optimisers, the update and its state.

:class:`DDPGAgent` puts together the networks (:mod:`gchgg.ddpg.networks`) and the loss
(:mod:`gchgg.ddpg.loss`) with the reference implementation's training defaults (``REFERENCE.md``,
"Training"; :class:`~gchgg.ddpg.loss.DDPGConfig`):

- exploration (eq. 22, :meth:`DDPGAgent.explore_actions`): with probability 0.3 a uniform random action,
  otherwise ``π + N(0, 0.2²)``, clipped to [−1, 1]; every draw comes from a ``torch.Generator`` the caller
  passes in;
- both losses computed from the same parameters and both networks stepped together (Adam, 1e-3);
- target networks ``θ' ← 0.95·θ' + 0.05·θ`` once every 20 updates;
- the value function HGG needs, ``V(s‖g) = clip(Q(s‖g, π(s‖g)), −1/(1−γ), 0)``, and a complete ``state_dict``.

Its :meth:`DDPGAgent.update` reads the batch's tensors once and runs the loss's tensor path, differentiated
by autograd or by hand with the same result bit for bit (:mod:`gchgg.fast.fused_update`, the default;
``benchmarks/agent_update.py`` times both). The other speed devices change speed, not the math: ``matmul``
picks who computes the wide layers' products (:mod:`gchgg.fast.linear`: oneDNN where measured faster), so
does ``subnormals`` (:mod:`gchgg.fast.subnormal`), so does stepping the fused Adam optimisers through
:func:`gchgg.fast.adam_step.adam_step`, and so do the rollout's one-row paths
(:mod:`gchgg.fast.small_batch`). ``fast=False`` (a run's ``plain=true``) is the plain path: none of them is
called, the settings take their :data:`PLAIN` values, and the agent is the networks, the loss, eq. 22 and
``torch.optim.Adam`` alone, with the same numbers (``tests/test_plain.py``).

An agent, one update and its value:

    >>> from tensordict import TensorDict
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

The networks' and the loss's names are importable from here too (``gchgg.ddpg.agent.DDPGConfig``): older
code, and checkpoints pickled as ``gchgg.agent.*``, name them so.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable, Sequence
from dataclasses import asdict, fields, replace
from functools import partial
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn

from gchgg.common.validation import check_choice
from gchgg.ddpg.loss import DDPGConfig, HindsightDDPGLoss
from gchgg.ddpg.networks import (
    GoalConditionedActor,
    GoalConditionedCritic,
    RunningNormalizer,
    load_policy,
    make_ddpg_networks,
)
from gchgg.fast.adam_step import adam_step
from gchgg.fast.fused_update import FusedDDPGUpdate, compiler_found, unsupported
from gchgg.fast.linear import (
    MATMUL_BACKENDS,
    PRECISIONS,
    OneDNNLinear,
    products_in,
    resolve_matmul,
    resolve_precision,
    use_onednn,
)
from gchgg.fast.small_batch import OneRowExploration, SmallBatchActor, one_row_policy
from gchgg.fast.subnormal import SUBNORMALS, flush_subnormals

__all__ = [
    "GRADIENTS",
    "PLAIN",
    "DDPGAgent",
    "DDPGConfig",
    "GoalConditionedActor",
    "GoalConditionedCritic",
    "HindsightDDPGLoss",
    "RunningNormalizer",
    "load_policy",
    "make_ddpg_networks",
]


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

PLAIN = {"matmul": "default", "precision": "float32", "gradients": "autograd", "subnormals": "keep"}
"""The settings of the plain path (``fast=False``): torch's matmul in float32, autograd's gradients, IEEE
subnormals. Each setting's ``auto`` resolves to its value here; another value is refused."""


def hand_differentiated(loss: HindsightDDPGLoss, gradients: str, precision: str) -> FusedDDPGUpdate | None:
    """The hand-differentiated update of ``loss`` that the ``gradients`` setting selects (:data:`GRADIENTS`), its
    products in ``precision`` (resolved), or ``None`` for autograd's.

    Raises:
        ValueError: ``gradients`` is not a setting, or ``fused`` / ``compiled`` for networks the fused update
            does not compute (the reason given).
    """
    if gradients not in GRADIENTS:
        raise ValueError(f"gradients must be one of {list(GRADIENTS)}, got {gradients!r}")
    if gradients == "autograd":
        return None
    reason = unsupported(loss)
    if reason is None:
        on_onednn = any(type(layer) is OneDNNLinear for layer in loss.modules())
        compiled = gradients == "compiled" or (
            gradients == "auto" and precision == "bfloat16" and on_onednn and compiler_found()
        )
        return FusedDDPGUpdate(loss, precision=precision, compiled=compiled,
                               fall_back=gradients == "auto")  # fmt: skip
    if gradients in ("fused", "compiled"):
        raise ValueError(f"gradients={gradients!r} differentiates ReLU MLPs of float32 linear layers, but "
                         f"{reason}; use gradients=auto or autograd")
    return None


def plain_settings(matmul: str, precision: str, gradients: str, subnormals: str) -> tuple[str, str, str, str]:
    """The four speed settings on the plain path: each ``auto`` or its :data:`PLAIN` value, which it becomes;
    another value is a ``ValueError`` naming the setting."""
    settings = {"matmul": matmul, "precision": precision, "gradients": gradients, "subnormals": subnormals}
    for (name, value), allowed in zip(settings.items(), (MATMUL_BACKENDS, PRECISIONS, GRADIENTS, SUBNORMALS),
                                      strict=True):
        check_choice(name, value, allowed)
        if value not in ("auto", PLAIN[name]):
            raise ValueError(f"fast=False (the plain path) computes with {name}={PLAIN[name]!r}, "
                             f"got {name}={value!r}; pass {name}='auto' or {PLAIN[name]!r}, or fast=True")
    return tuple(PLAIN.values())


class DDPGAgent:
    """Goal-conditioned DDPG with the reference hyperparameters: act, learn, value, checkpoint.

    Args:
        obs_dim: observation size.
        goal_dim: goal size (3 for every task here).
        action_dim: action size.
        config: the hyperparameters (:class:`DDPGConfig`; default: the original code's).
        generator: draws the initial weights (``None``: torch's global generator).
        matmul: who computes the wide layers' products, one of :data:`gchgg.fast.linear.MATMUL_BACKENDS`
            (``"auto"``: :func:`gchgg.fast.linear.resolve_matmul`'s choice), resolved into :attr:`matmul`, which a
            process acting with this policy passes to :func:`load_policy` to act alike. Speed only: not a
            hyperparameter, not saved; a state loads under any backend.
        precision: the dtype of those products in :meth:`update`, one of :data:`gchgg.fast.linear.PRECISIONS`:
            ``"float32"`` (default: the math as written), ``"bfloat16"`` (oneDNN's native products on CPUs with
            AVX-512 BF16 or AMX) or ``"auto"`` (bfloat16 where native, training's default), resolved into
            :attr:`precision`. It changes the numbers (rounding), so runs record it; acting stays float32.
        gradients: how :meth:`update` gets autograd's gradients, one of :data:`GRADIENTS` (:attr:`gradients`).
        subnormals: ``"flush"``: :meth:`update` flushes subnormal floats to zero, the same networks bit for bit
            (:mod:`gchgg.fast.subnormal`); ``"keep"``: IEEE subnormals; ``"auto"`` (default): ``flush``, or
            ``keep`` with ``fast=False``.
        fast: ``True`` (default): the speed devices (module docstring) where the settings choose them.
            ``False``: the plain path, which calls none (:func:`plain_settings`): the same actions and draws.
        **overrides: fields of :class:`DDPGConfig` to change (``hidden=(32,)``).

    :meth:`update`'s batch: ``observation``, ``desired_goal``, ``action``, ``("next", "observation")``, ``("next",
    "reward") [B, 1]``; other keys are ignored (``done`` too: there is no done mask).
    """

    def __init__(self, obs_dim: int, goal_dim: int, action_dim: int, config: DDPGConfig | None = None, *,
                 generator: torch.Generator | None = None, matmul: str = "auto", precision: str = "float32",
                 gradients: str = "auto", subnormals: str = "auto", fast: bool = True, **overrides: Any) -> None:
        unknown = set(overrides) - {f.name for f in fields(DDPGConfig)}
        if unknown:
            raise TypeError(f"unknown DDPGAgent settings {sorted(unknown)}; the settings are DDPGConfig's fields")
        config = replace(config or DDPGConfig(), **overrides)
        self.config = config
        self.fast = bool(fast)
        check_choice("subnormals", subnormals, SUBNORMALS)
        if not self.fast:  # the plain path: each setting at its plain value (auto resolves to it)
            matmul, precision, gradients, subnormals = plain_settings(matmul, precision, gradients, subnormals)
        self.subnormals = "flush" if subnormals == "auto" else subnormals
        self.obs_dim, self.goal_dim, self.action_dim = int(obs_dim), int(goal_dim), int(action_dim)
        self.gamma, self.polyak = float(config.gamma), float(config.polyak)
        self.target_update_every = int(config.target_update_every)
        self.random_eps, self.noise_std = float(config.random_eps), float(config.noise_std)
        self.hparams = dict(obs_dim=obs_dim, goal_dim=goal_dim, action_dim=action_dim, **asdict(config))

        actor, critic = make_ddpg_networks(
            obs_dim, goal_dim, action_dim, config.hidden,
            norm_std_min=config.norm_std_min, norm_clip=config.norm_clip, generator=generator,
        )  # fmt: skip
        self.loss_module = HindsightDDPGLoss(
            actor, critic, gamma=config.gamma, action_l2=config.action_l2, clip_return=config.clip_return
        )
        if self.fast:
            self.precision = resolve_precision(precision, matmul)  # "auto" -> what this machine does well
            self.matmul = resolve_matmul(matmul, self.precision)  # the backend the layers got: "onednn" or "default"
            use_onednn(self.loss_module, self.matmul)  # the online and the target networks
        else:  # torch's own layers, float32
            self.precision, self.matmul = precision, matmul
        # fused Adam: one kernel per step (stepped by gchgg.fast.adam_step, or by its own step on the plain path)
        self.actor_optimizer = torch.optim.Adam(self.actor.parameters(), lr=config.actor_lr, fused=True)
        self.critic_optimizer = torch.optim.Adam(self.critic.parameters(), lr=config.critic_lr, fused=True)
        self.observation_normalizer: RunningNormalizer = self.loss_module.actor.observation_normalizer
        self.goal_normalizer: RunningNormalizer = self.loss_module.actor.goal_normalizer
        self._small_batch_actor = self._explore_one_row = self._fused = None  # the plain path's: none
        if self.fast:
            self._small_batch_actor = SmallBatchActor(self.actor)  # act's speed devices on a few rows and on one:
            self._explore_one_row = OneRowExploration(self)  # the actor's forward and eq. 22, same actions and draws
            self._fused = hand_differentiated(self.loss_module, gradients, self.precision)
        self.num_updates = 0

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
    def act(self, observation: torch.Tensor, goal: torch.Tensor, explore: bool = False,
            generator: torch.Generator | None = None) -> torch.Tensor:
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
        _check_inputs(observation, goal, self.obs_dim, self.goal_dim)
        small = self._small_batch_actor
        if small is not None and small.takes(observation, goal):
            action = small(observation, goal)
        else:
            action = self.actor(observation, goal)
        if not explore:
            return action
        if generator is None:
            raise ValueError("act(explore=True) needs a torch.Generator: pass generator=...")
        if self._explore_one_row is not None and action.shape[:-1] == (1,):  # the per-episode loop's one row:
            return self._explore_one_row(action, generator)  # the speed device beside eq. 22
        return self.explore_actions(action, generator)

    def rollout_policy(self, generator: torch.Generator) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
        """``act(observation, goal, explore=True, generator=generator)`` for the steps of one rollout: the same
        actions and the same draws, call for call.

        The per-episode loop acts on one row 5,000 times an iteration; this reaches the one-row speed devices
        without ``act``'s per-call checks (:func:`gchgg.fast.small_batch.one_row_policy`; ``python
        benchmarks/iteration.py`` prints the rollout both ways); on the plain path (``fast=False``) it is that ``act``.
        Make one per rollout, as the trainer does per chunk.
        """
        if generator is None:
            raise ValueError("rollout_policy needs a torch.Generator for eq. 22's draws: pass generator=...")
        general = partial(self.act, explore=True, generator=generator)
        if not self.fast:
            return general
        return one_row_policy(self._small_batch_actor, self._explore_one_row, general, generator,
                              self.obs_dim, self.goal_dim)  # fmt: skip

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

    def random_action(self, batch_size: int | Sequence[int], generator: torch.Generator) -> torch.Tensor:
        """Uniform random actions ``[*batch_size, action_dim]`` in [−1, 1) (warm-up, ε-exploration)."""
        lead = (batch_size,) if isinstance(batch_size, numbers.Integral) else tuple(batch_size)
        return torch.rand((*lead, self.action_dim), generator=generator).mul_(2.0).sub_(1.0)

    def policy(self, explore: bool = False, *, random: bool = False,
               generator: torch.Generator | None = None) -> TensorDictModule:
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

    def value(self, observation: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
        """``V(s‖g) = Q(s‖g, π(s‖g))`` clipped to ``[−1/(1−γ), 0]``, computed under inference mode.

        Args:
            observation: ``[B, obs_dim]``.
            goal: ``[B, goal_dim]``.

        Returns:
            float32 ``[B]`` (an ordinary tensor: it may be modified in place).
        """
        _check_inputs(observation, goal, self.obs_dim, self.goal_dim)
        with torch.inference_mode():
            value = self.critic(observation, goal, self.actor(observation, goal)).squeeze(-1)
            value = value.clamp_(*self.loss_module.return_range)
        return value.clone()

    # -- learning -------------------------------------------------------------------------------

    def update_normalizer(self, observation: torch.Tensor, goal: torch.Tensor) -> None:
        """Add data to the running statistics of the networks' input normalisers.

        Args:
            observation: observations ``[..., obs_dim]`` (e.g. a rollout's, ``[N, T, obs_dim]``).
            goal: goals ``[..., goal_dim]`` (e.g. the relabelled goals); its leading shape may differ.
        """
        self.observation_normalizer.update(observation)
        self.goal_normalizer.update(goal)

    def clipped_fraction(self, observation: torch.Tensor, goal: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The fractions of the normalised observation's and goal's entries at the normalisers' clip
        (:meth:`~gchgg.ddpg.networks.RunningNormalizer.clipped_fraction`), two float32 scalar tensors."""
        return self.observation_normalizer.clipped_fraction(observation), self.goal_normalizer.clipped_fraction(goal)

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
        if not self.fast:  # the plain path: torch's own products, IEEE subnormals
            return self._update(batch)
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
        if self.fast:
            adam_step(self.actor_optimizer)  # = optimizer.step(), bit for bit, without its per-call bookkeeping
            adam_step(self.critic_optimizer)
        else:
            self.actor_optimizer.step()
            self.critic_optimizer.step()
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
        saved = {**state_dict["hparams"], "hidden": tuple(state_dict["hparams"]["hidden"])}
        if differing := [f"{k}: saved {saved.get(k)!r}, this agent {v!r}"
                         for k, v in self.hparams.items() if saved.get(k) != v]:
            raise ValueError(f"agent state_dict was saved with different settings ({', '.join(differing)})")
        self.loss_module.load_state_dict(state_dict["networks"])
        self.actor_optimizer.load_state_dict(state_dict["actor_optimizer"])
        self.critic_optimizer.load_state_dict(state_dict["critic_optimizer"])
        self.num_updates = int(state_dict["num_updates"])


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


def _check_inputs(observation: torch.Tensor, goal: torch.Tensor, obs_dim: int, goal_dim: int) -> None:
    """A ``ValueError`` unless ``observation [..., obs_dim]`` and ``goal [..., goal_dim]`` share their leading shape."""
    if observation.shape[-1:] != (obs_dim,) or goal.shape[-1:] != (goal_dim,):
        raise ValueError(
            f"expected observation [..., {obs_dim}] and goal [..., {goal_dim}], "
            f"got {tuple(observation.shape)} and {tuple(goal.shape)}"
        )
    if observation.shape[:-1] != goal.shape[:-1]:
        raise ValueError(
            f"observation and goal must share their leading shape, got {tuple(observation.shape)} "
            f"and {tuple(goal.shape)}"
        )
