"""argen: simulated AR capture of labelled RGB-D data for 6-DoF pose estimation."""

__version__ = "0.1.0"
