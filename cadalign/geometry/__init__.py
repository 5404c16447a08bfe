"""Numerically hardened geometry core (numpy/scipy only).

Rotations (quaternion, axis-angle, 6D, Euler at I/O), SE(3)/Sim(3) helpers,
Umeyama/Kabsch alignment, pinhole cameras, plane fits and 2D polygons. Every
estimate that is undefined for its input raises
:class:`~cadalign.errors.DegenerateGeometryError` instead of returning garbage.

Importing this package never imports torch: the differentiable batched
versions live in :mod:`cadalign.geometry.torch_rotations`, imported explicitly.
"""

from cadalign.geometry.camera import (
    backproject,
    decompose_intrinsics,
    depth_to_points,
    focal_to_fov,
    fov_to_focal,
    intrinsics,
    pixel_rays,
    project,
    project_jacobian,
    recover_focal_shift,
)
from cadalign.geometry.euler import euler_to_matrix, matrix_to_euler
from cadalign.geometry.plane import Plane, fit_plane, lift_from_plane_2d, plane_basis, project_to_plane_2d
from cadalign.geometry.polygon import convex_hull_2d, fan_triangulate, polygon_area, triangulate_convex_polygon
from cadalign.geometry.rotations import (
    axis_angle_to_matrix,
    geodesic_angle,
    is_rotation,
    matrix_to_axis_angle,
    matrix_to_quaternion,
    matrix_to_rotation_6d,
    orthonormalize,
    quaternion_angle,
    quaternion_canonicalize,
    quaternion_multiply,
    quaternion_normalize,
    quaternion_to_matrix,
    random_rotation,
    rotation_6d_to_matrix,
    skew,
)
from cadalign.geometry.transforms import compose, invert, relative_pose_error, sim3_from_matrix, transform_points
from cadalign.geometry.umeyama import kabsch, umeyama

__all__ = [
    "Plane",
    "axis_angle_to_matrix",
    "backproject",
    "compose",
    "convex_hull_2d",
    "decompose_intrinsics",
    "depth_to_points",
    "euler_to_matrix",
    "fan_triangulate",
    "fit_plane",
    "focal_to_fov",
    "fov_to_focal",
    "geodesic_angle",
    "intrinsics",
    "invert",
    "is_rotation",
    "kabsch",
    "lift_from_plane_2d",
    "matrix_to_axis_angle",
    "matrix_to_euler",
    "matrix_to_quaternion",
    "matrix_to_rotation_6d",
    "orthonormalize",
    "pixel_rays",
    "plane_basis",
    "polygon_area",
    "project",
    "project_jacobian",
    "project_to_plane_2d",
    "quaternion_angle",
    "quaternion_canonicalize",
    "quaternion_multiply",
    "quaternion_normalize",
    "quaternion_to_matrix",
    "random_rotation",
    "recover_focal_shift",
    "relative_pose_error",
    "rotation_6d_to_matrix",
    "sim3_from_matrix",
    "skew",
    "transform_points",
    "triangulate_convex_polygon",
    "umeyama",
]
