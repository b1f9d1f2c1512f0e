"""``fdnet reproduce``: the paper's experiments, one command, one self-contained HTML report.

:func:`reproduce` runs the chosen experiments (``comparison``, ``lengths``, ``similarity``,
``disentanglement``, ``viewpoint``, ``runtime``, ``examples``; ``ablation`` when named; one module
each) on a dataset and writes ``OUT/report.html`` (:mod:`fdnet.reproduce.report`),
``OUT/<experiment>.json`` and the figures. Descriptors are cached per model and image list
(:mod:`fdnet.reproduce.cache`), so one experiment can be rerun alone, a method added later costs
only that method, and an interrupted run resumes. docs/reproduce.md describes each experiment.
"""

from fdnet.reproduce.context import ReproduceSettings
from fdnet.reproduce.runner import DEFAULT_METHODS, reproduce
from fdnet.reproduce.sections import EXPERIMENTS

__all__ = ["DEFAULT_METHODS", "EXPERIMENTS", "ReproduceSettings", "reproduce"]
