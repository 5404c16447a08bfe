"""A ground-truth-free check that an SfM model is not broken: epipolar consistency of consecutive frames.

Around a (near-)symmetric subsea structure the incremental mapper sometimes registers a frame against
look-alike views or from too few points and the rest of the sequence continues from there: the model
is then two rigid pieces joined by a *hinge* (a few degrees of wrong relative rotation at one frame) or
a *fold* (a whole half turned onto the other side). Each piece looks fine on its own (low reprojection
error, every frame registered), so neither COLMAP's statistics nor the later alignment notice it.

Consecutive video frames are the most reliable evidence the database holds: hundreds of verified
matches, small baseline, no look-alike ambiguity. For each consecutive registered pair (in capture
order) this module measures the median Sampson epipolar error of the pair's verified matches under the
*model's* relative pose. In a sound model it is the feature noise (0.2-1 px on the murky default
scene); at a hinge or fold it jumps (3-40 px measured). A pair above ``max_px`` is a *break*.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Break:
    """Consecutive frames whose verified matches disagree with the model's relative pose."""

    frame_a: str
    frame_b: str
    matches: int
    median_px: float


@dataclass(frozen=True)
class Consistency:
    """Result of :func:`sequence_consistency` (errors in pixels)."""

    pairs_checked: int
    median_px: float
    """Median over the checked pairs of their median Sampson error."""
    max_px: float
    breaks: tuple[Break, ...] = field(default_factory=tuple)

    @property
    def ok(self) -> bool:
        return not self.breaks

    def to_dict(self) -> dict[str, Any]:
        return {
            "pairs_checked": self.pairs_checked, "median_px": self.median_px, "max_px": self.max_px,
            "breaks": [{"frames": [b.frame_a, b.frame_b], "matches": b.matches, "median_px": b.median_px}
                       for b in self.breaks],
        }


def sampson_px(xy_a: np.ndarray, xy_b: np.ndarray, R_b_from_a: np.ndarray, t_b_from_a: np.ndarray,
               focal_px: float) -> np.ndarray:
    """Sampson epipolar error (pixels) of normalised image points under a relative pose.

    Args:
        xy_a, xy_b: (N, 2) matched points in normalised (undistorted, K removed) camera coordinates.
        R_b_from_a, t_b_from_a: relative pose of camera b from camera a (any translation scale).
        focal_px: converts the normalised error to pixels.

    Returns:
        (N,) errors; ``inf`` when the baseline is zero (the pose cannot say anything about the pair).
    """
    n = np.linalg.norm(t_b_from_a)
    if not np.isfinite(n) or n <= 1e-12:
        return np.full(len(xy_a), np.inf)
    t = np.asarray(t_b_from_a, dtype=np.float64) / n
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    E = tx @ np.asarray(R_b_from_a, dtype=np.float64)
    xa = np.c_[xy_a, np.ones(len(xy_a))]
    xb = np.c_[xy_b, np.ones(len(xy_b))]
    Exa, Etxb = xa @ E.T, xb @ E
    num = np.sum(xb * Exa, axis=1) ** 2
    den = Exa[:, 0] ** 2 + Exa[:, 1] ** 2 + Etxb[:, 0] ** 2 + Etxb[:, 1] ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        err = np.sqrt(num / den) * focal_px
    return np.where(np.isfinite(err), err, np.inf)


def sequence_consistency(rec: Any, database: Path, names_in_order: Sequence[str], *, max_px: float = 2.0,
                         max_ratio: float = 8.0, min_matches: int = 50) -> Consistency:
    """Check the consecutive registered frames of ``rec`` (a ``pycolmap.Reconstruction``) against the
    verified matches in the COLMAP ``database``; see the module doc.

    A pair is a break when its median error exceeds both ``max_px`` and ``max_ratio`` times the median
    over all checked pairs (so noisier footage does not raise false alarms). Pairs with fewer than
    ``min_matches`` verified matches are not checked (too little evidence).
    """
    import pycolmap  # lazy: heavy dependency (pycolmap)

    registered = {im.name: im for im in rec.images.values() if im.has_pose}
    seq = [n for n in names_in_order if n in registered]
    wanted = {(a, b) for a, b in zip(seq, seq[1:], strict=False)}
    errors: list[tuple[str, str, int, float]] = []
    with pycolmap.Database.open(database) as db:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        for a, b in sorted(wanted, key=lambda p: seq.index(p[0])):
            if a not in ids or b not in ids or not db.exists_two_view_geometry(ids[a], ids[b]):
                continue
            m = np.asarray(db.read_two_view_geometry(ids[a], ids[b]).inlier_matches).reshape(-1, 2)
            if len(m) < min_matches:
                continue
            ia, ib = registered[a], registered[b]
            ka = np.asarray(db.read_keypoints(ids[a]))[m[:, 0], :2]
            kb = np.asarray(db.read_keypoints(ids[b]))[m[:, 1], :2]
            T = ib.cam_from_world() * ia.cam_from_world().inverse()
            err = sampson_px(np.asarray(ia.camera.cam_from_img(ka)), np.asarray(ib.camera.cam_from_img(kb)),
                             T.rotation.matrix(), np.asarray(T.translation), float(ia.camera.mean_focal_length()))
            errors.append((a, b, len(m), float(np.median(err))))
    med = [e[3] for e in errors]
    typical = float(np.median(med)) if med else 0.0
    limit = max(max_px, max_ratio * typical)
    breaks = tuple(Break(a, b, n, e) for a, b, n, e in errors if not e < limit)
    return Consistency(len(errors), typical, float(max(med)) if med else 0.0, breaks)


def pieces(names_in_order: Sequence[str], registered: set[str], breaks: Sequence[Break]) -> list[list[str]]:
    """Split the registered frames (capture order) at the breaks: each piece is rigidly consistent."""
    cut = {(b.frame_a, b.frame_b) for b in breaks}
    out: list[list[str]] = []
    prev = None
    for n in names_in_order:
        if n not in registered:
            continue
        if prev is None or (prev, n) in cut:
            out.append([])
        out[-1].append(n)
        prev = n
    return out


def keep_largest_piece(rec: Any, names_in_order: Sequence[str], cons: Consistency) -> dict[str, str]:
    """Deregister (in place) every frame of ``rec`` outside the largest consistent piece; returns the
    dropped frames with the reason (which break separates them from the kept piece)."""
    registered = {im.name: im for im in rec.images.values() if im.has_pose}
    parts = pieces(names_in_order, set(registered), cons.breaks)
    if len(parts) <= 1:
        return {}
    keep = max(parts, key=len)
    dropped = {}
    for part in parts:
        if part is keep:
            continue
        for n in part:
            rec.deregister_frame(registered[n].frame_id)
            dropped[n] = (f"dropped: beyond an SfM consistency break (kept frames {keep[0]}..{keep[-1]}, "
                          f"{len(keep)} of {len(registered)})")
    return dropped
