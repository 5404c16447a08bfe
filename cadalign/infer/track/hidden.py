"""Is a part there? The contours of the structure that it would hide.

A part in front of the structure hides some of the structure's own occluding contours (a beam's outline behind a
valve). Where the part is present the image shows its surface there, not those contours; where it is absent the
image shows them as at any other place of the structure. This cue does not depend on the part's own contrast,
which fails for a faint part (a dark valve on dark water) as for an absent one.

The structure here is the parts of class ``structure`` (the frame, plates, panels: the eval's ignored class);
the other parts (valves, hot stabs) are the ones checked. Its contours are ray-cast without the checked parts at
half resolution, and those whose near pixel lies in a checked part's visible mask (at full resolution) are searched
for an image edge as the tracker's quality test does.

Those at least twice the search's tolerance inside the part's visible outline are counted apart ("deep"): the
part's own outline cannot explain an edge found there, so many of them showing is evidence that the part is absent
(a thin part, a hot stab, has none).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import cv2
import numpy as np

from cadalign.align.edge_refine import EdgeRefineConfig, contour_samples, search_edges
from cadalign.infer.track.edges import array_pixels
from cadalign.raycast.core import RaycastRenderer
from cadalign.sim.structure import Structure
from cadalign.types import Camera

if TYPE_CHECKING:
    from cadalign.infer.track.tracker import TrackStep

BACKGROUND_CLASS = "structure"


class HiddenSeen(NamedTuple):
    """What the image shows of the structure's contours one part hides."""

    samples: int
    """Hidden contour samples (half-resolution cast)."""
    seen: float
    """Share of them with an image edge."""
    deep_samples: int
    """Those at least twice ``support_px`` inside the part's visible outline (3 px at the tracker's 1.5), where an
    edge of the outline itself is too far to support them."""
    deep_seen: float
    """Share of those with an image edge; NaN without any."""


class HiddenContours:
    """The structure's contours that each checked part hides at a tracked pose, and the share the image shows."""

    def __init__(self, structure: Structure, camera: Camera, scale: float = 0.5) -> None:
        meshes = [m for m in structure.render_meshes() if structure.class_names[m.class_id] == BACKGROUND_CLASS]
        self.background = {m.instance for m in meshes}
        self.camera = camera
        small = camera.scaled(max(int(round(camera.width * scale)), 8), max(int(round(camera.height * scale)), 8))
        self.renderer = RaycastRenderer(meshes, small) if meshes else None

    def seen(self, gray: np.ndarray, step: TrackStep, support_px: float = 1.5, min_contrast: float = 3.0,
             ) -> dict[int, HiddenSeen]:
        """Per checked part (ray-cast instance) visible in a tracked frame: the structure's contour samples it
        hides and the share of them with an image edge of at least ``min_contrast`` within ``support_px``
        full-resolution pixels (as the tracker's quality test reads edges), all and deep (:class:`HiddenSeen`); empty
        for a lost frame or a structure without background parts."""
        fit = step.fit
        if self.renderer is None or step.T_cam_from_world is None or fit is None or fit.instance is None:
            return {}
        f = self.renderer.render(step.T_cam_from_world.inverse(), with_full_masks=False, with_normals=False)
        X_cam, _, n = contour_samples(f.depth_m, f.rays_cam, f.range_m, EdgeRefineConfig(point_step=1), f.instance)
        if len(X_cam) == 0:
            return {}
        uv = array_pixels(self.camera.K, X_cam) + 0.5 * n  # half a pixel towards the far side, as the tracker's
        H, W = fit.instance.shape
        near = np.floor(uv - 0.5 * n + 0.5).astype(int)
        ok = (near[:, 0] >= 0) & (near[:, 0] < W) & (near[:, 1] >= 0) & (near[:, 1] < H)
        part = np.zeros(len(uv), dtype=np.int64)
        part[ok] = fit.instance[near[ok, 1], near[ok, 0]]
        hidden = (part > 0) & ~np.isin(part, list(self.background))
        if not hidden.any():
            return {}
        cfg = EdgeRefineConfig(search_px=2.0 * support_px, min_contrast=min_contrast)
        off = search_edges(gray, uv[hidden], n[hidden], cfg)
        edge = np.abs(np.nan_to_num(off, nan=np.inf)) <= support_px
        k_h = part[hidden]
        n_k = np.bincount(k_h)
        seen_k = np.bincount(k_h, edge, minlength=len(n_k))
        # the outline lies half a pixel beyond the centre of the nearest pixel of another instance
        deep = _inside_by(fit.instance)[near[hidden, 1], near[hidden, 0]] + 0.5 >= 2.0 * support_px
        nd_k = np.bincount(k_h, deep, minlength=len(n_k))
        sd_k = np.bincount(k_h, deep & edge, minlength=len(n_k))
        return {int(k): HiddenSeen(int(n_k[k]), float(seen_k[k] / n_k[k]), int(nd_k[k]),
                                   float(sd_k[k] / nd_k[k]) if nd_k[k] else float("nan")) for k in np.flatnonzero(n_k)}


def _inside_by(instance: np.ndarray) -> np.ndarray:
    """(H, W) distance of each pixel's centre to the nearest pixel on either side of a change of instance (the
    visible outlines), pixels."""
    outline = np.zeros(instance.shape, dtype=np.uint8)
    across = instance[:, 1:] != instance[:, :-1]
    down = instance[1:, :] != instance[:-1, :]
    outline[:, 1:] |= across
    outline[:, :-1] |= across
    outline[1:, :] |= down
    outline[:-1, :] |= down
    return cv2.distanceTransform(1 - outline, cv2.DIST_L2, 3)
