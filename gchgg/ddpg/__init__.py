"""Goal-conditioned DDPG, the learner of HER, HGG, G-HGG, CHER and GC-HGG: networks, the loss and the agent.

- :mod:`~gchgg.ddpg.networks`: the input normaliser, the actor ``π(s‖g)`` and the critic ``Q(s‖g, a)``;
- :mod:`~gchgg.ddpg.loss`: the losses and target networks, written once, and the hyperparameters;
- :mod:`~gchgg.ddpg.agent`: acting (eq. 22), the optimisers, the update and the agent's state.
"""

from gchgg.ddpg.agent import GRADIENTS, DDPGAgent
from gchgg.ddpg.loss import DDPGConfig, HindsightDDPGLoss, check_gamma
from gchgg.ddpg.networks import (
    GoalConditionedActor,
    GoalConditionedCritic,
    RunningNormalizer,
    load_policy,
    make_ddpg_networks,
)

__all__ = ["GRADIENTS", "DDPGAgent", "DDPGConfig", "GoalConditionedActor", "GoalConditionedCritic",
           "HindsightDDPGLoss", "RunningNormalizer", "check_gamma", "load_policy", "make_ddpg_networks"]
