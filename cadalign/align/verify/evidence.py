"""The evidence of one placement of the CAD in the images: edge lift per part, free-space violations,
photo-consistency, and the local contour fit (see :mod:`cadalign.align.verify.core` for how they are combined)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from cadalign.align.edge_refine import (
    EdgeRefineConfig,
    contour_samples,
    fit_edge_correction,
    moved_camera,
    search_edges,
)
from cadalign.raycast.core import RaycastRenderer, RenderMesh, _o3d_mesh
from cadalign.types import Camera, Rigid3, Sim3

if TYPE_CHECKING:
    from cadalign.align.verify.config import VerifyConfig

@dataclass(frozen=True)
class View:
    """A registered frame: its camera, rays (SfM lens model), grey image and SfM pose."""

    name: str
    camera: Camera
    rays_cam: np.ndarray
    gray: np.ndarray
    R_cw: np.ndarray
    c_sfm: np.ndarray

    def pose(self, cad_from_sfm: Sim3) -> Rigid3:
        """``T_world_from_cam`` in the CAD frame under ``cad_from_sfm``."""
        return cad_from_sfm.carry_pose(Rigid3(self.R_cw.T, self.c_sfm))


def edge_evidence(renderer: RaycastRenderer, gray: np.ndarray, T_world_from_cam: Rigid3, cfg: VerifyConfig,
                  ) -> np.ndarray:
    """Per CAD instance seen in one view: rows ``(instance, samples, hits at the predicted contour, displaced
    samples, hits at the displaced contour)``, (P, 5) int."""
    f = renderer.render(T_world_from_cam, with_full_masks=False)
    ecfg = EdgeRefineConfig(point_step=1, search_px=cfg.near_px, min_contrast=cfg.min_contrast)
    _, uv, n = contour_samples(f.depth_m, f.rays_cam, f.range_m, ecfg, f.instance)
    H, W = gray.shape
    if len(uv) == 0:
        return np.zeros((0, 5), dtype=np.int64)
    # the near pixel of each sample (half a pixel back along its normal) names its part
    near = np.clip(np.rint(uv - 0.5 * n).astype(np.int64), 0, [W - 1, H - 1])
    inst = f.instance[near[:, 1], near[:, 0]].astype(np.int64)
    hit0 = np.isfinite(search_edges(gray, uv, n, ecfg))
    ids = np.unique(inst[inst > 0])
    rows = np.zeros((len(ids), 5), dtype=np.int64)
    rows[:, 0] = ids
    for j, i in enumerate(ids):
        rows[j, 1], rows[j, 2] = int((inst == i).sum()), int(hit0[inst == i].sum())
    for s in cfg.shifts_px:
        for sign in (1.0, -1.0):
            q = uv + sign * s * n
            inside = (q[:, 0] > 2) & (q[:, 0] < W - 3) & (q[:, 1] > 2) & (q[:, 1] < H - 3)
            if not inside.any():
                continue
            hit = np.isfinite(search_edges(gray, q[inside], n[inside], ecfg))
            for j, i in enumerate(ids):
                m = inst[inside] == i
                rows[j, 3] += int(m.sum())
                rows[j, 4] += int(hit[m].sum())
    return rows


def part_lift(rows: np.ndarray, min_part_samples: int) -> tuple[float, float, float, int, int]:
    """(edge lift, hit rate, displaced hit rate, samples, parts scored) from per-part rows of all views.

    The lift is the mean over parts with at least ``min_part_samples`` contour samples of each part's
    ``(h0 - h_shifted) / (1 - h_shifted)``: a big, nearly symmetric part (a frame) cannot outvote the small
    asymmetric ones that tell a placement from its turned look-alike."""
    if len(rows) == 0:
        return 0.0, 0.0, 0.0, 0, 0
    ids = np.unique(rows[:, 0])
    tot = np.array([rows[rows[:, 0] == i, 1:].sum(axis=0) for i in ids])  # (P, 4)
    n = int(tot[:, 0].sum())
    hit = tot[:, 1].sum() / max(n, 1)
    base = tot[:, 3].sum() / max(tot[:, 2].sum(), 1)
    ok = (tot[:, 0] >= min_part_samples) & (tot[:, 2] > 0)
    if not ok.any():
        return 0.0, float(hit), float(base), n, 0
    h0 = tot[ok, 1] / tot[ok, 0]
    hb = tot[ok, 3] / tot[ok, 2]
    lift = (h0 - hb) / np.maximum(1.0 - hb, 1e-6)
    return float(lift.mean()), float(hit), float(base), n, int(ok.sum())


@dataclass(frozen=True)
class FreeSpaceRays:
    """Observations of SfM points: camera centres and points (N, 3) each, in the SfM frame."""

    origins_sfm: np.ndarray
    points_sfm: np.ndarray


def free_space_rays(rec: Any, n_points: int, per_point: int, seed: int) -> FreeSpaceRays:
    """A seeded subset of the observations of ``rec``'s points (a ``pycolmap.Reconstruction``)."""
    rng = np.random.default_rng(seed)
    ids = np.array(sorted(rec.points3D), dtype=np.int64)
    if len(ids) > n_points:
        ids = np.sort(rng.choice(ids, n_points, replace=False))
    centres = {iid: np.asarray(im.projection_center(), dtype=np.float64) for iid, im in rec.images.items()
               if im.has_pose}
    origins, points = [], []
    for pid in ids:
        p = rec.points3D[int(pid)]
        imgs = [e.image_id for e in p.track.elements if e.image_id in centres]
        if len(imgs) > per_point:
            imgs = [imgs[i] for i in rng.choice(len(imgs), per_point, replace=False)]
        for iid in imgs:
            origins.append(centres[iid])
            points.append(np.asarray(p.xyz, dtype=np.float64))
    return FreeSpaceRays(np.reshape(origins, (-1, 3)), np.reshape(points, (-1, 3)))


