"""Stage 1 (and the paper's single-shot network): PointNet++ with per-point class and control-point votes."""
