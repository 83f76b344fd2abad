"""Goal-conditioned DDPG, the learner of HER, HGG, G-HGG, CHER and GC-HGG: networks, the loss and the agent."""

from gchgg.ddpg.agent import (
    DDPGAgent,
    DDPGConfig,
    GoalConditionedActor,
    GoalConditionedCritic,
    HindsightDDPGLoss,
    RunningNormalizer,
    load_policy,
    make_ddpg_networks,
)

__all__ = ["DDPGAgent", "DDPGConfig", "GoalConditionedActor", "GoalConditionedCritic", "HindsightDDPGLoss",
           "RunningNormalizer", "load_policy", "make_ddpg_networks"]