def free_space_evidence(scene: Any, origin_m: np.ndarray, rays: FreeSpaceRays, cad_from_sfm: Sim3, margin_m: float,
                        margin_rel: float) -> tuple[int, int]:
    """(rays meeting the CAD at or before their point, of which meet it clearly before: violations).

    ``scene``: an Open3D ``RaycastingScene`` of the CAD with coordinates relative to ``origin_m``."""
    import open3d as o3d  # lazy: heavy dependency (open3d)

    if len(rays.points_sfm) == 0:
        return 0, 0
    o = cad_from_sfm.apply(rays.origins_sfm) - origin_m
    x = cad_from_sfm.apply(rays.points_sfm) - origin_m
    d = x - o
    dist = np.linalg.norm(d, axis=1)
    ok = dist > 0
    o, d, dist = o[ok], d[ok] / dist[ok, None], dist[ok]
    t = scene.cast_rays(o3d.core.Tensor(np.concatenate([o, d], 1).astype(np.float32)))["t_hit"].numpy()
    margin = np.maximum(margin_m, margin_rel * dist)
    meets = t < dist + margin
    return int(meets.sum()), int((t < dist - margin).sum())


def photo_consistency(views: Sequence[View], scene: Any, origin_m: np.ndarray, T: Sim3, surface_m: np.ndarray,
                      min_views: int = 3) -> tuple[float, int]:
    """(photo-consistency, points used) of the CAD surface under ``cad_from_sfm = T``.

    Each surface sample (N, 3, CAD frame) is projected into the views that see it (a ray from the camera meets
    the CAD first at it) and its grey value read; the score is ``1 - mean per-point std / std of all values``
    over samples seen in ``min_views`` views or more: near 0 when the CAD lies over unrelated image content in
    each view, towards 1 on a textured surface at the right pose (a uniform surface gives no evidence)."""
    import open3d as o3d  # lazy: heavy dependency (open3d)

    vals = np.full((len(surface_m), len(views)), np.nan)
    for j, v in enumerate(views):
        pose = v.pose(T)
        d = surface_m - pose.t
        dist = np.linalg.norm(d, axis=1)
        o = np.broadcast_to(pose.t - origin_m, d.shape)
        t = scene.cast_rays(o3d.core.Tensor(np.concatenate([o, d / dist[:, None]], 1).astype(np.float32)))
        seen = t["t_hit"].numpy() >= dist - 1e-3 * np.maximum(dist, 1.0)
        X = (surface_m - pose.t) @ pose.R  # camera frame
        front = X[:, 2] > 0
        uv = (X @ v.camera.K.T)[:, :2] / np.where(front, X[:, 2], 1.0)[:, None]
        px = np.floor(uv).astype(np.int64)
        H, W = v.gray.shape
        ok = seen & front & (px[:, 0] >= 0) & (px[:, 0] < W) & (px[:, 1] >= 0) & (px[:, 1] < H)
        vals[ok, j] = v.gray[px[ok, 1], px[ok, 0]]
    many = np.sum(np.isfinite(vals), axis=1) >= min_views
    if many.sum() < 20:
        return 0.0, int(many.sum())
    v = vals[many]
    spread = float(np.nanstd(v))
    if spread <= 0:
        return 0.0, int(many.sum())
    return float(1.0 - np.mean(np.nanstd(v, axis=1)) / spread), int(many.sum())


