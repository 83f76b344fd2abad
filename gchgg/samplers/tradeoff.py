"""Trade-off schedules λ between diversity and proximity: fixed, CHER's (eq. 4), GC-HGG's adaptive (eq. 20).

A schedule is a small object the training loop updates (``update(...)``) and a sampler reads
(``value``) at every draw; its ``state_dict`` round-trips through checkpoints. Samplers take a
schedule or a plain float (a :class:`FixedTradeoff`), see :func:`as_tradeoff`.
"""

from __future__ import annotations

import math
from typing import Any, Protocol, runtime_checkable

import torch

from gchgg.common.validation import check_number

__all__ = ["AdaptiveTradeoff", "ExponentialTradeoff", "FixedTradeoff", "Tradeoff", "as_tradeoff"]


def _number(name: str, value: Any, *, low: float | None = None, strict: bool = False) -> float:
    return float(check_number(name, value, low=low, low_open=strict))


@runtime_checkable
class Tradeoff(Protocol):
    """What a sampler reads (``value``) and what a training loop calls on a schedule.

    A loop calls ``begin_iteration`` once per iteration, before its first episode, with the
    per-episode distances between intermediate and target goals (``None`` when the episodes are
    collected for the targets themselves), and ``after_episodes`` after each chunk of episodes has
    been stored and trained on; the schedule decides what, if anything, changes. ``update`` sets λ
    from one distance directly (for use outside such a loop).
    """

    @property
    def value(self) -> float: ...

    def update(self, distance: float | None = None) -> float: ...

    def begin_iteration(self, iteration: int, distances: torch.Tensor | None = None) -> float: ...

    def after_episodes(self, episodes: int) -> float: ...

    def state_dict(self) -> dict[str, Any]: ...

    def load_state_dict(self, state_dict: dict[str, Any]) -> None: ...


class FixedTradeoff:
    """A constant λ (≥ 0); ``update`` changes nothing.

    >>> FixedTradeoff(2.0).update(distance=0.3)
    2.0
    """

    def __init__(self, value: float = 1.0) -> None:
        self._value = _number("tradeoff", value, low=0.0)

    @property
    def value(self) -> float:
        return self._value

    def update(self, distance: float | None = None) -> float:
        return self._value

    def begin_iteration(self, iteration: int, distances: torch.Tensor | None = None) -> float:
        return self._value

    def after_episodes(self, episodes: int) -> float:
        return self._value

    def state_dict(self) -> dict[str, Any]:
        return {"value": self._value}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self._value = _number("tradeoff", state_dict["value"], low=0.0)

    def __repr__(self) -> str:
        return f"FixedTradeoff({self._value})"


class ExponentialTradeoff:
    """CHER's schedule λ_k = (1 + τ)^k · λ_0 (eq. 4): k counts the calls to ``update``.

    The caller decides what a step is: GC-HGG's CHER runs step once per iteration with τ = 0.005
    (:meth:`begin_iteration` sets k to the iteration, so iteration 0 uses λ_0); CHER's own code
    stepped once per sampled batch with τ = 1e-4.

    Args:
        lambda_0: λ before the first update (≥ 0). Default 1.
        tau: growth rate per update (> −1). Default 0.005.

    >>> schedule = ExponentialTradeoff(lambda_0=1.0, tau=0.5)
    >>> [schedule.update() for _ in range(3)]
    [1.5, 2.25, 3.375]
    """

    def __init__(self, lambda_0: float = 1.0, tau: float = 0.005) -> None:
        self.lambda_0 = _number("lambda_0", lambda_0, low=0.0)
        self.tau = _number("tau", tau, low=-1.0, strict=True)
        self.step = 0

    @property
    def value(self) -> float:
        return self.lambda_0 * (1.0 + self.tau) ** self.step

    def update(self, distance: float | None = None) -> float:
        self.step += 1
        return self.value

    def begin_iteration(self, iteration: int, distances: torch.Tensor | None = None) -> float:
        """λ of iteration ``iteration`` (counted from 0): λ_0 · (1 + τ)^iteration."""
        self.step = int(iteration)
        return self.value

    def after_episodes(self, episodes: int) -> float:
        return self.value

    def state_dict(self) -> dict[str, Any]:
        return {"lambda_0": self.lambda_0, "tau": self.tau, "step": self.step}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.lambda_0 = _number("lambda_0", state_dict["lambda_0"], low=0.0)
        self.tau = _number("tau", state_dict["tau"], low=-1.0, strict=True)
        self.step = int(state_dict["step"])

    def __repr__(self) -> str:
        return f"ExponentialTradeoff(lambda_0={self.lambda_0}, tau={self.tau}, step={self.step})"


