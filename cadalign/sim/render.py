"""Render a simulated scene: RGB with pyrender (EGL, headless) and exact ground truth by ray casting
(:mod:`cadalign.raycast.core`: one ray through each pixel centre, z-depth and range)."""

from __future__ import annotations

import os

import numpy as np

from cadalign.raycast.core import RaycastFrame, RaycastRenderer, RenderMesh
from cadalign.sim.scene import SEABED_INSTANCE, SimScene, triplanar_uv
from cadalign.sim.textures import make_texture
from cadalign.types import Rigid3

GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])
TEXTURE_TILE_M = 1.5


FrameGT = RaycastFrame
"""Exact ground truth of one simulated frame; ``instance`` k (and ``full_masks`` key k) is scene object k-1."""


class GroundTruthCaster:
    """Exact depth, normals, instance and class maps of a simulated scene (objects + seabed) by ray casting."""

    def __init__(self, scene: SimScene) -> None:
        meshes = [
            RenderMesh(obj.T_world_from_obj.apply(obj.mesh.vertices), obj.mesh.faces, k + 1, obj.class_id)
            for k, obj in enumerate(scene.objects)
        ]
        if scene.seabed is not None:
            meshes.append(RenderMesh(scene.seabed.vertices, scene.seabed.faces, SEABED_INSTANCE, 0))
        self.scene = scene
        self.camera = scene.camera
        self._renderer = RaycastRenderer(meshes, scene.camera)

    def cast(self, T_world_from_cam: Rigid3, *, with_full_masks: bool = True) -> FrameGT:
        return self._renderer.render(T_world_from_cam, with_full_masks=with_full_masks)


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
        import pyrender  # lazy: heavy dependency (pyrender)

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
