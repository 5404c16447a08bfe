"""Exact per-pixel ground truth (depth, normals, part ids, classes, masks) by ray casting meshes."""

from cadalign.raycast.core import RaycastFrame, RaycastRenderer, RenderMesh, pixel_rays_cam

__all__ = ["RaycastFrame", "RaycastRenderer", "RenderMesh", "pixel_rays_cam"]
