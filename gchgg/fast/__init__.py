"""Speed devices: each gives the plain path's numbers (up to rounding, said in its test) behind one seam.

- :mod:`~gchgg.fast.linear`: matrix products on oneDNN, in float32 or bfloat16 (``matmul``, ``precision``);
- :mod:`~gchgg.fast.fused_update`: the DDPG update differentiated by hand, eager or compiled (``gradients``);
- :mod:`~gchgg.fast.subnormal`: the update's subnormal floats flushed to zero (``subnormals``);
- :mod:`~gchgg.fast.adam_step`: Adam's fused step without ``torch.optim``'s bookkeeping;
- :mod:`~gchgg.fast.small_batch`: the actor's forward and eq. 22 on the rollout's one-row steps, without modules;
- :mod:`~gchgg.fast.candidates`: Alg. 1's candidates drawn ahead and scored from per-row caches (``fast``,
  ``draw_ahead``, ``on_write`` of the curriculum sampler), with :mod:`~gchgg.fast.rows` (the caches);
- :mod:`~gchgg.fast.nearest`: F_div's nearest-neighbour search through a Euclidean shortlist
  (:mod:`~gchgg.fast.shortlist`);
- :mod:`~gchgg.fast.storage`: a replay storage that reads a sampled batch field by field.

A run's ``plain=true`` (the agent's, the samplers' and the replay buffer's ``fast=False``) calls none of them.
Nothing here imports the algorithm (:mod:`gchgg.ddpg`, :mod:`gchgg.samplers`, ...): the algorithm
imports the device, and a test holds the two equal.
"""
