"""gchgg: graph-curriculum-guided hindsight goal generation (GC-HGG) and its baselines as TorchRL parts.

The algorithm is the package's top level: :mod:`gchgg.graph` (d_G), :mod:`gchgg.transforms` (HER,
EBP energy), :mod:`gchgg.samplers` (EBP, Alg. 1, CHER, λ), :mod:`gchgg.hgg` (eqs. 5-7) and
:mod:`gchgg.ddpg` (the learner); :mod:`gchgg.train` is Algorithm 2 and the command line. Below it,
:mod:`gchgg.fast` (speed devices) and :mod:`gchgg.common`; above it, :mod:`gchgg.run` (run machinery)
and :mod:`gchgg.analysis`. ``docs/architecture.md`` draws the layers.
"""

from gchgg.common import moved

moved.install()
