"""Render a simulated scene: RGB with pyrender (EGL, headless) and exact ground truth by ray casting.

Ground truth comes from Open3D's ``RaycastingScene`` with one ray through each
pixel centre (``K^-1 (u + 0.5, v + 0.5, 1)``, the convention of
:mod:`cadalign.types`). Ray directions are left with camera-frame z = 1, so
the hit parameter is the z-depth; the Euclidean range is ``t * |d|``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from cadalign.sim.scene import SEABED_INSTANCE, SimScene, triplanar_uv
from cadalign.sim.textures import make_texture
from cadalign.types import Camera, Rigid3

GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])
TEXTURE_TILE_M = 1.5


@dataclass(frozen=True)
class FrameGT:
    """Exact per-pixel ground truth of one frame (H×W).

    Attributes:
        depth_m: z-depth in metres, 0 where no surface.
        range_m: Euclidean camera–surface distance, inf where no surface.
        normals_cam: unit surface normals in the camera frame, facing the camera; 0 where no surface.
        rays_cam: unit ray directions in the camera frame.
        instance: 0 for seabed/open water, k for the scene object with index k-1.
        class_id: class index per pixel (0 background).
        full_masks: object index -> (H, W) bool mask of the object alone (ignoring occluders).
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
    import open3d as o3d

    m = o3d.t.geometry.TriangleMesh()
    m.vertex.positions = o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32))
    m.triangle.indices = o3d.core.Tensor(np.ascontiguousarray(faces, dtype=np.int32))
    return m


class GroundTruthCaster:
    """Exact depth, normals, instance and class maps by ray casting the scene meshes."""

    def __init__(self, scene: SimScene) -> None:
        import open3d as o3d

        self.scene = scene
        self.camera = scene.camera
        self._all = o3d.t.geometry.RaycastingScene()
        self._geom_to_instance: dict[int, int] = {}
        self._single = []
        self._world_bounds = []
        for k, obj in enumerate(scene.objects):
            v_world = obj.T_world_from_obj.apply(obj.mesh.vertices)
            gid = self._all.add_triangles(_o3d_mesh(v_world, obj.mesh.faces))
            self._geom_to_instance[gid] = k + 1
            alone = o3d.t.geometry.RaycastingScene()
            alone.add_triangles(_o3d_mesh(v_world, obj.mesh.faces))
            self._single.append(alone)
            self._world_bounds.append(np.array([v_world.min(0), v_world.max(0)]))
        if scene.seabed is not None:
            gid = self._all.add_triangles(_o3d_mesh(scene.seabed.vertices, scene.seabed.faces))
            self._geom_to_instance[gid] = SEABED_INSTANCE
        n_geom = max(self._geom_to_instance) + 2
        self._lut_instance = np.zeros(n_geom, dtype=np.int32)
        for gid, inst in self._geom_to_instance.items():
            self._lut_instance[gid] = inst
        self._lut_class = np.array([0] + [o.class_id for o in scene.objects], dtype=np.uint8)
        self._dirs_cam = pixel_rays_cam(self.camera)
        self._ray_len = np.linalg.norm(self._dirs_cam, axis=-1).astype(np.float32)
        self._rays_unit = (self._dirs_cam / self._ray_len[..., None]).astype(np.float32)
        self._dirs_cam32 = self._dirs_cam.astype(np.float32)
        self._rays_unit.flags.writeable = False  # shared by every frame's FrameGT

    def _rays(self, T_world_from_cam: Rigid3, rows: slice, cols: slice) -> np.ndarray:
        d = self._dirs_cam[rows, cols] @ T_world_from_cam.R.T
        o = np.broadcast_to(T_world_from_cam.t, d.shape)
        return np.concatenate([o, d], axis=-1).astype(np.float32)

    def cast(self, T_world_from_cam: Rigid3, *, with_full_masks: bool = True) -> FrameGT:
        import open3d as o3d

        H, W = self.camera.height, self.camera.width
        rays = self._rays(T_world_from_cam, slice(None), slice(None))
        ans = self._all.cast_rays(o3d.core.Tensor(rays), nthreads=0)
        t = ans["t_hit"].numpy()
        hit = np.isfinite(t)
        depth = np.where(hit, t, 0.0).astype(np.float32)
        range_m = np.where(hit, t * self._ray_len, np.float32(np.inf))
        gid = ans["geometry_ids"].numpy().astype(np.int64)
        gid = np.where(hit, gid, len(self._lut_instance) - 1)  # the last LUT slot maps to background
        instance = self._lut_instance[gid]
        n_cam = ans["primitive_normals"].numpy() @ T_world_from_cam.R.astype(np.float32)
        # face the camera; zero where nothing was hit (Open3D returns zero normals there already)
        flip = np.where(np.einsum("hwk,hwk->hw", n_cam, self._dirs_cam32) > 0, np.float32(-1), np.float32(1))
        n_cam *= flip[..., None]
        n_cam[~hit] = 0.0
        full = self._full_masks(T_world_from_cam) if with_full_masks else {}
        return FrameGT(
            depth,
            range_m,
            n_cam,
            self._rays_unit,
            instance.reshape(H, W),
            self._lut_class[instance].reshape(H, W),
            full,
        )

    def _full_masks(self, T_world_from_cam: Rigid3) -> dict[int, np.ndarray]:
        import open3d as o3d

        H, W = self.camera.height, self.camera.width
        T_cam_from_world = T_world_from_cam.inverse()
        masks = {}
        for k, (alone, bounds) in enumerate(zip(self._single, self._world_bounds, strict=True)):
            box = _bbox_in_image(bounds, T_cam_from_world, self.camera)
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


