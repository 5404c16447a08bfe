"""One frame of the dataset build as a self-contained, picklable job, and the code that renders and writes it.

The builder (:func:`cadalign.build.run.render_frames`) turns every registered frame that is not yet on
disk into a :class:`FrameJob` (its metric pose, camera and source files); :func:`write_frame` ray-casts the
CAD for it and writes the frame's BOP files. The local path calls it in the builder's loop; the Ray executor
(:mod:`cadalign.build.executor`) sends chunks of jobs to worker processes, with the meshes and camera models
(:class:`FrameShared`) put into the object store once. Both paths run this same code on the same inputs, so
they write byte-identical files.

A frame's files are written in place and its record ``frames_json/NNNNNN.json`` atomically last
(:func:`cadalign.raycast.bop_writer.write_bop_frame`), so a job killed mid-frame leaves no record and its
retry rewrites every file of the frame; a retried job skips the frames whose record exists.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from cadalign.align.camera_refine import rays_of
from cadalign.formats import bop
from cadalign.io import write_image
from cadalign.raycast.bop_writer import PosedObject, frame_done, write_bop_frame
from cadalign.raycast.core import RaycastRenderer, RenderMesh
from cadalign.types import Camera, Progress, Rigid3


@dataclass(frozen=True)
class CameraModel:
    """A COLMAP camera model by value (rebuilt as a ``pycolmap.Camera`` where the frame is rendered)."""

    model: str
    """COLMAP model name, e.g. ``SIMPLE_RADIAL``."""
    width: int
    """Image width, pixels."""
    height: int
    """Image height, pixels."""
    params: tuple[float, ...]
    """The model's parameters in COLMAP order (focal lengths, principal point, distortion)."""

    @classmethod
    def of(cls, cam) -> CameraModel:  # noqa: ANN001  (a pycolmap.Camera)
        return cls(cam.model.name, int(cam.width), int(cam.height), tuple(float(p) for p in cam.params))

    def rays_cam(self) -> np.ndarray:
        """(H, W, 3) camera-frame rays with z = 1 through the pixel centres, distortion included."""
        import pycolmap  # lazy: heavy dependency (pycolmap)

        cam = pycolmap.Camera(model=self.model, width=self.width, height=self.height, params=list(self.params))
        return rays_of(cam)


@dataclass(frozen=True)
class FrameJob:
    """Everything needed to render and write BOP frame ``k`` (small: no image arrays)."""

    k: int
    """BOP image id."""
    camera_id: int
    """Key of the frame's camera model in :attr:`FrameShared.cameras`."""
    camera: Camera
    """Pinhole camera written to scene_camera.json (K of the SfM camera)."""
    T_world_from_cam: Rigid3
    """Metric camera pose in the CAD frame."""
    rgb_source: Path
    """The frame's image, hard-linked (or copied) to ``rgb/``."""
    sfm_depth: Path | None
    """The frame's semi-dense SfM depth (.npy, SfM units), or None."""
    sfm_scale: float
    """Scale of ``cad_from_sfm``: SfM units -> metres."""


@dataclass(frozen=True)
class FrameShared:
    """Inputs shared by every frame of a build (sent once to each worker through the object store)."""

    meshes: tuple[RenderMesh, ...]
    """The structure's meshes in world coordinates (metres), instance ids ``i + 1`` for ``objects[i]``."""
    objects: tuple[PosedObject, ...]
    """The structure's posed object instances."""
    cameras: dict[int, CameraModel]
    """camera_id -> COLMAP camera model (the rays include its distortion)."""
    scene_dir: Path
    """The BOP scene folder written (must be on storage every worker can reach)."""
    depth_scale: float
    """BOP depth scale: millimetres per depth-PNG unit."""


def write_frame(job: FrameJob, renderer: RaycastRenderer, shared: FrameShared) -> None:
    """Ray-cast frame ``job.k`` and write its BOP files into ``shared.scene_dir`` (its record last, atomically)."""
    gt = renderer.render(job.T_world_from_cam)
    if any(m.instance == 0 for m in shared.meshes):  # background geometry (the seabed) occludes; no CAD depth
        bg = gt.instance == 0
        gt = replace(gt, depth_m=np.where(bg, np.float32(0), gt.depth_m),
                                 normals_cam=np.where(bg[..., None], np.float32(0), gt.normals_cam))
    scene_dir, scale = Path(shared.scene_dir), shared.depth_scale
    if job.sfm_depth is not None:  # semi-dense SfM depth, now in metres
        d = np.load(job.sfm_depth).astype(np.float64) * job.sfm_scale
        write_image(scene_dir / "depth_sfm" / bop.frame_name(job.k), bop.encode_depth(d, scale), atomic=False)
    write_bop_frame(scene_dir, job.k, job.camera, job.T_world_from_cam.inverse(), gt, shared.objects, scale,
                    rgb_source=job.rgb_source)


def render_chunk(jobs: Sequence[FrameJob], shared: FrameShared, progress: Progress | None = None) -> list[int]:
    """Render and write ``jobs`` (one renderer per camera model, built once for the chunk); the frame ids
    written. Frames already complete on disk (an earlier attempt of this chunk) are skipped. A Ray worker runs
    it on one chunk; a local build on every frame (with ``progress``)."""
    renderers: dict[int, RaycastRenderer] = {}
    written: list[int] = []
    for job in progress(jobs, "render", len(jobs)) if progress else jobs:
        if frame_done(shared.scene_dir, job.k):
            continue
        if job.camera_id not in renderers:
            rays = shared.cameras[job.camera_id].rays_cam()
            renderers[job.camera_id] = RaycastRenderer(list(shared.meshes), job.camera, rays_cam=rays)
        write_frame(job, renderers[job.camera_id], shared)
        written.append(job.k)
    return written
