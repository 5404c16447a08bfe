"""An ElasticFusion-like semantic surfel map (no loop closure: poses are given).

Each surfel has a position, normal, radius, confidence, colour and class log-probabilities (the same
Bayes update as the TSDF voxels, :mod:`cadalign.fuse.semantic`). Per frame:

1. *Measurements* at every valid pixel: the back-projected point, a normal from the vertex map's central
   differences, a radius ``sqrt(2) d / (f |n_z|)`` (the pixel footprint) and a weight
   ``exp(-r^2 / (2 * 0.6^2))`` that trusts the image centre more (``r``: normalised distance from it).
2. *Projective association*: every surfel is projected into the frame; it merges the measurement at its
   pixel when the depths differ by less than ``surfel_max_dist_voxels`` voxels and the normals by less than
   ``surfel_max_normal_deg`` (each surfel gets at most one observation per frame). Merging is the
   confidence-weighted average of position, normal and colour, the smaller radius, confidence ``+ weight``
   (capped at ``weight_cap``), and one Bayes label update.
3. *New surfels* come from the remaining pixels, at most one per voxel cell and normal direction (a hash
   set of ``(cell, dominant normal axis)`` keys, kept per surfel as ``cell`` so a re-opened map continues
   exactly), so the map density follows ``voxel_m``, not the image.
"""

from __future__ import annotations

import math
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
from cadalign.fuse.semantic import bayes_update, clamped_log_probs
from cadalign.fuse.tsdf import require_open3d
from cadalign.types import Rigid3

FIELDS = ("position", "normal", "radius", "confidence", "color", "label", "last_seen", "cell")