class AdaptiveTradeoff:
    """GC-HGG's λ = η · exp(−D / σ²) (eq. 20), D the distance between intermediate and target goals.

    D is the graph-based Wasserstein distance D_G(T, T*) of eq. 21, which the goal generator
    estimates as the mean matched distance of the iteration. A large D (intermediate goals far from
    the targets) gives λ ≈ 0: pure diversity; as D shrinks λ grows towards η: proximity.

    Without a goal generator (no HGG: episodes collected for their own goals) nothing ever calls
    :meth:`update` with a distance, and λ stays at ``initial`` (0: pure diversity) for the whole run.
    There, pick :class:`FixedTradeoff` (a constant λ; with ``scale="standardized"`` in the curriculum
    sampler λ = 1 weighs the two terms equally) or :class:`ExponentialTradeoff` (CHER's eq. 4: λ
    grows from λ_0 by (1 + τ) per ``update()``, e.g. once per iteration: diversity first, proximity
    later), or call ``update(distance=D)`` yourself with your own measure of how far the goals
    trained on are from the goals that matter.

    When D is read (``update_every``):

    * ``"iteration"`` (the paper): :meth:`begin_iteration` sets λ once per iteration from the mean
      of the iteration's intermediate-to-target distances, D_G;
    * ``"episode"`` (the authors' code): after each chunk of an iteration, λ = η·exp(−(S_i/N)/σ²)
      with S_i the *running sum* of the distances of the i episodes collected so far and N the
      iteration's episodes, so λ starts an iteration near η and falls to η·exp(−D_G/σ²) by its end.

    An iteration whose episodes go to the targets themselves (``distances=None``: the first
    iteration, or after HGG's stop) sets λ = 0.

    Args:
        eta: η ≥ 0. Default 1000.
        sigma: σ > 0 in metres. Default 0.3.
        initial: λ before the first update. Default 0, as in the original code (which updates λ only
            after the first iteration, where the intermediate goals are the targets themselves).
        update_every: ``"iteration"`` (default) or ``"episode"``, see above.

    >>> schedule = AdaptiveTradeoff(eta=1000.0, sigma=0.3)
    >>> schedule.value, round(schedule.update(distance=0.3), 2), round(schedule.update(distance=0.0), 2)
    (0.0, 35.67, 1000.0)
    >>> per_episode = AdaptiveTradeoff(eta=1000.0, sigma=0.3, update_every="episode")
    >>> per_episode.begin_iteration(1, torch.tensor([0.3, 0.3]))  # unchanged until episodes are done
    0.0
    >>> round(per_episode.after_episodes(1), 2), round(per_episode.after_episodes(2), 2)
    (188.88, 35.67)
    """

    UPDATE_EVERY = ("iteration", "episode")

    def __init__(
        self, eta: float = 1000.0, sigma: float = 0.3, initial: float = 0.0, update_every: str = "iteration"
    ) -> None:
        self.eta = _number("eta", eta, low=0.0)
        self.sigma = _number("sigma", sigma, low=0.0, strict=True)
        self._value = _number("initial", initial, low=0.0)
        if update_every not in self.UPDATE_EVERY:
            raise ValueError(f"tradeoff.update_every must be one of {self.UPDATE_EVERY}, got {update_every!r}")
        self.update_every = update_every
        self.distance: float | None = None
        self._episode_distances: torch.Tensor | None = None  # this iteration's, in episode mode

    @property
    def value(self) -> float:
        return self._value

    def update(self, distance: float | None = None) -> float:
        """Sets λ from the latest distance D (metres, ≥ 0; ``inf`` gives λ = 0) and returns it."""
        if distance is None:
            raise ValueError("AdaptiveTradeoff.update needs distance=D, the mean intermediate-to-target goal distance")
        distance = float(distance)
        if math.isnan(distance) or distance < 0:
            raise ValueError(f"distance must be >= 0 metres (inf allowed), got {distance!r}")
        self.distance = distance
        self._value = self.eta * math.exp(-distance / self.sigma**2)  # eq. 20
        return self._value

    def begin_iteration(self, iteration: int, distances: torch.Tensor | None = None) -> float:
        """Starts an iteration whose episodes have these intermediate-to-target ``distances`` ``[N]``
        (``None``: the episodes go to the targets; λ = 0)."""
        if distances is None:
            self._episode_distances = None
            return self.update(math.inf)
        distances = torch.as_tensor(distances, dtype=torch.float64).reshape(-1)
        if len(distances) == 0 or bool(torch.isnan(distances).any()) or bool((distances < 0).any()):
            raise ValueError(f"distances must be a non-empty tensor of metres >= 0, got {distances!r}")
        if self.update_every == "iteration":
            return self.update(float(distances.mean()))  # D_G of eq. 21
        self._episode_distances = distances
        return self._value

    def after_episodes(self, episodes: int) -> float:
        """In ``"episode"`` mode: λ from the running sum of the first ``episodes`` episodes' distances."""
        if self.update_every == "episode" and self._episode_distances is not None:
            d = self._episode_distances
            return self.update(float(d[: int(episodes)].sum()) / len(d))
        return self._value

    def state_dict(self) -> dict[str, Any]:
        return {
            "eta": self.eta,
            "sigma": self.sigma,
            "value": self._value,
            "distance": self.distance,
            "update_every": self.update_every,
        }

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.eta = _number("eta", state_dict["eta"], low=0.0)
        self.sigma = _number("sigma", state_dict["sigma"], low=0.0, strict=True)
        self._value = _number("value", state_dict["value"], low=0.0)
        distance = state_dict.get("distance")
        self.distance = None if distance is None else float(distance)
        self.update_every = state_dict.get("update_every", self.update_every)
        self._episode_distances = None  # state is saved between iterations

    def __repr__(self) -> str:
        return (
            f"AdaptiveTradeoff(eta={self.eta}, sigma={self.sigma}, value={self._value:g}, "
            f"update_every={self.update_every!r})"
        )


def as_tradeoff(tradeoff: Tradeoff | float) -> Tradeoff:
    """A schedule as is; a number as a :class:`FixedTradeoff`."""
    if isinstance(tradeoff, (int, float)) and not isinstance(tradeoff, bool):
        return FixedTradeoff(tradeoff)
    if isinstance(tradeoff, Tradeoff):
        return tradeoff
    raise TypeError(
        f"tradeoff must be a number >= 0 or a schedule with value/update/begin_iteration/after_episodes/"
        f"state_dict/load_state_dict "
        f"(FixedTradeoff, ExponentialTradeoff, AdaptiveTradeoff), got {tradeoff!r}"
    )
