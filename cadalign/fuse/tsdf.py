"""Semantic TSDF on Open3D's tensor ``VoxelBlockGrid`` (CPU), with a per-voxel class layer.

Geometry: Open3D integrates depth (metres, ``depth_scale=1``, a real ``depth_max``) and colour into the
attributes ``tsdf``, ``weight``, ``color`` of voxel blocks allocated around the observed surface; after each
frame the weights of the touched blocks are capped (a capped running average, so old frames fade and the map
keeps adapting). The legacy ``ScalableTSDFVolume`` is not used: in open3d 0.20 it integrates nothing.

Labels: a fourth attribute ``label`` holds class log-probabilities relative to the most likely class per
voxel (zero-filled = uniform, see :mod:`cadalign.fuse.semantic`). The update is pixel-driven: each valid
pixel (one in ``label_pixel_stride``^2 a frame, the grid's offset cycling; ``label_cell_voxels`` > 1 puts a
label cell's distribution in its lowest voxel) casts samples along its ray at z-offsets inside
``+-label_band/2`` of its depth (a band no wider than
the truncation), i.e. only voxels with ``|sdf| < trunc/2`` near the surface it saw, and each such voxel
gets one Bayes update per frame (when several samples of one frame land in one voxel, one of them is used: a
frame is one observation, not many). ``label_lookup`` picks how samples find their voxels: ``frustum`` (one
hash query per distinct block, a dense table per frame, threads; :mod:`cadalign.fuse.tsdf_frustum`) or
``reference`` (one hash query per sample, the first implementation); both write identical values.

Speed (640x480, 2 cm voxels): Open3D's ``integrate`` is most of the time; it visits every voxel of every
block the frame touches, so 4^3 blocks (``block_resolution=4``) visit far fewer voxels in front of and behind
the surface than 8^3 ones, and colour is about a third of it (``color_every``). The ``realtime`` preset uses
both; the default keeps the first implementation's geometry exactly.

Voxel ``(i, j, k)`` samples the local point ``(i, j, k) * voxel_m`` (Open3D's convention); the local frame
is ``world - origin``. Open3D truncates projected pixel coordinates to integers (pixel ``i`` covers
``[i, i+1)``), which is cadalign's pixel convention already, so ``K`` is passed unchanged (shifting it by half
a pixel moved the fused surface by ~1 cm at 3 cm pixels in the tests).
"""

from __future__ import annotations

import logging
import time

import numpy as np

from cadalign.errors import InputError
from cadalign.fuse.base import (
    FuseFrame,
    LabelledGeometry,
    origin_from_frame,
    probs_from_stored,
    require_valid_depth,
)
from cadalign.fuse.config import FuseConfig
from cadalign.fuse.semantic import bayes_update, clamped_log_probs, gather_rows, scatter_rows
from cadalign.fuse.tsdf_frustum import FrustumLabeler
from cadalign.fuse.tsdf_labels import Rays, band_offsets, band_pixels, cell_holder, label_stride
from cadalign.types import Rigid3

log = logging.getLogger(__name__)
MIN_OPEN3D = (0, 17)
ATTRS = ("tsdf", "weight", "color", "label")
SPARSE_DEPTH_FRACTION = 0.25
"""Below this fraction of valid pixels a depth map counts as sparse (SfM depth): Open3D's block selection looks
at every 4th pixel only and would skip most of its points, so blocks are picked around every valid point."""


def require_open3d():  # -> module
    """Import open3d, refusing versions without a working tensor ``VoxelBlockGrid``."""
    import open3d as o3d  # lazy: heavy dependency (open3d)

    version = tuple(int(p) for p in o3d.__version__.split(".")[:2] if p.isdigit())
    if version < MIN_OPEN3D or not hasattr(o3d.t.geometry, "VoxelBlockGrid"):
        raise InputError(f"open3d {o3d.__version__} is too old for the TSDF map: it needs the tensor "
                         f"VoxelBlockGrid of open3d >= {'.'.join(map(str, MIN_OPEN3D))}; upgrade open3d")
    return o3d


def _view(o3d_tensor) -> np.ndarray:  # noqa: ANN001 - an open3d.core.Tensor
    """A NumPy view sharing memory with a CPU Open3D tensor: the grid's buffer, valid until the hash map grows."""
    return o3d_tensor.numpy()