def measurement_normals(pts_cam: np.ndarray, valid: np.ndarray,
                        max_jump_rel: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, 3) camera-frame unit normals facing the camera, and the (H, W) mask where they are defined.

    Central differences of the vertex map; undefined at the border, next to invalid pixels and across depth
    jumps larger than ``max_jump_rel`` of the depth.
    """
    z = pts_cam[..., 2]
    ok = valid.copy()
    ok[0, :] = ok[-1, :] = ok[:, 0] = ok[:, -1] = False
    for axis in (0, 1):
        for shift in (1, -1):
            nb_valid = np.roll(valid, shift, axis=axis)
            jump = np.abs(np.roll(z, shift, axis=axis) - z) > max_jump_rel * np.maximum(z, 1e-6)
            ok &= nb_valid & ~jump
    dx = np.roll(pts_cam, -1, axis=1) - np.roll(pts_cam, 1, axis=1)
    dy = np.roll(pts_cam, -1, axis=0) - np.roll(pts_cam, 1, axis=0)
    n = np.cross(dy, dx)
    norm = np.linalg.norm(n, axis=-1)
    ok &= norm > 0
    n = n / np.maximum(norm, 1e-12)[..., None]
    n *= np.where(np.einsum("hwk,hwk->hw", n, pts_cam) > 0, -1.0, 1.0)[..., None]
    return n.astype(np.float32), ok


def _normal_bucket(n: np.ndarray) -> np.ndarray:
    """0..5: the dominant axis of each normal and its sign."""
    axis = np.abs(n).argmax(axis=1)
    sign = n[np.arange(len(n)), axis] > 0
    return (2 * axis + sign).astype(np.int32)


class SurfelMap:
    """A semantic surfel map (see the module docstring). Implements :class:`~cadalign.fuse.base.SemanticMap`."""

    def __init__(self, cfg: FuseConfig, n_classes: int, origin: np.ndarray | None = None) -> None:
        if n_classes < 1:
            raise InputError(f"a semantic map needs at least one class, got {n_classes}")
        o3d = require_open3d()
        self.cfg = cfg
        self.n_classes = int(n_classes)
        self.origin = None if origin is None else np.asarray(origin, dtype=np.float64).reshape(3)
        self.frames_integrated = 0
        self.seconds = {"associate": 0.0, "create": 0.0}
        self._cells = o3d.core.HashSet(max(int(cfg.block_count), 16), o3d.core.int32, (4,))
        self.n = 0
        self._data = self._empty(1024)

    def _empty(self, capacity: int) -> dict[str, np.ndarray]:
        c = self.n_classes
        return {"position": np.zeros((capacity, 3), np.float32), "normal": np.zeros((capacity, 3), np.float32),
                "radius": np.zeros(capacity, np.float32), "confidence": np.zeros(capacity, np.float32),
                "color": np.zeros((capacity, 3), np.float32), "label": np.zeros((capacity, c), np.float32),
                "last_seen": np.zeros(capacity, np.int32), "cell": np.zeros((capacity, 4), np.int32)}

    def __len__(self) -> int:
        return self.n

    def field(self, name: str) -> np.ndarray:
        """A view of one per-surfel array (``FIELDS``) over the live surfels."""
        return self._data[name][: self.n]

    def _T_cam_from_local(self, frame: FuseFrame) -> Rigid3:
        return frame.T_cam_from_world @ Rigid3(np.eye(3), self.origin)

    def integrate(self, frame: FuseFrame) -> None:
        """Fuse one frame: associate and merge, then add surfels for the uncovered surface."""
        cfg = self.cfg
        mask = require_valid_depth(frame, cfg.depth_min_m, cfg.depth_max_m, f"frame {self.frames_integrated}",
                                   self.n_classes)
        if self.origin is None:
            self.origin = origin_from_frame(frame, mask, cfg.voxel_m * cfg.block_resolution)
        t0 = time.perf_counter()
        meas = self._measurements(frame, mask)
        T = self._T_cam_from_local(frame)
        self._associate(frame, meas, T)
        t1 = time.perf_counter()
        self._create(frame, meas, T.inverse())
        self.seconds["associate"] += t1 - t0
        self.seconds["create"] += time.perf_counter() - t1
        self.frames_integrated += 1

    def _measurements(self, frame: FuseFrame, mask: np.ndarray) -> dict[str, np.ndarray]:
        cam = frame.camera
        h, w = cam.height, cam.width
        u = (np.arange(w) + 0.5 - cam.cx) / cam.fx
        v = (np.arange(h) + 0.5 - cam.cy) / cam.fy
        z = np.where(mask, frame.depth_m, 0).astype(np.float32)
        pts = np.stack([u[None, :] * z, v[:, None] * z, z], axis=-1).astype(np.float32)
        normals, ok = measurement_normals(pts, mask)
        r_img = np.hypot((np.arange(w) + 0.5 - cam.cx)[None, :] / cam.cx,
                         (np.arange(h) + 0.5 - cam.cy)[:, None] / cam.cy)
        weight = np.exp(-(r_img**2) / (2 * 0.6**2)).astype(np.float32)
        radius = math.sqrt(2) * z / (cam.fx * np.maximum(np.abs(normals[..., 2]), 0.3))
        rgb = frame.rgb if frame.rgb is not None else np.full((h, w, 3), 128, np.uint8)
        return {"points": pts, "normals": normals, "ok": ok, "weight": weight, "radius": radius.astype(np.float32),
                "rgb": rgb.astype(np.float32), "depth": z}

    def _associate(self, frame: FuseFrame, meas: dict[str, np.ndarray], T: Rigid3) -> None:
        if self.n == 0:
            return
        cfg, cam = self.cfg, frame.camera
        pc = self.field("position") @ T.R.T.astype(np.float32) + T.t.astype(np.float32)
        z = pc[:, 2]
        front = z > cfg.depth_min_m
        u = np.floor(np.where(front, pc[:, 0] / np.where(front, z, 1) * cam.fx + cam.cx, -1)).astype(np.int64)
        v = np.floor(np.where(front, pc[:, 1] / np.where(front, z, 1) * cam.fy + cam.cy, -1)).astype(np.int64)
        cand = np.flatnonzero(front & (z <= cfg.depth_max_m) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height))
        if cand.size == 0:
            return
        pu, pv = u[cand], v[cand]
        ok = meas["ok"][pv, pu]
        d = meas["depth"][pv, pu]
        ok &= np.abs(d - z[cand]) < cfg.surfel_max_dist_voxels * cfg.voxel_m
        n_cam = self.field("normal")[cand] @ T.R.T.astype(np.float32)
        ok &= np.einsum("nk,nk->n", n_cam, meas["normals"][pv, pu]) > math.cos(math.radians(cfg.surfel_max_normal_deg))
        idx, pu, pv = cand[ok], pu[ok], pv[ok]
        if idx.size:
            self._merge(idx, pu, pv, frame, meas, T.inverse())

    def _merge(self, idx: np.ndarray, pu: np.ndarray, pv: np.ndarray, frame: FuseFrame,
               meas: dict[str, np.ndarray], T_local_from_cam: Rigid3) -> None:
        D, cfg = self._data, self.cfg
        R, t = T_local_from_cam.R.astype(np.float32), T_local_from_cam.t.astype(np.float32)
        a = meas["weight"][pv, pu][:, None]
        c = D["confidence"][idx][:, None]
        p_new = meas["points"][pv, pu] @ R.T + t
        n_new = meas["normals"][pv, pu] @ R.T
        D["position"][idx] = (c * D["position"][idx] + a * p_new) / (c + a)
        n = c * D["normal"][idx] + a * n_new
        D["normal"][idx] = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        D["color"][idx] = (c * D["color"][idx] + a * meas["rgb"][pv, pu]) / (c + a)
        D["radius"][idx] = np.minimum(D["radius"][idx], meas["radius"][pv, pu])
        D["confidence"][idx] = np.minimum(c[:, 0] + a[:, 0], cfg.weight_cap)
        D["last_seen"][idx] = self.frames_integrated
        obs = clamped_log_probs(frame.probs[:, pv, pu].T, cfg.label_min_prob)
        D["label"][idx] = bayes_update(D["label"][idx], obs, cfg.label_log_floor)

    def _keys(self, pos_local: np.ndarray, normals: np.ndarray) -> np.ndarray:
        cell = np.round(pos_local / self.cfg.voxel_m).astype(np.int32)
        return np.ascontiguousarray(np.concatenate([cell, _normal_bucket(normals)[:, None]], axis=1))

    def _create(self, frame: FuseFrame, meas: dict[str, np.ndarray], T_local_from_cam: Rigid3) -> None:
        o3d = require_open3d()
        vv, uu = np.nonzero(meas["ok"])
        if vv.size == 0:
            return
        R, t = T_local_from_cam.R.astype(np.float32), T_local_from_cam.t.astype(np.float32)
        pos = meas["points"][vv, uu] @ R.T + t
        nrm = meas["normals"][vv, uu] @ R.T
        keys = self._keys(pos, nrm)
        # one candidate per key, the first pixel in raster order: the hash set's parallel insert would pick
        # an arbitrary one among duplicates, and maps must not depend on thread timing
        packed = (keys[:, :3].astype(np.int64) + (1 << 19)) @ np.array([1 << 43, 1 << 23, 1 << 3]) + keys[:, 3]
        first = np.sort(np.unique(packed, return_index=True)[1])
        _, new = self._cells.insert(o3d.core.Tensor.from_numpy(np.ascontiguousarray(keys[first])))
        sel = first[new.numpy()]
        k = len(sel)
        if k == 0:
            return
        self._reserve(self.n + k)
        s = slice(self.n, self.n + k)
        D, vv, uu = self._data, vv[sel], uu[sel]
        D["position"][s], D["normal"][s] = pos[sel], nrm[sel]
        D["radius"][s], D["confidence"][s] = meas["radius"][vv, uu], meas["weight"][vv, uu]
        D["color"][s], D["last_seen"][s] = meas["rgb"][vv, uu], self.frames_integrated
        D["cell"][s] = keys[sel]
        obs = clamped_log_probs(frame.probs[:, vv, uu].T, self.cfg.label_min_prob)
        D["label"][s] = bayes_update(np.zeros((k, self.n_classes), np.float32), obs, self.cfg.label_log_floor)
        self.n += k

    def _reserve(self, size: int) -> None:
        cap = len(self._data["radius"])
        if size <= cap:
            return
        grown = self._empty(max(size, 2 * cap))
        for name, arr in self._data.items():
            grown[name][: self.n] = arr[: self.n]
        self._data = grown

    def _stable(self) -> np.ndarray:
        keep = np.flatnonzero(self.field("confidence") >= self.cfg.surfel_min_confidence)
        if keep.size == 0:
            raise InputError(f"the surfel map has no surfel with confidence >= {self.cfg.surfel_min_confidence} "
                             f"({self.n} surfels after {self.frames_integrated} frames): integrate more frames or "
                             "lower surfel_min_confidence")
        return keep

    def extract_points(self) -> LabelledGeometry:
        """Confident surfels as a labelled point cloud (world coordinates)."""
        keep = self._stable()
        probs = probs_from_stored(self.field("label")[keep])
        return LabelledGeometry(self.field("position")[keep].astype(np.float64) + self.origin,
                                self.field("normal")[keep].copy(),
                                np.clip(np.round(self.field("color")[keep]), 0, 255).astype(np.uint8),
                                probs.argmax(axis=1).astype(np.int64), probs, None)

    def extract_mesh(self) -> LabelledGeometry:
        """Confident surfels as a splat mesh: one square (two triangles) of the surfel's radius each."""
        pts = self.extract_points()
        keep = self._stable()
        n = pts.normals.astype(np.float64)
        helper = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
        t1 = np.cross(n, helper)
        t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
        t2 = np.cross(n, t1)
        r = self.field("radius")[keep].astype(np.float64)[:, None]
        signs = ((-1, -1), (1, -1), (1, 1), (-1, 1))
        corners = np.stack([pts.points_m + r * (sa * t1 + sb * t2) for sa, sb in signs], 1)
        base = 4 * np.arange(len(keep))[:, None]
        faces = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]], axis=0).astype(np.int64)
        rep = np.repeat
        return LabelledGeometry(corners.reshape(-1, 3), rep(pts.normals, 4, 0), rep(pts.colors, 4, 0),
                                rep(pts.labels, 4), rep(pts.probs, 4, 0), faces)

    def state(self) -> dict[str, np.ndarray]:
        """The live surfels' arrays (``FIELDS``) for saving."""
        return {name: self.field(name).copy() for name in FIELDS}

    def load_state(self, arrays: dict[str, np.ndarray]) -> None:
        """Insert saved surfels (see :meth:`state`) into this (empty) map."""
        o3d = require_open3d()
        k = len(arrays["radius"])
        if arrays["label"].shape[1:] != (self.n_classes,):
            raise InputError(f"saved surfels have {arrays['label'].shape[1:]} classes, this map {self.n_classes}")
        self._reserve(self.n + k)
        for name in FIELDS:
            self._data[name][self.n:self.n + k] = arrays[name]
        self.n += k
        if k:
            self._cells.insert(o3d.core.Tensor.from_numpy(np.ascontiguousarray(arrays["cell"], dtype=np.int32)))
