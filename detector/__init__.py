"""detector: 6-DoF object poses from depth. The default model has two stages (:mod:`detector.two_stage`): the paper's
PointNet++ finds the objects and their centres, a crop network (:mod:`detector.cropnet`) their poses; the paper's
single multi-task PointNet++ (:mod:`detector.model`) is the alternative."""

__version__ = "0.1.0"
