"""TensorDict transforms for goal-conditioned replay: HER relabelling, EBP episode energy, next-goal sharing,
observation noise."""

from gchgg.transforms.energy import EpisodeEnergy, trajectory_energy
from gchgg.transforms.her import DEFAULT_DROP_KEYS, GoalToNext, HerStrategy, HindsightRelabel
from gchgg.transforms.noise import ObservationNoise

__all__ = [
    "DEFAULT_DROP_KEYS",
    "EpisodeEnergy",
    "GoalToNext",
    "HerStrategy",
    "HindsightRelabel",
    "ObservationNoise",
    "trajectory_energy",
]
