"""Hindsight experience replay as a TorchRL transform: k relabelled copies of every step (Alg. 2, lines 15–18).

:class:`HindsightRelabel` turns complete episodes ``[..., T]`` into the transitions a replay buffer
stores: for every step the original transition plus ``k`` copies whose goal is an achieved goal of
the same episode, with the reward recomputed by the task's pure reward function. Each goal has one
name: ``desired_goal`` is the goal a transition trains on (relabelled in the copies),
``episode_goal`` the goal the episode was collected for (under HGG an intermediate goal), and
``task_goal`` the target task's goal T* the episode serves (eq. 15's g*: the episode's own goal
unless the episode carries another under ``task_goal``, as HGG's episodes do).

Stored layout (the training loop and the samplers rely on it)::

    rollout [N, T] ──HindsightRelabel(k)──► transitions [N·(k+1)·T]   (flatten=True, the default)
    row r = (n·(k+1) + c)·T + t :  episode n, copy c (c = 0 the original, 1..k relabelled), step t

    e.g. N = 2, k = 4, T = 100: rows 0–99 are episode 0 as collected, rows 100–499 its four
    relabelled copies, rows 500–999 episode 1 in the same order.

Keys of one stored transition (push_new: obs_dim 25, action 3; 283 bytes with ``energy``, as
``benchmarks/samplers.py`` prints): ``observation``, ``action``, ``desired_goal`` (goal to train
on), ``episode_goal`` (goal the episode was collected for), ``task_goal`` (the target task's goal
T*), ``achieved_goal``, ``energy`` (if :class:`~gchgg.transforms.EpisodeEnergy` ran first), and
under ``next``: ``observation``, ``achieved_goal``, ``reward``, ``done``, ``terminated``,
``truncated``. Dropped by default (:data:`DEFAULT_DROP_KEYS`): ``("next", "desired_goal")`` (it
equals ``desired_goal``; :class:`GoalToNext` puts it back at sample time for free), ``is_success``
(valid for the collected goal only), the root ``done``/``terminated``/``truncated`` copies and
``object_position`` (the KUKA envs' reset input, the object's start).
"""

from __future__ import annotations

import enum
from collections.abc import Callable, Sequence

import torch
from tensordict import NestedKey, TensorDictBase
from torchrl.envs.transforms import Transform

from gchgg.common.validation import check_number
from gchgg.transforms._mask import DEFAULT_MASK_KEY, episode_lengths

__all__ = ["DEFAULT_DROP_KEYS", "GoalToNext", "HerStrategy", "HindsightRelabel"]

DEFAULT_DROP_KEYS: tuple[NestedKey, ...] = (
    ("next", "desired_goal"),
    "is_success",
    ("next", "is_success"),
    "done",
    "terminated",
    "truncated",
    "object_position",  # a reset input of the KUKA envs (the object's start), constant over an episode
)


class HerStrategy(str, enum.Enum):  # noqa: UP042 -- StrEnum would change str()/format() of a public enum
    """Where a relabelled goal comes from (HER, Andrychowicz et al. 2017).

    With ``ag_t`` the achieved goal *before* step ``t`` (so ``("next", "achieved_goal")`` at step
    ``u`` is ``ag_{u+1}``), the goal of a copy of step ``t`` of an episode of ``T`` steps is

    * ``FUTURE``: ``ag_{t'}`` with ``t'`` uniform in ``{t+1, …, T}``, i.e. the next achieved goal of
      a step ``u`` uniform in ``{t, …, T−1}``: the Fetch HER convention, so the last step's copies
      all use the final achieved goal and every copy can be rewarded by its own transition;
    * ``FINAL``: ``ag_T``, the achieved goal after the last step (all ``k`` copies are equal);
    * ``EPISODE``: ``ag_{t'}`` with ``t'`` uniform in ``{1, …, T}``.
    """

    FUTURE = "future"
    FINAL = "final"
    EPISODE = "episode"