def _bbox_in_image(
    bounds: np.ndarray, T_cam_from_world: Rigid3, camera: Camera
) -> tuple[int, int, int, int] | None:
    """Pixel box (r0, r1, c0, c1) covering a world AABB; the whole image if it straddles the camera plane."""
    corners = np.array(
        [[bounds[i, 0], bounds[j, 1], bounds[k, 2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)]
    )
    pc = T_cam_from_world.apply(corners)
    if np.all(pc[:, 2] <= 0):
        return None
    if np.any(pc[:, 2] <= 1e-3):
        return 0, camera.height, 0, camera.width
    uv = pc[:, :2] / pc[:, 2:] * [camera.fx, camera.fy] + [camera.cx, camera.cy]
    c0, r0 = np.floor(uv.min(0)).astype(int) - 1
    c1, r1 = np.ceil(uv.max(0)).astype(int) + 1
    c0, c1 = max(c0, 0), min(c1, camera.width)
    r0, r1 = max(r0, 0), min(r1, camera.height)
    if c0 >= c1 or r0 >= r1:
        return None
    return int(r0), int(r1), int(c0), int(c1)


class RGBRenderer:
    """Textured, lit RGB frames with pyrender over EGL (no display needed).

    The clean render holds only the scene's ambient (down-welling) light, so
    its colours are exactly albedo × ambient; the ROV lamps (shading) and all
    water effects are applied afterwards by the declared effect stages. The
    albedo is rasterised unlit (pyrender's FLAT mode, 4x MSAA, ~4x cheaper than
    its PBR shader on the CPU rasteriser) and scaled by the ambient level here.
    """

    def __init__(self, scene: SimScene) -> None:
        os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
        import pyrender

        self._pr = pyrender
        cam = scene.camera
        self._ambient = float(scene.spec.ambient)
        self.scene = pyrender.Scene(ambient_light=np.full(3, scene.spec.ambient), bg_color=np.zeros(4))
        textures: dict[str, object] = {}
        for obj in scene.objects:
            self.scene.add(
                self._mesh(obj.mesh, obj.texture, textures, scene.spec.seed),
                pose=obj.T_world_from_obj.matrix(),
            )
        if scene.seabed is not None:
            self.scene.add(self._mesh(scene.seabed, scene.spec.seabed.texture, textures, scene.spec.seed))
        camera = pyrender.IntrinsicsCamera(cam.fx, cam.fy, cam.cx, cam.cy, znear=0.05, zfar=500.0)
        self._cam_node = self.scene.add(camera, pose=np.eye(4))
        self.renderer = pyrender.OffscreenRenderer(cam.width, cam.height)

    def _mesh(self, mesh, texture: str, cache: dict, seed: int):
        pr = self._pr
        if texture not in cache:
            img = make_texture(texture, seed)
            tex = pr.Texture(source=img, source_channels="RGB", sampler=pr.Sampler())
            cache[texture] = pr.MetallicRoughnessMaterial(
                baseColorTexture=tex, metallicFactor=0.0, roughnessFactor=1.0
            )
        pos, nrm, uv, idx = triplanar_uv(mesh, TEXTURE_TILE_M)
        prim = pr.Primitive(positions=pos, normals=nrm, texcoord_0=uv, indices=idx, material=cache[texture])
        return pr.Mesh([prim])

    def render(self, T_world_from_cam: Rigid3) -> np.ndarray:
        """(H, W, 3) float32 linear RGB in [0, 1]."""
        self.scene.set_pose(self._cam_node, T_world_from_cam.matrix() @ GL_FROM_CV)
        flags = self._pr.RenderFlags.FLAT | self._pr.RenderFlags.SKIP_CULL_FACES
        color, _ = self.renderer.render(self.scene, flags=flags)
        return color.astype(np.float32) * np.float32(self._ambient / 255.0)

    def close(self) -> None:
        self.renderer.delete()