class SemanticTSDF:
    """A semantic TSDF map (see the module docstring). Implements :class:`~cadalign.fuse.base.SemanticMap`."""

    def __init__(self, cfg: FuseConfig, n_classes: int, origin: np.ndarray | None = None) -> None:
        if n_classes < 1:
            raise InputError(f"a semantic map needs at least one class, got {n_classes}")
        require_open3d()
        self.cfg = cfg
        self.n_classes = int(n_classes)
        self.origin = None if origin is None else np.asarray(origin, dtype=np.float64).reshape(3)
        self.frames_integrated = 0
        self.seconds = {"tsdf": 0.0, "labels": 0.0}
        self.cpu_seconds = {"tsdf": 0.0, "labels": 0.0}  # process CPU time (all threads) per part
        self.res = int(cfg.block_resolution)
        self.vbg = self._new_grid(int(cfg.block_count))
        self._rays: Rays | None = None  # per-pixel ray slopes of the last camera (frustum label lookup)
        self._labeler = FrustumLabeler(cfg.label_threads)

    def _new_grid(self, capacity: int):  # -> o3d.t.geometry.VoxelBlockGrid
        o3d = require_open3d()
        f32 = o3d.core.float32
        return o3d.t.geometry.VoxelBlockGrid(
            ATTRS, (f32,) * 4, ((1,), (1,), (3,), (self.n_classes,)), float(self.cfg.voxel_m), self.res,
            capacity, o3d.core.Device("CPU:0"),
        )

    @property
    def trunc_m(self) -> float:
        return self.cfg.trunc_voxels * self.cfg.voxel_m

    @property
    def n_blocks(self) -> int:
        return int(self.vbg.hashmap().size())

    def _T_cam_from_local(self, frame: FuseFrame) -> np.ndarray:
        return (frame.T_cam_from_world @ Rigid3(np.eye(3), self.origin)).matrix()

    def integrate(self, frame: FuseFrame) -> None:
        """Fuse one frame: TSDF + colour (Open3D), weight cap, then the label update near the surface."""
        o3d = require_open3d()
        cfg = self.cfg
        mask = require_valid_depth(frame, cfg.depth_min_m, cfg.depth_max_m, f"frame {self.frames_integrated}",
                                   self.n_classes)
        if self.origin is None:
            self.origin = origin_from_frame(frame, mask, cfg.voxel_m * self.res)
        t0, c0 = time.perf_counter(), time.process_time()
        depth = np.where(mask, frame.depth_m, 0).astype(np.float32)
        Kt = o3d.core.Tensor(frame.camera.K)
        E = o3d.core.Tensor(self._T_cam_from_local(frame))
        dimg = o3d.t.geometry.Image(o3d.core.Tensor(depth))
        color = self.frames_integrated % cfg.color_every == 0
        if color:
            rgb = frame.rgb if frame.rgb is not None else np.full((*depth.shape, 3), 128, np.uint8)
            cimg = o3d.t.geometry.Image(o3d.core.Tensor(np.ascontiguousarray(rgb, dtype=np.float32) / 255.0))
        dmax, mult = float(cfg.depth_max_m), float(cfg.trunc_voxels)
        capped = self.frames_integrated + 1 > cfg.weight_cap  # weights grow by <= 1 a frame: nothing to cap before
        coords = self._touched_blocks(frame, mask, dimg, Kt, E)
        self._activate(coords)
        # integrate() activates the blocks again and may grow (rehash) the table: look rows up after it
        if color:
            self.vbg.integrate(coords, dimg, cimg, Kt, E, 1.0, dmax, mult)
        else:
            self.vbg.integrate(coords, dimg, Kt, E, 1.0, dmax, mult)
        if capped:
            self._cap_weights(coords)
        t1, c1 = time.perf_counter(), time.process_time()
        if cfg.label_lookup != "frustum" or not self._update_labels_frustum(frame, mask):
            self._update_labels(frame, mask)
        t2, c2 = time.perf_counter(), time.process_time()
        self.seconds["tsdf"] += t1 - t0
        self.seconds["labels"] += t2 - t1
        self.cpu_seconds["tsdf"] += c1 - c0
        self.cpu_seconds["labels"] += c2 - c1
        self.frames_integrated += 1

    def _cap_weights(self, coords) -> None:  # noqa: ANN001 - an (N, 3) int32 open3d.core.Tensor
        """Cap the weights of the given blocks at ``weight_cap``, writing only blocks that exceed it (reading
        them as whole rows in buffer order is ~4x cheaper than a min-and-write of every block)."""
        cap = np.float32(self.cfg.weight_cap)
        rows = np.sort(self.vbg.hashmap().find(coords)[0].numpy().astype(np.int64))
        weight = _view(self.vbg.attribute("weight")).reshape(-1, self.res**3)
        w = np.take(weight, rows, axis=0)
        over = w.max(axis=1) > cap
        if over.any():
            weight[rows[over]] = np.minimum(w[over], cap)

    def _touched_blocks(self, frame: FuseFrame, mask: np.ndarray, dimg, Kt, E):  # noqa: ANN001, ANN202 - o3d
        """(N, 3) int32 keys of the blocks this frame integrates: Open3D's own selection (rays of every 4th
        pixel, +-trunc) for dense depth; for sparse depth, or when no valid pixel lies on that grid, every
        block within the truncation of a valid point (Open3D would otherwise skip them or fail)."""
        o3d = require_open3d()
        cfg = self.cfg
        if mask.mean() >= SPARSE_DEPTH_FRACTION and mask[::4, ::4].any():
            return self.vbg.compute_unique_block_coordinates(dimg, Kt, E, 1.0, float(cfg.depth_max_m),
                                                             float(cfg.trunc_voxels))
        v, u = np.nonzero(mask)
        z = np.asarray(frame.depth_m, dtype=np.float64)[v, u]
        cam = frame.camera
        pc = np.stack([(u + 0.5 - cam.cx) / cam.fx * z, (v + 0.5 - cam.cy) / cam.fy * z, z], axis=1)
        T = np.linalg.inv(self._T_cam_from_local(frame))
        pts = (pc @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
        pcd = o3d.t.geometry.PointCloud(o3d.core.Tensor(pts))
        return self.vbg.compute_unique_block_coordinates(pcd, float(cfg.trunc_voxels))

    def _activate(self, coords) -> None:  # noqa: ANN001 - an (N, 3) int32 open3d.core.Tensor
        """Insert the blocks; fresh ones start empty and uniform whatever the allocator left there."""
        buf, new = self.vbg.hashmap().activate(coords)
        new = new.numpy()
        if new.any():
            fresh = buf.numpy()[new].astype(np.int64)
            for name in ATTRS:
                _view(self.vbg.attribute(name))[fresh] = 0.0

    def _label_pixels(self, frame: FuseFrame, mask: np.ndarray) -> np.ndarray:
        """Flat indices of the pixels whose labels this frame fuses: every valid pixel, or those on a
        ``label_pixel_stride`` grid (see :func:`~cadalign.fuse.tsdf_labels.label_stride`) whose offset
        cycles with the frame count, so s^2 consecutive frames use every pixel once (no voxel is skipped
        frame after frame by a camera that hardly moves). Sparse depth keeps every point."""
        s = self.cfg.label_pixel_stride if mask.mean() >= SPARSE_DEPTH_FRACTION else 1
        if s > 1:
            s = label_stride(s, self.cfg.voxel_m, frame.camera.fx, np.asarray(frame.depth_m)[mask])
        return band_pixels(mask, s, self.frames_integrated)

    def _surface_samples(self, frame: FuseFrame, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
        """Voxel indices (n P, 3) int32 of samples with |sdf| < label_band/2 <= trunc/2 (offset-major: the n
        samples of the P pixels), the flat pixel indices (P,) and n."""
        pix = self._label_pixels(frame, mask)
        cam = frame.camera
        v, u = np.divmod(pix, cam.width)
        z = np.asarray(frame.depth_m, dtype=np.float32).reshape(-1)[pix]
        T = np.linalg.inv(self._T_cam_from_local(frame))
        R = (T[:3, :3] / self.cfg.voxel_m).astype(np.float32)  # in voxels
        t = (T[:3, 3] / self.cfg.voxel_m).astype(np.float32)
        # ray (x, y, 1) in the local frame, column by column (an (N, 3) @ (3, 3) matmul is slow in numpy)
        x = ((u + np.float32(0.5 - cam.cx)) * np.float32(1 / cam.fx)).astype(np.float32)
        y = ((v + np.float32(0.5 - cam.cy)) * np.float32(1 / cam.fy)).astype(np.float32)
        dirs = [x * R[k, 0] + y * R[k, 1] + R[k, 2] for k in range(3)]
        # samples one label cell apart (or closer) across the band
        offsets = band_offsets(self.cfg.label_band_voxels, self.cfg.voxel_m, self.cfg.label_cell_voxels)
        n = len(offsets)
        vox = np.empty((n * len(pix), 3), dtype=np.int32)
        for j, o in enumerate(offsets):
            zo = z + np.float32(o)
            for k in range(3):
                vox[j * len(pix):(j + 1) * len(pix), k] = np.rint(zo * dirs[k] + t[k])
        return cell_holder(vox, self.cfg.label_cell_voxels), pix, n

    def _flat_index(self, vox: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Flattened voxel index into the attribute buffers and a found-mask, for (M, 3) int32 voxel indices."""
        o3d = require_open3d()
        res = self.res
        block = np.floor_divide(vox, res)
        local = vox - block * res
        buf, ok = self.vbg.hashmap().find(o3d.core.Tensor.from_numpy(block))
        flat = buf.numpy().astype(np.int64) * res**3 + (local[:, 0] + res * (local[:, 1] + res * local[:, 2]))
        return flat, ok.numpy()

    def _update_labels(self, frame: FuseFrame, mask: np.ndarray) -> None:
        vox, pix, n = self._surface_samples(frame, mask)
        if len(pix) == 0:  # label_pixel_stride left no valid pixel
            return
        flat, ok = self._flat_index(vox)
        probs = np.asarray(frame.probs, dtype=np.float32).reshape(self.n_classes, -1)
        obs_pix = clamped_log_probs(probs[:, pix].T, self.cfg.label_min_prob)
        obs = np.tile(obs_pix, (n, 1))
        if not ok.all():  # samples outside allocated blocks (rare: blocks cover the whole truncation band)
            flat, obs = flat[ok], obs[ok]
        label = _view(self.vbg.attribute("label")).reshape(-1, self.n_classes)
        scatter_rows(label, flat, bayes_update(gather_rows(label, flat), obs, self.cfg.label_log_floor))

    def _update_labels_frustum(self, frame: FuseFrame, mask: np.ndarray) -> bool:
        """The label update of :meth:`_update_labels` (same voxels, same values) through the frustum path;
        False (nothing done) when the frame's blocks span too big a box."""
        cfg, cam = self.cfg, frame.camera
        pix = self._label_pixels(frame, mask)
        if len(pix) == 0:  # label_pixel_stride left no valid pixel
            return True
        if self._rays is None or self._rays.key != Rays.of_key(cam.K, cam.width, cam.height):
            self._rays = Rays.of(cam.K, cam.width, cam.height)
        T = np.linalg.inv(self._T_cam_from_local(frame))
        T[:3] /= cfg.voxel_m
        o3d = require_open3d()

        def find_rows(keys: np.ndarray) -> np.ndarray:
            buf, found = self.vbg.hashmap().find(o3d.core.Tensor.from_numpy(keys))
            return np.where(found.numpy(), buf.numpy().astype(np.int32), -1)

        return self._labeler.update(
            _view(self.vbg.attribute("label")).reshape(-1, self.n_classes),
            np.asarray(frame.probs, dtype=np.float32).reshape(self.n_classes, -1), pix, (self._rays.x, self._rays.y),
            np.asarray(frame.depth_m, dtype=np.float32).reshape(-1), T,
            band_offsets(cfg.label_band_voxels, cfg.voxel_m, cfg.label_cell_voxels), self.res, cfg.label_min_prob,
            cfg.label_log_floor, find_rows, cfg.label_cell_voxels)

    def stored_at(self, points_local: np.ndarray) -> np.ndarray:
        """(N, C) stored relative log-probabilities of the voxel nearest to each local point (0 = uniform)."""
        vox = np.ascontiguousarray(np.round(np.asarray(points_local) / self.cfg.voxel_m).astype(np.int32))
        flat, ok = self._flat_index(cell_holder(vox, self.cfg.label_cell_voxels))
        out = np.zeros((len(vox), self.n_classes), dtype=np.float32)
        label = _view(self.vbg.attribute("label")).reshape(-1, self.n_classes)
        out[ok] = gather_rows(label, flat[ok])
        return out

    def probs_at(self, points_local: np.ndarray, chunk: int = 500_000) -> np.ndarray:
        """(N, C) class probabilities at local points: the mean over the 8 voxels of the enclosing cell."""
        pts = np.asarray(points_local, dtype=np.float64)
        out = np.empty((len(pts), self.n_classes), dtype=np.float32)
        corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=np.float64)
        for a in range(0, len(pts), chunk):
            base = np.floor(pts[a:a + chunk] / self.cfg.voxel_m)
            q = ((base[:, None, :] + corners[None]) * self.cfg.voxel_m).reshape(-1, 3)
            p = probs_from_stored(self.stored_at(q)).reshape(len(base), 8, self.n_classes).mean(axis=1)
            out[a:a + chunk] = p / p.sum(axis=1, keepdims=True)
        return out

    def _labelled(self, geom, faces: np.ndarray | None) -> LabelledGeometry:  # noqa: ANN001 - o3d.t geometry
        attrs = geom.vertex if faces is not None else geom.point
        pos = attrs.positions.numpy().astype(np.float64)
        normals = attrs.normals.numpy().astype(np.float32) if "normals" in attrs else np.zeros_like(pos, np.float32)
        colors = attrs.colors.numpy() if "colors" in attrs else np.full_like(pos, 0.5)
        probs = self.probs_at(pos)
        origin = self.origin if self.origin is not None else np.zeros(3)
        return LabelledGeometry(pos + origin, normals, np.clip(np.round(colors * 255), 0, 255).astype(np.uint8),
                                probs.argmax(axis=1).astype(np.int64), probs, faces)

    def _require_data(self) -> None:
        if self.n_blocks == 0:
            raise InputError("the map is empty: integrate at least one frame with valid depth first")

    def _weight_threshold(self) -> float:
        # Open3D keeps voxels with weight strictly above its threshold; ours means "at least"
        return max(float(self.cfg.mesh_weight_threshold) - 0.5, 0.0)

    def extract_mesh(self) -> LabelledGeometry:
        """The zero level set as a labelled triangle mesh (world coordinates)."""
        self._require_data()
        mesh = self.vbg.extract_triangle_mesh(weight_threshold=self._weight_threshold())
        if mesh.vertex.positions.shape[0] == 0:
            raise InputError("the map holds no surface yet (no zero crossing with enough weight)")
        return self._labelled(mesh, mesh.triangle.indices.numpy().astype(np.int64))

    def extract_points(self) -> LabelledGeometry:
        """Surface points (one per zero crossing) with normals, colours and labels (world coordinates)."""
        self._require_data()
        pcd = self.vbg.extract_point_cloud(weight_threshold=self._weight_threshold())
        return self._labelled(pcd, None)

    def state(self) -> dict[str, np.ndarray]:
        """The active blocks as arrays (``keys`` (B, 3) int32 and one array per attribute) for saving.

        Blocks are in lexicographic key order: Open3D's hash map inserts blocks from parallel threads, so its
        buffer order can differ between two runs over the same frames; sorting makes equal maps equal arrays."""
        hm = self.vbg.hashmap()
        buf = hm.active_buf_indices().numpy().astype(np.int64)
        keys = hm.key_tensor().numpy()[buf]
        buf = buf[np.lexsort(keys.T[::-1])]
        out = {"keys": hm.key_tensor().numpy()[buf].copy()}
        for name in ATTRS:
            out[name] = self.vbg.attribute(name).numpy()[buf].copy()
        return out

    def load_state(self, arrays: dict[str, np.ndarray]) -> None:
        """Insert saved blocks (see :meth:`state`) into this (empty) map."""
        o3d = require_open3d()
        keys = np.ascontiguousarray(arrays["keys"], dtype=np.int32)
        if len(keys) == 0:
            return
        buf, _ = self.vbg.hashmap().activate(o3d.core.Tensor.from_numpy(keys))
        idx = buf.numpy().astype(np.int64)
        for name in ATTRS:
            view = _view(self.vbg.attribute(name))
            if tuple(arrays[name].shape[1:]) != tuple(view.shape[1:]):
                raise InputError(f"saved attribute {name!r} has block shape {arrays[name].shape[1:]}, "
                                 f"this map expects {tuple(view.shape[1:])} (different voxel blocks or classes)")
            view[idx] = np.asarray(arrays[name], dtype=np.float32)
