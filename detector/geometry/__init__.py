"""Geometry of poses, numpy only: vote clustering, Kabsch (and RANSAC over it), ICP and the fit measures,
the Detection / ObjectInfo types and GeometryConfig."""
