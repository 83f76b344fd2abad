"""Run machinery: settings, the parts built from them, checkpoints, forks, evaluation, metrics, trackers, replay files.

It wires the algorithm (the package's top level) into :mod:`gchgg.train`'s Algorithm 2 loop and keeps
a run's record; nothing in the algorithm imports it.
"""