def cad_scene(meshes: Sequence[RenderMesh]) -> tuple[Any, np.ndarray]:
    import open3d as o3d  # lazy: heavy dependency (open3d)

    parts = [m for m in meshes if m.instance > 0]
    origin = np.concatenate([m.vertices_m for m in parts]).mean(axis=0)
    scene = o3d.t.geometry.RaycastingScene()
    for m in parts:
        scene.add_triangles(_o3d_mesh(np.asarray(m.vertices_m, dtype=np.float64) - origin, m.faces))
    return scene, origin


def refine_locally(views: Sequence[View], renderer_of: Any, T: Sim3, centre: np.ndarray, diameter_m: float,
                   cfg: VerifyConfig) -> tuple[Sim3, bool]:
    """``cad_from_sfm`` moved to its nearest fit of the image contours, and whether it moved (see
    :attr:`VerifyConfig.refine`)."""
    ecfg = EdgeRefineConfig(search_px=cfg.refine_search_px, tukey_px=cfg.refine_search_px / 2, rounds=4,
                            min_edges=cfg.min_samples, max_turn_deg=cfg.refine_max_turn_deg,
                            max_shift_m=cfg.refine_max_shift_rel * diameter_m, max_scale_rel=0.1,
                            min_contrast=cfg.min_contrast)
    poses = [v.pose(T) for v in views]
    corr = fit_edge_correction([renderer_of(v) for v in views], [v.gray for v in views], poses, centre, ecfg)
    if not corr.applied:
        return T, False
    # moved_camera(H, pose) sees X where pose saw H(X): the CAD placed by H^-1 @ cad_from_sfm
    assert np.allclose(moved_camera(corr.H_world, poses[0]).t, views[0].pose(corr.H_world.inverse() @ T).t,
                       atol=1e-6 * max(1.0, diameter_m))
    return corr.H_world.inverse() @ T, True


def surface_samples(meshes: Sequence[RenderMesh], n: int, seed: int) -> np.ndarray:
    """(n, 3) area-uniform samples of the meshes' surfaces, pushed 1 mm off along the face normals."""
    tris = np.concatenate([m.vertices_m[m.faces] for m in meshes])  # (F, 3, 3)
    cross = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    rng = np.random.default_rng(seed)
    f = rng.choice(len(tris), n, p=area / area.sum())
    a, b = rng.random((2, n))
    flip = a + b > 1
    a, b = np.where(flip, 1 - a, a), np.where(flip, 1 - b, b)
    p = tris[f, 0] + a[:, None] * (tris[f, 1] - tris[f, 0]) + b[:, None] * (tris[f, 2] - tris[f, 0])
    normal = cross[f] / np.maximum(2 * area[f, None], 1e-12)
    return p + 1e-3 * normal  # outside on a consistently wound mesh; the visibility test tolerates either side
