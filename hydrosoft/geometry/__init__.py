"""Geometry: batched SE(3) poses, signed distance functions and rigid-object surface discretizations."""
from hydrosoft.geometry import se3, sdf, surface

__all__ = ["se3", "sdf", "surface"]
