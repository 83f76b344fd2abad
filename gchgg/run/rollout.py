"""Batched episodes: collect one episode per simulation of a batched env, and evaluate a policy on target goals."""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol, runtime_checkable

import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase

ActFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


@runtime_checkable
class RollsOutTensorPolicy(Protocol):
    """An env that runs a plain-tensor policy's episodes itself (e.g. :class:`envs.torchrl_env.KukaEnv`):
    ``rollout_with(act, steps, start)`` returns what ``env.rollout`` returns for the policy that writes
    ``action = act(observation, desired_goal)``, without a TensorDict per step."""

    def rollout_with(self, act: ActFn, steps: int, start: TensorDictBase) -> TensorDictBase: ...


def collect(env: EnvBase, act: ActFn, steps: int, start: TensorDictBase) -> TensorDictBase:
    """One whole episode in every simulation of ``env``, from the reset TensorDict ``start``.

    Args:
        env: a batched env (``batch_size=[N]``) whose observation keys include ``observation`` and
            ``desired_goal``.
        act: ``act(observation [N, obs_dim], goal [N, 3]) -> action [N, A]``, called once per step
            for all N simulations.
        steps: episode length T.
        start: the TensorDict returned by ``env.reset(...)``.

    Returns:
        The rollout TensorDict ``[N, T]`` (time last), with ``action`` and the ``next`` entries: that of
        ``env.rollout``, which computes it unless the env's class is a :class:`RollsOutTensorPolicy`
        (checked on the class, so that a wrapper forwarding attributes to its base env, such as
        ``TransformedEnv``, still steps through its transforms).
    """
    if issubclass(type(env), RollsOutTensorPolicy):
        return env.rollout_with(act, steps, start)

    def policy(td: TensorDictBase) -> TensorDictBase:
        return td.set("action", act(td.get("observation"), td.get("desired_goal")))

    return env.rollout(steps, policy, tensordict=start, auto_reset=False, break_when_any_done=False)


def fraction(mask: torch.Tensor, dim: int | None = None) -> float | list[float]:
    """The fraction of True entries of a boolean ``mask`` (over ``dim`` if given), as the exact
    ratio of counts: 90 of 100 is 0.9, which a float32 mean would make 0.8999999762 (< 0.9)."""
    if dim is None:
        return int(mask.sum()) / mask.numel()
    return [int(count) / mask.shape[dim] for count in mask.sum(dim).reshape(-1)]


def evaluate(env: EnvBase, act: ActFn, steps: int) -> float:
    """Success rate of ``act`` over one episode per simulation of ``env``, on the task's own goals.

    Success is ``is_success`` at the last step (the original evaluation).
    """
    with torch.inference_mode():
        rollout = collect(env, act, steps, env.reset())
    return fraction(rollout["next", "is_success"][:, -1])
