"""Geometry layer: landmarks on the affine Grassmannian, rigid transforms and distances."""

from graffmatch.geometry.landmarks import (
    Landmark,
    LandmarkSet,
    LandmarkType,
    fit_landmark,
    plane_basis,
)
from graffmatch.geometry.transforms import (
    invert,
    make_transform,
    random_transform,
    rotation_error_deg,
    transform_errors,
    transform_points,
)

__all__ = [
    "Landmark",
    "LandmarkSet",
    "LandmarkType",
    "fit_landmark",
    "invert",
    "make_transform",
    "plane_basis",
    "random_transform",
    "rotation_error_deg",
    "transform_errors",
    "transform_points",
]
