"""detector: 6-DoF object poses from depth. The default model has two stages (:mod:`detector.two_stage`): stage 1,
the paper's PointNet++ (:mod:`detector.stage1`), finds the objects and their centres; stage 2, a crop network
(:mod:`detector.stage2`), their poses. The paper's single multi-task PointNet++ (stage 1's network trained on all its
heads) is the alternative. docs/architecture.md draws the tree."""

__version__ = "0.1.0"
