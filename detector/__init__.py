"""detector: a multi-task PointNet++ that predicts per-point class, 9 box control points and confidence."""

__version__ = "0.1.0"
