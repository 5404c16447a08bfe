"""Exact per-pixel ground truth by ray casting meshes with Open3D (CPU, no GL).

Used by the simulator (true cameras) and by the dataset builder (SfM cameras, aligned CAD). One ray goes
through each pixel centre, ``K^-1 (u + 0.5, v + 0.5, 1)`` (the convention of :mod:`cadalign.types`).
Ray directions keep camera-frame z = 1, so Open3D's hit parameter ``t`` is the z-depth, not the range;
the Euclidean range is ``t * |d|``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from cadalign.errors import InputError
from cadalign.types import Camera, Rigid3


@dataclass(frozen=True)
class RaycastFrame:
    """Exact per-pixel ground truth of one frame (H×W).

    Attributes:
        depth_m: z-depth in metres, 0 where no surface.
        range_m: Euclidean camera–surface distance, inf where no surface.
        normals_cam: unit surface normals in the camera frame, facing the camera; 0 where no surface.
        rays_cam: unit ray directions in the camera frame.
        instance: the ``RenderMesh.instance`` seen at each pixel; 0 for background geometry and open water.
        class_id: class index per pixel (0 background).
        full_masks: instance id -> (H, W) bool mask of the instance alone (ignoring occluders), for
            instances that project into the image.
    """

    depth_m: np.ndarray
    range_m: np.ndarray
    normals_cam: np.ndarray
    rays_cam: np.ndarray
    instance: np.ndarray
    class_id: np.ndarray
    full_masks: dict[int, np.ndarray]


def pixel_rays_cam(camera: Camera) -> np.ndarray:
    """(H, W, 3) camera-frame ray directions with z = 1 through the pixel centres."""
    u = (np.arange(camera.width) + 0.5 - camera.cx) / camera.fx
    v = (np.arange(camera.height) + 0.5 - camera.cy) / camera.fy
    uu, vv = np.meshgrid(u, v)
    return np.stack([uu, vv, np.ones_like(uu)], axis=-1)


def _o3d_mesh(vertices: np.ndarray, faces: np.ndarray):  # -> o3d.t.geometry.TriangleMesh
    import open3d as o3d  # lazy: heavy dependency (open3d)

    m = o3d.t.geometry.TriangleMesh()
    m.vertex.positions = o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32))
    m.triangle.indices = o3d.core.Tensor(np.ascontiguousarray(faces, dtype=np.int32))
    return m


class MeshQuery:
    """Closest points on, and distances to, a triangle mesh (Open3D ``RaycastingScene``, exact, CPU).

    Open3D works in float32, so coordinates are taken relative to ``origin`` (the vertex mean unless
    given): a structure in UTM-sized coordinates keeps sub-millimetre precision.
    """

    def __init__(self, vertices_m: np.ndarray, faces: np.ndarray, origin: np.ndarray | None = None) -> None:
        import open3d as o3d  # lazy: heavy dependency (open3d)

        vertices_m = np.asarray(vertices_m, dtype=np.float64)
        self.origin = vertices_m.mean(axis=0) if origin is None else np.asarray(origin, dtype=np.float64)
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(_o3d_mesh(vertices_m - self.origin, faces))

    def _query(self, points_m: np.ndarray):  # -> o3d.core.Tensor
        import open3d as o3d  # lazy: heavy dependency (open3d)

        q = (np.asarray(points_m, dtype=np.float64).reshape(-1, 3) - self.origin).astype(np.float32)
        return o3d.core.Tensor(q)

    def distances(self, points_m: np.ndarray) -> np.ndarray:
        """(N,) distance of each point (N, 3) to the triangles, metres."""
        return self._scene.compute_distance(self._query(points_m)).numpy().astype(np.float64)

    def closest_points(self, points_m: np.ndarray) -> np.ndarray:
        """(N, 3) closest point on the triangles to each point (N, 3), metres."""
        got = self._scene.compute_closest_points(self._query(points_m))
        return got["points"].numpy().astype(np.float64) + self.origin


@dataclass(frozen=True)
class RenderMesh:
    """One mesh to ray cast, already in world coordinates.

    Attributes:
        vertices_m: (V, 3) world coordinates, metres.
        faces: (F, 3) vertex indices.
        instance: > 0 for an object instance (its label in ``RaycastFrame.instance``); 0 for background
            geometry such as the seabed, which occludes but gets no mask.
        class_id: class index written to ``RaycastFrame.class_id`` (0 = background).
    """

    vertices_m: np.ndarray
    faces: np.ndarray
    instance: int
    class_id: int


class RaycastRenderer:
    """Exact depth, normals, instance and class maps, and full (unoccluded) masks, by ray casting.

    One ``RaycastingScene`` holds every mesh; each instance also gets a scene of its own for its full
    mask, cast only inside the instance's projected bounding box. A renderer keeps one buffer of rays: give each
    thread its own.
    """

    def __init__(self, meshes: Sequence[RenderMesh], camera: Camera, rays_cam: np.ndarray | None = None) -> None:
        """``rays_cam``: optional (H, W, 3) camera-frame ray directions with z = 1 through the pixel centres,
        for lens models beyond the pinhole ``camera.K`` (e.g. SfM's radial distortion); default: from K."""
        import open3d as o3d  # lazy: heavy dependency (open3d)

        if not meshes:
            raise InputError("nothing to render: the mesh list is empty")
        self.camera = camera
        # Open3D casts in float32: work relative to the scene centre so world coordinates far from the
        # origin (UTM, 5e6 m) keep millimetre precision; ray origins are shifted the same way.
        lo = np.min([np.asarray(m.vertices_m, dtype=np.float64).min(0) for m in meshes], axis=0)
        hi = np.max([np.asarray(m.vertices_m, dtype=np.float64).max(0) for m in meshes], axis=0)
        self._origin = (lo + hi) / 2
        self._all = o3d.t.geometry.RaycastingScene()
        self._single: dict[int, object] = {}
        self._world_bounds: dict[int, np.ndarray] = {}
        gid_to_instance: dict[int, int] = {}
        class_of: dict[int, int] = {0: 0}
        for m in meshes:
            v = np.asarray(m.vertices_m, dtype=np.float64) - self._origin
            gid_to_instance[self._all.add_triangles(_o3d_mesh(v, m.faces))] = m.instance
            if m.instance > 0:
                if m.instance in self._single:
                    raise InputError(f"instance id {m.instance} is used by two meshes; give each its own id")
                alone = o3d.t.geometry.RaycastingScene()
                alone.add_triangles(_o3d_mesh(v, m.faces))
                self._single[m.instance] = alone
                self._world_bounds[m.instance] = np.array([v.min(0), v.max(0)])
                class_of[m.instance] = m.class_id
        self._lut_instance = np.zeros(max(gid_to_instance) + 2, dtype=np.int32)
        for gid, inst in gid_to_instance.items():
            self._lut_instance[gid] = inst
        self._lut_class = np.zeros(max(class_of) + 1, dtype=np.uint8)
        for inst, cid in class_of.items():
            self._lut_class[inst] = cid
        self._dirs_cam = pixel_rays_cam(camera) if rays_cam is None else np.asarray(rays_cam, dtype=np.float64)
        if self._dirs_cam.shape != (camera.height, camera.width, 3):
            raise InputError(f"rays_cam has shape {self._dirs_cam.shape}; expected ({camera.height}, "
                             f"{camera.width}, 3) for this camera")
        # how far (pixels) the lens moves a point from where a pinhole of K puts it: each part's full mask is cast in
        # the pinhole box of its corners widened by this (a pincushion lens puts a part further out)
        self._lens_px = 0 if rays_cam is None else _lens_px(self._dirs_cam, camera)
        self._ray_len = np.linalg.norm(self._dirs_cam, axis=-1).astype(np.float32)
        self._rays_unit = (self._dirs_cam / self._ray_len[..., None]).astype(np.float32)
        self._dirs_cam32 = self._dirs_cam.astype(np.float32)
        self._buffer: np.ndarray | None = None  # the whole frame's rays, made on the first render
        self._rays_unit.flags.writeable = False  # shared by every frame's result

    def _rays(self, T_world_from_cam: Rigid3, rows: slice, cols: slice, out: np.ndarray | None = None) -> np.ndarray:
        """(h, w, 6) float32 origins and directions of the pixels' rays, relative to the scene centre, into ``out``
        (a buffer of that shape) or a new array."""
        d = self._dirs_cam[rows, cols]
        if out is None:
            out = np.empty((*d.shape[:2], 6), dtype=np.float32)
        out[..., :3] = (T_world_from_cam.t - self._origin).astype(np.float32)
        # turned in double precision (cv2's SIMD transform), stored in single as Open3D casts: turned in single, the
        # directions differ in the last bit, which moves edge pixels' hits and the tracker's poses by millimetres
        out[..., 3:] = cv2.transform(np.ascontiguousarray(d), T_world_from_cam.R)
        return out

    def render(self, T_world_from_cam: Rigid3, *, with_full_masks: bool = True,
               with_normals: bool = True) -> RaycastFrame:
        """Ground truth of the view from ``T_world_from_cam`` (camera: x right, y down, z forward).
        ``with_normals``: False leaves ``normals_cam`` all zero (a tracker that reads contours only)."""
        import open3d as o3d  # lazy: heavy dependency (open3d)

        H, W = self.camera.height, self.camera.width
        if self._buffer is None:
            self._buffer = np.empty((H, W, 6), dtype=np.float32)
        # the rays in a buffer kept for every render, which Open3D reads in place (the cast is synchronous)
        rays = self._rays(T_world_from_cam, slice(None), slice(None), self._buffer)
        ans = self._all.cast_rays(o3d.core.Tensor.from_numpy(rays), nthreads=0)
        t = ans["t_hit"].numpy()
        hit = np.isfinite(t)
        depth = np.where(hit, t, np.float32(0.0))
        range_m = t * self._ray_len  # inf where nothing was hit
        # a miss has Open3D's invalid id (the largest uint32): the last LUT slot, which maps to background
        instance = self._lut_instance[np.minimum(ans["geometry_ids"].numpy(), len(self._lut_instance) - 1)]
        if with_normals:
            n_cam = ans["primitive_normals"].numpy() @ T_world_from_cam.R.astype(np.float32)
            # face the camera; zero where nothing was hit (Open3D returns zero normals there already)
            flip = np.where(np.einsum("hwk,hwk->hw", n_cam, self._dirs_cam32) > 0, np.float32(-1), np.float32(1))
            n_cam *= flip[..., None]
            n_cam[~hit] = 0.0
        else:
            n_cam = np.zeros((H, W, 3), dtype=np.float32)
        full = self._full_masks(T_world_from_cam) if with_full_masks else {}
        return RaycastFrame(
            depth,
            range_m,
            n_cam,
            self._rays_unit,
            instance.reshape(H, W),
            self._lut_class[instance].reshape(H, W),
            full,
        )

    def silhouettes(self, views: Sequence[Rigid3], chunk: int = 1000) -> np.ndarray:
        """(V, H * W) bool: which pixels see any mesh from each of ``views`` (``T_world_from_cam``), cast in chunks of
        ``chunk`` views (many low-resolution views in one call: a search over poses)."""
        import open3d as o3d  # lazy: heavy dependency (open3d)

        H, W = self.camera.height, self.camera.width
        HW = H * W
        out = np.zeros((len(views), HW), dtype=bool)
        for a in range(0, len(views), chunk):
            part = views[a:a + chunk]
            rays = np.empty((len(part), H, W, 6), dtype=np.float32)
            for i, T in enumerate(part):
                self._rays(T, slice(None), slice(None), rays[i])
            t = self._all.cast_rays(o3d.core.Tensor.from_numpy(rays.reshape(-1, 6)), nthreads=0)["t_hit"].numpy()
            out[a:a + len(part)] = np.isfinite(t).reshape(len(part), HW)
        return out

    def _full_masks(self, T_world_from_cam: Rigid3) -> dict[int, np.ndarray]:
        import open3d as o3d  # lazy: heavy dependency (open3d)

        H, W = self.camera.height, self.camera.width
        T_cam_from_world = T_world_from_cam.inverse() @ Rigid3(np.eye(3), self._origin)  # cam from local
        masks = {}
        for k, alone in self._single.items():
            box = _bbox_in_image(self._world_bounds[k], T_cam_from_world, self.camera, self._lens_px)
            if box is None:
                continue
            r0, r1, c0, c1 = box
            rays = self._rays(T_world_from_cam, slice(r0, r1), slice(c0, c1))
            t = alone.cast_rays(o3d.core.Tensor(rays), nthreads=0)["t_hit"].numpy()
            mask = np.zeros((H, W), dtype=bool)
            mask[r0:r1, c0:c1] = np.isfinite(t)
            if mask.any():
                masks[k] = mask
        return masks


def _lens_px(rays_cam: np.ndarray, camera: Camera) -> int:
    """The most, in whole pixels, that the lens of per-pixel ``rays_cam`` moves a point from where a pinhole of
    ``camera.K`` puts it (0 below a thousandth of a pixel: a pinhole camera's own rays)."""
    lens = rays_cam[..., :2] / rays_cam[..., 2:] - pixel_rays_cam(camera)[..., :2]
    return int(np.ceil(max(camera.fx * np.abs(lens[..., 0]).max(), camera.fy * np.abs(lens[..., 1]).max()) - 1e-3))


def _bbox_in_image(
    bounds: np.ndarray, T_cam_from_world: Rigid3, camera: Camera, margin_px: int = 0
) -> tuple[int, int, int, int] | None:
    """Pixel box (r0, r1, c0, c1) covering a world AABB, widened by ``margin_px`` on each side; the whole image if it
    straddles the camera plane."""
    corners = np.array(
        [[bounds[i, 0], bounds[j, 1], bounds[k, 2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)]
    )
    pc = T_cam_from_world.apply(corners)
    if np.all(pc[:, 2] <= 0):
        return None
    if np.any(pc[:, 2] <= 1e-3):
        return 0, camera.height, 0, camera.width
    uv = pc[:, :2] / pc[:, 2:] * [camera.fx, camera.fy] + [camera.cx, camera.cy]
    c0, r0 = np.floor(uv.min(0)).astype(int) - 1 - margin_px
    c1, r1 = np.ceil(uv.max(0)).astype(int) + 1 + margin_px
    c0, c1 = max(c0, 0), min(c1, camera.width)
    r0, r1 = max(r0, 0), min(r1, camera.height)
    if c0 >= c1 or r0 >= r1:
        return None
    return int(r0), int(r1), int(c0), int(c1)
