"""Per-model geometry the pose refinement and the overlay need, computed once per CAD model.

Camera frame x right, y down, z forward; pixel centres at integer + 0.5 (:mod:`cadalign.types`), so a
camera point projects to ``u = fx x / z + cx`` in those pixel-edge coordinates; OpenCV's rasteriser puts
centres at integers, hence the ``- 0.5`` before handing points to ``cv2``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
import trimesh
from scipy.spatial import cKDTree

from cadalign.cad.model import CadModel
from cadalign.geometry.camera import project_points
from cadalign.types import Rigid3

__all__ = ["ModelGeometry", "contour_points", "draw_wireframe", "project_points", "render_depth", "render_silhouette"]

_CV_SHIFT = 4  # fixed-point bits for cv2.fillPoly / cv2.polylines (1/16 px)


@dataclass(frozen=True, eq=False)
class ModelGeometry:
    """Edges with their two faces, feature edges for drawing, and surface samples with normals (metres).

    Attributes:
        vertices: (V, 3) model-frame vertices.
        faces: (F, 3) triangles.
        face_normals: (F, 3) unit outward normals.
        edges: (E, 2) vertex indices of every unique edge.
        edge_faces: (E, 2) the faces sharing each edge; -1 for an open (boundary) edge.
        feature_edges: (G, 2) edges with a dihedral angle above 30 degrees or open ones (the wireframe).
        samples: (S, 3) points sampled evenly on the surface; ``sample_normals`` (S, 3) their normals.
        diameter_m: the model's diameter.
    """

    vertices: np.ndarray
    faces: np.ndarray
    face_normals: np.ndarray
    edges: np.ndarray
    edge_faces: np.ndarray
    feature_edges: np.ndarray
    samples: np.ndarray
    sample_normals: np.ndarray
    diameter_m: float
    tree: cKDTree
    _scene: list = field(default_factory=list, repr=False)

    def raycaster(self):  # -> open3d.t.geometry.RaycastingScene, built on first use
        if not self._scene:
            import open3d as o3d  # lazy: heavy dependency (open3d)

            mesh = o3d.t.geometry.TriangleMesh()
            mesh.vertex.positions = o3d.core.Tensor(self.vertices.astype(np.float32))
            mesh.triangle.indices = o3d.core.Tensor(self.faces.astype(np.int32))
            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(mesh)
            self._scene.append(scene)
        return self._scene[0]

    @staticmethod
    def from_cad(model: CadModel, n_samples: int = 3000, seed: int = 0) -> ModelGeometry:
        mesh = trimesh.Trimesh(model.vertices_m, model.faces, process=False)
        fn = np.asarray(mesh.face_normals, dtype=np.float64)
        e_sorted = np.sort(np.asarray(mesh.edges, dtype=np.int64), axis=1)
        uniq, inv = np.unique(e_sorted, axis=0, return_inverse=True)
        inv = inv.ravel()
        face_of_edge = np.asarray(mesh.edges_face, dtype=np.int64)
        edge_faces = np.full((len(uniq), 2), -1, dtype=np.int64)
        order = np.argsort(inv, kind="stable")
        first = np.ones(len(order), dtype=bool)
        first[1:] = inv[order][1:] != inv[order][:-1]
        edge_faces[inv[order][first], 0] = face_of_edge[order][first]
        second = ~first  # non-manifold edges keep only their second face; good enough for contours
        edge_faces[inv[order][second], 1] = face_of_edge[order][second]
        both = edge_faces[:, 1] >= 0
        cos_dihedral = np.ones(len(uniq))
        cos_dihedral[both] = np.einsum("ij,ij->i", fn[edge_faces[both, 0]], fn[edge_faces[both, 1]])
        feature = (~both) | (cos_dihedral < np.cos(np.radians(30.0)))
        pts, fidx = trimesh.sample.sample_surface(mesh, n_samples, seed=seed)
        pts = np.asarray(pts, dtype=np.float64)
        return ModelGeometry(np.asarray(model.vertices_m, float), np.asarray(model.faces), fn, uniq, edge_faces,
                             uniq[feature], pts, fn[fidx], float(model.diameter_m), cKDTree(pts))


def render_silhouette(geom: ModelGeometry, T_cam_from_obj: Rigid3, K: np.ndarray, shape: tuple[int, int],
                      offset: tuple[int, int] = (0, 0)) -> np.ndarray:
    """(H, W) bool silhouette of the model, in a window whose top-left pixel is ``offset`` = (x0, y0).

    Exact: one ray through each pixel centre, cast against the model (Open3D, one thread), the same rule as
    the ground-truth masks of :mod:`cadalign.raycast.core`.
    """
    return np.isfinite(render_depth(geom, T_cam_from_obj, K, shape, offset))


def render_depth(geom: ModelGeometry, T_cam_from_obj: Rigid3, K: np.ndarray, shape: tuple[int, int],
                 offset: tuple[int, int] = (0, 0)) -> np.ndarray:
    """(H, W) camera z (metres) of the model's nearest surface through each pixel centre of a window whose
    top-left pixel is ``offset`` = (x0, y0); ``inf`` where the ray misses the model (ray cast as
    :func:`render_silhouette`)."""
    import open3d as o3d  # lazy: heavy dependency (open3d)

    H, W = shape
    u = np.arange(W) + 0.5 + offset[0]
    v = np.arange(H) + 0.5 + offset[1]
    uu, vv = np.meshgrid((u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1])
    d_cam = np.stack([uu, vv, np.ones_like(uu)], -1).reshape(-1, 3)
    R_obj_from_cam = T_cam_from_obj.R.T
    origin = -R_obj_from_cam @ T_cam_from_obj.t
    rays = np.concatenate([np.broadcast_to(origin, d_cam.shape), d_cam @ R_obj_from_cam.T], axis=1)
    hit = geom.raycaster().cast_rays(o3d.core.Tensor(rays.astype(np.float32)), nthreads=1)["t_hit"].numpy()
    # the ray direction has camera z = 1, so the hit distance in its units is the camera depth
    return hit.astype(np.float64).reshape(H, W)


def contour_points(geom: ModelGeometry, T_cam_from_obj: Rigid3, K: np.ndarray, spacing_px: float = 2.0,
                   max_points: int = 600, rng: np.random.Generator | None = None) -> np.ndarray:
    """Model-frame points (N, 3) on the occluding contour: edges between a front- and a back-facing face.

    Open edges count when their face is seen. Points are spread along each edge every ``spacing_px``
    pixels of its projection, then evenly thinned to ``max_points``. Hidden contour edges (inside the
    silhouette) are included; :func:`cadalign.infer.refine.refine_silhouette` drops them.
    """
    R, t = T_cam_from_obj.R, T_cam_from_obj.t
    centroids = geom.vertices[geom.faces].mean(axis=1) @ R.T + t
    front = np.einsum("ij,ij->i", geom.face_normals @ R.T, centroids) < 0
    f0, f1 = geom.edge_faces[:, 0], geom.edge_faces[:, 1]
    open_edge = f1 < 0
    sil = np.where(open_edge, front[f0], front[f0] != front[np.maximum(f1, 0)])
    e = geom.edges[sil]
    if len(e) == 0:
        return np.zeros((0, 3))
    a, b = geom.vertices[e[:, 0]], geom.vertices[e[:, 1]]
    ac, bc = a @ R.T + t, b @ R.T + t
    keep = (ac[:, 2] > 0.01) & (bc[:, 2] > 0.01)
    a, b, ac, bc = a[keep], b[keep], ac[keep], bc[keep]
    length_px = np.linalg.norm(project_points(K, ac) - project_points(K, bc), axis=1)
    n = np.clip(np.ceil(length_px / spacing_px), 1, 200).astype(int)
    idx = np.repeat(np.arange(len(a)), n)
    frac = (np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n) + 0.5) / np.repeat(n, n)
    pts = a[idx] + frac[:, None] * (b[idx] - a[idx])
    if len(pts) > max_points:
        pick = np.linspace(0, len(pts) - 1, max_points).astype(int) if rng is None else \
            np.sort(rng.choice(len(pts), max_points, replace=False))
        pts = pts[pick]
    return pts


def draw_wireframe(image: np.ndarray, geom: ModelGeometry, T_cam_from_obj: Rigid3, K: np.ndarray,
                   color: tuple[int, int, int], thickness: int = 1) -> None:
    """Draw the model's feature edges at a pose onto an RGB uint8 image in place."""

    e = geom.feature_edges
    Xc = T_cam_from_obj.apply(geom.vertices)
    keep = (Xc[e[:, 0], 2] > 0.01) & (Xc[e[:, 1], 2] > 0.01)
    if not keep.any():
        return
    uv = project_points(K, np.where(Xc[:, 2:3] > 0.01, Xc, 1.0)) - 0.5
    uv = np.clip(uv, -8 * max(image.shape), 8 * max(image.shape))
    lines = np.round(uv[e[keep]] * (1 << _CV_SHIFT)).astype(np.int32)
    cv2.polylines(image, list(lines), False, color, thickness, cv2.LINE_AA, _CV_SHIFT)
