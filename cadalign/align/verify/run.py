"""``verify_alignment``: the image verification of an alignment on disk, its picture and ``verify.json``.

Output (``OUT``, the build's ``verify/`` folder)::

    OUT/verify.json        outcome, chosen hypothesis, margin, reasons, fix and every hypothesis's evidence
    OUT/hypotheses.png     the best two distinct hypotheses' CAD contours over a few frames (green: chosen,
                           red: runner-up), so a person can choose with --hypothesis N or give picks
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from cadalign.align.camera_refine import rays_of
from cadalign.align.edge_refine import EdgeRefineConfig, contour_samples
from cadalign.align.verify.core import Verification, VerifyConfig, View, free_space_rays, verify
from cadalign.errors import InputError, VerificationError
from cadalign.io import write_bytes, write_json
from cadalign.raycast.core import RaycastRenderer, RenderMesh
from cadalign.types import Camera, Sim3

log = logging.getLogger(__name__)

__all__ = ["VERIFY_JSON", "VERIFY_PNG", "VerificationError", "hypotheses_png", "load_views", "verify_alignment"]

VERIFY_JSON = "verify.json"
VERIFY_PNG = "hypotheses.png"


def load_views(rec: Any, images_dir: Path, n: int) -> list[View]:
    """``n`` evenly spaced registered frames of ``rec`` (a ``pycolmap.Reconstruction``) with grey images."""

    ims = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    pick = [ims[int(i)] for i in np.unique(np.linspace(0, len(ims) - 1, min(n, len(ims))).round())] if ims else []
    views, rays = [], {}
    for im in pick:
        gray = cv2.imread(str(images_dir / im.name), cv2.IMREAD_GRAYSCALE)
        if gray is None:
            raise InputError(f"cannot read frame {images_dir / im.name} for the verification; re-run the build "
                             "with --overwrite to extract the frames again")
        cam = im.camera
        if cam.camera_id not in rays:
            rays[cam.camera_id] = rays_of(cam)
        T = im.cam_from_world()
        R_cw = T.rotation.matrix()
        views.append(View(im.name, Camera(np.asarray(cam.calibration_matrix(), dtype=np.float64), int(cam.width),
                                          int(cam.height)), rays[cam.camera_id], gray.astype(np.float32), R_cw,
                          -R_cw.T @ np.asarray(T.translation, dtype=np.float64)))
    return views


def hypotheses_png(views: Sequence[View], meshes: Sequence[RenderMesh], ver: Verification, n_frames: int) -> bytes:
    """A grid of frames (columns) with the chosen (green) and the next best (red: the runner-up, else the best
    other hypothesis, a look-alike) hypotheses' contours drawn."""

    hyps = ver.hypotheses
    second = ver.runner_up
    if second is None:
        others = [e.index for e in sorted(ver.evidence, key=lambda e: -e.score) if e.index != ver.chosen]
        second = others[0] if others else None
    picks = [views[int(i)] for i in np.unique(np.linspace(0, len(views) - 1, min(n_frames, len(views))).round())]
    shown = [(ver.chosen, (60, 220, 60))] + ([(second, (60, 60, 255))] if second is not None else [])
    cad = [m for m in meshes if m.instance > 0]
    tiles = []
    for v in picks:
        img = cv2.cvtColor(v.gray.astype(np.uint8), cv2.COLOR_GRAY2BGR)
        r = RaycastRenderer(cad, v.camera, rays_cam=v.rays_cam)
        for k, colour in shown[::-1]:  # the chosen one on top
            f = r.render(v.pose(hyps[k]), with_full_masks=False)
            _, uv, _ = contour_samples(f.depth_m, f.rays_cam, f.range_m, EdgeRefineConfig(point_step=1), f.instance)
            for x, y in np.round(uv).astype(int):
                cv2.circle(img, (int(x), int(y)), 1, colour, -1)
        scale = 480 / img.shape[1]
        img = cv2.resize(img, (480, int(round(img.shape[0] * scale))))
        cv2.putText(img, v.name, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1)
        tiles.append(img)
    h = max(t.shape[0] for t in tiles)
    grid = np.concatenate([np.pad(t, ((0, h - t.shape[0]), (0, 4), (0, 0))) for t in tiles], axis=1)
    e = {x.index: x for x in ver.evidence}
    legend = f"green: hypothesis {ver.chosen} (score {e[ver.chosen].score:.3f})"
    if second is not None:
        legend += f"   red: hypothesis {second} (score {e[second].score:.3f})"
    bar = np.zeros((28, grid.shape[1], 3), dtype=np.uint8)
    cv2.putText(bar, f"{ver.outcome.upper()}  {legend}", (6, 19), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1)
    ok, buf = cv2.imencode(".png", np.concatenate([bar, grid], axis=0))
    assert ok
    return buf.tobytes()


def refusal_message(ver: Verification, out_dir: Path) -> str:
    """The refusal: the failing checks first, then the evidence table, the fix and where the picture is."""
    head = (f"ground truth refused: the image verification found the alignment {ver.outcome.upper()} "
            f"(hypothesis {ver.chosen})")
    lines = [head] + [f"  FAIL {r}" for r in ver.reasons]
    lines.append("  hypotheses (index: image score = edge lift x (1 - free-space violations); cloud F-score):")
    for e in sorted(ver.evidence, key=lambda x: -x.score):
        same = f", look-alike of {e.same_as}" if e.same_as >= 0 else ""
        lines.append(f"    {e.index}: {e.score:.3f} = {e.edge:.3f} x (1 - {e.free_violation:.3f}); cloud "
                     f"{e.cloud_score:.3f}; {e.samples} contour samples, {e.free_rays} rays{same}")
    lines.append(f"  fix: {ver.fix}")
    lines.append(f"  picture of the best two hypotheses: {out_dir / VERIFY_PNG}; evidence: {out_dir / VERIFY_JSON}")
    return "\n".join(lines)


def verify_alignment(cfg: VerifyConfig, rec: Any, images_dir: Path, meshes: Sequence[RenderMesh],
                     hyps: Sequence[Sim3], cloud_scores: Sequence[float], inlier_m: float, out_dir: Path,
                     choice: int | None = None) -> Verification:
    """Verify, write ``verify.json`` and ``hypotheses.png``, and raise unless the outcome is ``ok``.

    Raises:
        VerificationError: outcome ``uncertain`` or ``wrong`` (the message names the checks, the fix and the
            picture); nothing else of the dataset is written.
        InputError: an unreadable frame or a ``choice`` out of range.
    """
    views = load_views(rec, images_dir, cfg.frames)
    rays = free_space_rays(rec, cfg.free_points, cfg.free_obs, cfg.seed)
    ver = verify(views, meshes, hyps, cloud_scores, rays, cfg, inlier_m, choice)
    out_dir = Path(out_dir)
    write_json(out_dir / VERIFY_JSON, ver.summary())
    if views:
        write_bytes(out_dir / VERIFY_PNG, hypotheses_png(views, meshes, ver, cfg.picture_frames))
    if ver.outcome != "ok":
        raise VerificationError(refusal_message(ver, out_dir), ver)
    return ver