class HindsightRelabel(Transform):
    """Relabels complete episodes with hindsight goals and flattens them into transitions.

    Use it as a collector ``postproc`` or call it on a rollout before ``buffer.extend``; it is not an
    env transform and not a buffer transform (its ``forward`` relabels). The input's last batch
    dimension is time and must hold whole episodes (``T`` steps each). Goals may have any
    dimension d ≥ 1 (``goal_key`` and ``("next", achieved_goal_key)`` ``[..., T, d]``, the same d).

    Variable-length episodes: pad them to ``[N, Tmax]`` with TorchRL's ``split_trajectories``, which
    marks the real steps in a boolean mask (``("collector", "mask")`` for a collector's batch, the
    default ``mask_key``; name another with ``mask_key=``). Episode n of length L_n then draws its
    hindsight goals from its own valid steps only (``future``: ``t' ∈ (t, L_n]``; ``final``:
    ``ag_{L_n}``; ``episode``: ``t' ∈ [1, L_n]``) and only its ``(k+1)·L_n`` real rows are returned
    (``flatten=True``; row order as below with the padded steps left out). Without a mask every step
    counts as real: a padded batch whose mask is missing or under another key is relabelled with the
    padding's goals.

    Args:
        reward_fn: pure batched reward ``reward_fn(achieved_goal [..., d], goal [..., d]) -> [...]``
            (eq. 23 for the KUKA tasks). It is evaluated on ``("next", achieved_goal_key)`` and the
            transition's goal, for the original transitions too, so every stored reward comes from it.
        k: relabelled copies per step (≥ 0); HER's "future, k = 4" keeps 1/5 original transitions.
        strategy: a :class:`HerStrategy` or its name (``"future"``, ``"final"``, ``"episode"``).

    Keyword Args:
        generator: ``torch.Generator`` for the goal draws (CPU); by default a fresh, randomly
            seeded one. Pass one for reproducible relabelling.
        goal_key: key of the goal the policy is conditioned on. Default ``"desired_goal"``.
        achieved_goal_key: key of the achieved goal (the hindsight goals' source). Default ``"achieved_goal"``.
        reward_achieved_goal_key: key of the achieved goal the rewards are computed from; by default
            ``achieved_goal_key``. With observation noise, the true achieved goal
            (``"true_achieved_goal"``, see :class:`~gchgg.transforms.ObservationNoise`) keeps rewards true
            to physics while the hindsight goals are the observed positions.
        episode_goal_key: key written with the goal the episode was collected for (the episode's
            ``goal_key`` before relabelling). Default ``"episode_goal"``.
        task_goal_key: key of the target task's goal T*: read from the episode where it has one (HGG
            collects an episode for an intermediate goal and names its target task's goal here), else
            the episode's goal (HER: episodes are collected for their task's goal); written in every
            transition. Default ``"task_goal"``.
        reward_key: reward entry to overwrite (same shape and dtype). Default ``("next", "reward")``.
        drop_keys: entries not stored (missing ones are ignored). Default :data:`DEFAULT_DROP_KEYS`.
        flatten: ``True`` (default) returns ``[N·(k+1)·T]`` transitions for a ``[N, T]`` input (any
            leading batch shape is flattened); ``False`` returns ``[..., k+1, T]`` (not for padded
            episodes: it cannot leave out their padded rows).
        mask_key: boolean valid-step mask ``[..., T]`` of padded episodes, used when the input has it
            (valid steps first in each episode); ``None`` ignores any mask. Default
            ``("collector", "mask")``. It is not stored.

    Returns (of ``forward``):
        A new TensorDict; the input is not modified.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> def reward(achieved, goal):  # eq. 23
        ...     return torch.where(torch.linalg.vector_norm(achieved - goal, dim=-1) > 0.05, -1.0, 0.0)
        >>> T = 4
        >>> x = torch.tensor([0.0, 0.125, 0.25, 0.375, 0.5])
        >>> path = torch.stack([x, torch.zeros(5), torch.zeros(5)], -1)  # ag_0 .. ag_4 of one episode
        >>> episode = TensorDict({
        ...     "observation": torch.zeros(1, T, 5), "action": torch.zeros(1, T, 3),
        ...     "achieved_goal": path[None, :-1], "desired_goal": torch.ones(1, T, 3),
        ...     "next": {"observation": torch.zeros(1, T, 5), "achieved_goal": path[None, 1:],
        ...              "reward": -torch.ones(1, T, 1), "done": torch.zeros(1, T, 1, dtype=torch.bool)},
        ... }, batch_size=[1, T])
        >>> her = HindsightRelabel(reward, k=2, strategy="final", generator=torch.Generator().manual_seed(0))
        >>> transitions = her(episode)
        >>> transitions.batch_size  # (k + 1) * T
        torch.Size([12])
        >>> transitions["desired_goal"][:, 0].tolist()  # T originals, then k copies with the final ag_4
        [1.0, 1.0, 1.0, 1.0, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5]
        >>> transitions["next", "reward"].squeeze(-1).tolist()  # 0 where the step reaches its goal
        [-1.0, -1.0, -1.0, -1.0, -1.0, -1.0, -1.0, 0.0, -1.0, -1.0, -1.0, 0.0]
        >>> bool((transitions["episode_goal"] == 1).all() and (transitions["task_goal"] == 1).all())
        True
    """

    def __init__(
        self,
        reward_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
        k: int = 4,
        strategy: HerStrategy | str = HerStrategy.FUTURE,
        *,
        generator: torch.Generator | None = None,
        goal_key: NestedKey = "desired_goal",
        achieved_goal_key: NestedKey = "achieved_goal",
        reward_achieved_goal_key: NestedKey | None = None,
        episode_goal_key: NestedKey = "episode_goal",
        task_goal_key: NestedKey = "task_goal",
        reward_key: NestedKey = ("next", "reward"),
        drop_keys: Sequence[NestedKey] = DEFAULT_DROP_KEYS,
        flatten: bool = True,
        mask_key: NestedKey | None = DEFAULT_MASK_KEY,
    ) -> None:
        super().__init__(in_keys=[], out_keys=[])
        if not callable(reward_fn):
            raise TypeError(f"reward_fn must be a callable (achieved_goal, goal) -> reward, got {reward_fn!r}")
        check_number("k (relabelled copies per step)", k, integer=True, low=0)
        try:
            self.strategy = HerStrategy(strategy)
        except ValueError:
            allowed = ", ".join(repr(s.value) for s in HerStrategy)
            raise ValueError(f"strategy must be one of {allowed}, got {strategy!r}") from None
        self.reward_fn = reward_fn
        self.k = k
        if generator is None:
            generator = torch.Generator()
            generator.seed()
        self.generator = generator
        self.goal_key = goal_key
        self.achieved_goal_key = achieved_goal_key
        self.reward_achieved_goal_key = (
            achieved_goal_key if reward_achieved_goal_key is None else reward_achieved_goal_key
        )
        self.episode_goal_key = episode_goal_key
        self.task_goal_key = task_goal_key
        self.reward_key = reward_key
        self.drop_keys = tuple(drop_keys)
        self.flatten = bool(flatten)
        self.mask_key = mask_key

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if tensordict.batch_dims < 1 or tensordict.shape[-1] < 1:
            raise ValueError(
                f"HindsightRelabel needs episodes with time as the last batch dimension ([..., T], T >= 1), "
                f"got batch_size={tuple(tensordict.shape)}"
            )
        batch, steps = tensordict.shape[:-1], tensordict.shape[-1]
        copies = self.k + 1
        next_key = self._next(self.achieved_goal_key)
        reward_from = self._next(self.reward_achieved_goal_key)
        for key in (self.goal_key, next_key, reward_from, self.reward_key):
            if key not in tensordict.keys(include_nested=True):
                raise KeyError(
                    f"HindsightRelabel reads {key!r} from the episode, which has keys "
                    f"{sorted(map(str, tensordict.keys(include_nested=True, leaves_only=True)))}"
                )
        goal = tensordict.get(self.goal_key)  # [*batch, T, d]
        achieved_next = tensordict.get(next_key)  # [*batch, T, d]: ag_1 .. ag_T
        for key, value in ((self.goal_key, goal), (next_key, achieved_next)):
            if value.ndim != tensordict.batch_dims + 1 or value.shape[-1] < 1 or value.shape[-1] != goal.shape[-1]:
                raise ValueError(
                    f"HindsightRelabel needs goals of one dimension d >= 1 per step: {key!r} must have shape "
                    f"[..., T, d] = {(*tensordict.shape, goal.shape[-1] if goal.ndim > tensordict.batch_dims else 'd')}"
                    f" like {self.goal_key!r}, got {tuple(value.shape)}"
                )
        lengths = episode_lengths(tensordict, self.mask_key, "HindsightRelabel")
        if lengths is not None and not self.flatten:
            raise ValueError(
                f"HindsightRelabel(flatten=False) cannot leave out padded rows, and the input has a valid-step mask "
                f"{self.mask_key!r}: use flatten=True (only real rows are returned), or mask_key=None to keep them"
            )

        # Copy c of step t takes the next achieved goal of step source[..., c - 1, t].
        source = self._hindsight_steps(batch, steps, lengths).to(achieved_next.device)  # [*batch, k, T]
        hindsight = torch.gather(
            achieved_next.unsqueeze(-3).expand(*batch, self.k, steps, achieved_next.shape[-1]),
            -2,
            source.unsqueeze(-1).expand(*batch, self.k, steps, achieved_next.shape[-1]),
        )
        goals = torch.cat([goal.unsqueeze(-3), hindsight.to(goal.dtype)], dim=-3)  # [*batch, k+1, T, 3]

        old_reward = tensordict.get(self.reward_key)
        reward_achieved = achieved_next if reward_from == next_key else tensordict.get(reward_from)
        reward = torch.as_tensor(self.reward_fn(reward_achieved.unsqueeze(-3), goals))
        tail = old_reward.shape[len(batch) + 1 :]
        expected = (*batch, copies, steps)
        if reward.shape not in (torch.Size(expected), torch.Size((*expected, *tail))):
            raise ValueError(
                f"reward_fn must map goals [..., 3] to rewards [...]: for goals of shape {tuple(goals.shape)} "
                f"it returned shape {tuple(reward.shape)}"
            )
        reward = reward.reshape(*expected, *tail).to(old_reward.dtype)

        drop = self.drop_keys if lengths is None else (*self.drop_keys, self.mask_key)
        out = tensordict.exclude(*drop).unsqueeze(len(batch)).expand(*batch, copies, steps)
        out.set(self.goal_key, goals)
        episode_goal = goal.unsqueeze(-3).expand(*batch, copies, steps, goal.shape[-1])
        out.set(self.episode_goal_key, episode_goal)
        if self.task_goal_key not in out.keys(include_nested=True):  # HER: the episode's goal is its task's
            out.set(self.task_goal_key, episode_goal)
        out.set(self.reward_key, reward)
        if self._next(self.goal_key) in out.keys(include_nested=True):
            out.set(self._next(self.goal_key), goals)
        if lengths is not None:  # the real rows only, in row order (n, c, t)
            valid = torch.arange(steps, device=lengths.device) < lengths.unsqueeze(-1)  # [*batch, T]
            return out[valid.unsqueeze(-2).expand(*batch, copies, steps)]
        if self.flatten:
            return out.reshape(-1)  # materialises every entry once, in row order (n, c, t)
        return out.clone()

    def _hindsight_steps(self, batch: torch.Size, steps: int, lengths: torch.Tensor | None = None) -> torch.Tensor:
        """Index ``u`` in ``[0, T)`` of the step whose *next* achieved goal each copy uses; with episode
        ``lengths`` ``[*batch]`` (padded episodes), in ``[0, L)`` of each episode (padded steps' copies: any)."""
        shape = (*batch, self.k, steps)
        if lengths is None:
            last = steps - 1
        else:  # [*batch, 1, 1]; an empty episode (L = 0) has no rows to fill
            last = (lengths - 1).clamp(min=0).view(*batch, 1, 1).cpu()
        if self.strategy is HerStrategy.FINAL:
            return torch.full(shape, steps - 1, dtype=torch.long) if lengths is None else last.expand(shape).clone()
        uniform = torch.rand(shape, generator=self.generator, device=self.generator.device)
        length = steps if lengths is None else last + 1
        if self.strategy is HerStrategy.EPISODE:
            return torch.minimum((uniform * length).long(), torch.as_tensor(last)).clamp_(min=0)
        # FUTURE: u = t + floor(U · (T − t)) is uniform in {t, …, T − 1};
        # e.g. T = 100, t = 97: U < 1/3 → 97, U < 2/3 → 98, else 99.
        t = torch.arange(steps, device=uniform.device)
        if lengths is None:
            return (t + (uniform * (steps - t)).long()).clamp_(max=steps - 1)
        return torch.minimum(t + (uniform * (length - t)).long(), last).clamp_(min=0)

    @staticmethod
    def _next(key: NestedKey) -> tuple:
        return ("next", *key) if isinstance(key, tuple) else ("next", key)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        raise RuntimeError(
            "HindsightRelabel works on whole episodes: use it as a collector postproc or call it on a "
            "rollout before buffer.extend, not inside a TransformedEnv"
        )

    def __repr__(self) -> str:
        return f"{type(self).__name__}(k={self.k}, strategy={self.strategy.value!r})"


class GoalToNext(Transform):
    """Replay-buffer transform that restores ``("next", goal)`` from ``goal`` at sample time.

    :class:`HindsightRelabel` does not store ``("next", "desired_goal")`` (it equals
    ``desired_goal``); TorchRL losses read the next state's goal there. Setting it shares the
    tensor, so it costs no copy.

    Args:
        goal_keys: the goal entries to mirror under ``"next"``. Default ``("desired_goal",)``.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> batch = GoalToNext()(TensorDict({"desired_goal": torch.ones(2, 3), "next": {}}, [2]))
        >>> batch["next", "desired_goal"].shape
        torch.Size([2, 3])
    """

    def __init__(self, goal_keys: Sequence[NestedKey] = ("desired_goal",)) -> None:
        super().__init__(in_keys=list(goal_keys), out_keys=[HindsightRelabel._next(k) for k in goal_keys])

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        for key, next_key in zip(self.in_keys, self.out_keys, strict=True):
            tensordict.set(next_key, tensordict.get(key))
        return tensordict

    _call = forward
