"""One frame's camera pose against the CAD's occluding contours in the image, coarse to fine.

At each level (a scale of the image) the CAD is ray-cast at the current pose with a camera of that size, its
occluding contours are sampled with their image-plane normals
(:func:`cadalign.align.edge_refine.contour_samples`), the image is searched along each normal for the edge of
the expected contrast sign (:func:`~cadalign.align.edge_refine.search_edges`), and one rigid motion is
fitted to the offsets by Tukey IRLS (:func:`~cadalign.align.edge_refine.fit_correction`). A coarse level
with a long search range captures motions of tens of pixels; the finer levels finish to sub-pixel.

The quality of the result is read at the finest level with a short search: the share of contour samples
that have an image edge of the right sign within ``support_px`` (edge support), and their median offset.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np

from cadalign.align.edge_refine import (
    EdgeRefineConfig,
    contour_samples,
    correction_prior,
    edge_jacobian,
    fit_correction,
    motion,
    moved_camera,
    search_edges,
)
from cadalign.geometry import geodesic_angle
from cadalign.geometry.camera import project
from cadalign.infer.track.region import RegionConfig, RegionModel, sample_instances
from cadalign.raycast.core import RaycastRenderer, RenderMesh
from cadalign.types import Camera, Rigid3


@dataclass(frozen=True)
class EdgeLevel:
    """One level of the coarse-to-fine correction."""

    scale: float
    """Image scale of the level (1 = the frame's resolution)."""
    iterations: int
    """Render -> search -> fit rounds at this level (fewer when a round moves less than ``converged_px``)."""
    search_px: float
    """Search range along the contour normal, pixels of this level each way."""
    tukey_px: float
    """Tukey biweight scale of the offsets, pixels of this level."""


@dataclass(frozen=True)
class EdgeTrackConfig:
    """How one frame is corrected against its contours, and how its quality is judged."""

    levels: tuple[EdgeLevel, ...] = (
        EdgeLevel(0.25, 5, 6.0, 4.0),
        EdgeLevel(0.5, 4, 4.0, 2.5),
        EdgeLevel(1.0, 3, 2.5, 1.5),
    )
    """Coarse to fine. The coarsest search reaches 24 px at full resolution: between consecutive frames of a
    survey video (3 deg, 0.5 m apart at 11 m) a constant-velocity prediction is off by less."""
    point_step: int = 1
    """Use every n-th contour pixel (raster order) at each level."""
    fit_step: int = 1
    """The rounds of each level fit every n-th of those samples; the quality is still read on all of them."""
    colour: bool = False
    """Search the edges in the three colour channels (each sample takes its strongest) rather than in grey: a
    part and its background can differ in hue more than in brightness (a yellow part on a white desk). Off: on
    visp_rbt's cluttered desk it found more edges for wrong poses too (docs/tuning/tracker.md)."""
    min_contrast: float = 3.0
    """Weakest accepted edge: grey-level step over one pixel (0-255); turbid water lowers contrast."""
    depth_jump: float = 0.05
    """A neighbour farther by this fraction of the near depth (or open water) makes an occluding contour."""
    min_edges: int = 40
    """Fewer matched contour samples than this at a level: the level is skipped (too little to fit 6 DoF)."""
    converged_px: float = 0.05
    """A round whose fitted motion moves the contours less than this (pixels of the level, RMS) ends the level."""
    reuse_px: float = 0.25
    """The quality is read at the last full-resolution level's render when that level moved the contours by less
    than this (pixels, summed RMS over its rounds); otherwise the CAD is rendered once more at the final pose."""
    min_level_width: int = 64
    """A level whose image would be narrower than this (pixels) is skipped: too few pixels to fit a pose."""
    support_px: float = 1.5
    """An edge within this many full-resolution pixels of a contour sample supports it (quality)."""
    region: RegionConfig = field(default_factory=RegionConfig)
    """Colour-region correspondences beside the edges (:mod:`cadalign.infer.track.region`)."""
    region_support_px: float = 3.0
    """A colour boundary within this many full-resolution pixels of a contour sample supports it (the region
    offset is coarser than the edge's: it rests on whole pixels' colours)."""
    prior_px: float = 0.0
    """Hold the fit's total correction near its start (a Gaussian prior, see :func:`~cadalign.align.edge_refine.
    fit_correction`): moving ``prior_deg`` or ``prior_m`` costs as much as one contour sample off by this many
    pixels. 0: none (a whole structure's contours fix all six degrees of freedom; a lone small part's do not)."""
    prior_deg: float = 2.0
    """See ``prior_px``: the rotation scale, degrees."""
    prior_m: float = 0.05
    """See ``prior_px``: the translation scale, metres."""
    carry_deg: float = 0.0
    """The full-resolution level fits the contours of the last judged render (moved with the pose) instead of
    rendering again when its start turned, and moved as seen from the contours, by at most this (degrees); 0: never."""
    carry_drop: float = 0.05
    """A fit on carried contours whose support is lower than the carried render's by more than this is fitted
    again on fresh renders (docs/tuning/tracker.md#carried-contours-s56)."""


@dataclass(frozen=True)
class EdgeFit:
    """The corrected pose of one frame and what it rests on."""

    T_world_from_cam: Rigid3
    samples: int
    """Contour samples of the CAD at the final pose (full resolution)."""
    support: float
    """Share of those samples with an image edge of the right sign within ``support_px``; 0 without samples."""
    residual_px: float
    """Median |offset| of the supported samples, pixels; NaN without any."""
    instance_support: dict[int, tuple[int, float, float]]
    """Per ray-cast instance: (its contour samples, share supported, concentration: the share of the edges
    found within twice ``support_px`` that lie within ``support_px`` / 1.5 — about 1/3 for edges of texture
    or clutter that only happen to be near, close to 1 for the part's own outline)."""
    instance: np.ndarray | None = None
    """(H, W) ray-cast instance map at the pose (0: background, water)."""
    uv: np.ndarray | None = None
    """(N, 2) contour samples' pixel positions (array convention: pixel centres at integers)."""
    supported: np.ndarray | None = None
    """(N,) bool: the sample has an image edge within ``support_px``."""
    offsets_px: np.ndarray | None = None
    """(N,) the image edge's offset along the normal within twice ``support_px``, full-resolution pixels; NaN:
    none."""
    normal: np.ndarray | None = None
    """(N, 2) the samples' unit normals, towards the far side."""
    sample_instance: np.ndarray | None = None
    """(N,) each sample's ray-cast instance (its part)."""
    region_support: float = float("nan")
    """Share of the samples whose colour boundary (:mod:`~cadalign.infer.track.region`) lies within
    ``region_support_px`` of them; NaN before the tracker has learned the parts' colours."""
    instance_region: dict[int, float] = field(default_factory=dict)
    """Per ray-cast instance: its samples' region support (empty before the colours are learned)."""
    depth_m: np.ndarray | None = None
    """(H, W) the CAD's z-depth at the pose (0: none), the size of ``instance``."""


class EdgeTracker:
    """Renderers of the CAD structure at each level, and the per-frame correction (see the module doc)."""

    def __init__(self, meshes: list[RenderMesh], camera: Camera, cfg: EdgeTrackConfig) -> None:
        self.cfg = cfg
        self.camera = camera
        self._meshes = meshes
        self._renderers: dict[float, RaycastRenderer] = {}
        self.region = RegionModel(cfg.region)
        """The parts' colours, taught by the tracker on tracked frames."""
        self._colour: np.ndarray | None = None
        self._colour_at: dict[int, np.ndarray] = {}  # the colour frame at each level's width, float32
        self._carry: _Judged | None = None  # the last judged render (see EdgeTrackConfig.carry_deg)

    @property
    def colour_frame(self) -> np.ndarray | None:
        """(H, W, 3) the frame being fitted, in colour (the region term's input); None: edges only."""
        return self._colour

    @colour_frame.setter
    def colour_frame(self, rgb: np.ndarray | None) -> None:
        self._colour, self._colour_at = rgb, {}

    def colour_at(self, camera: Camera) -> np.ndarray:
        """The colour frame at a level's size (area-averaged, as stored), float32: made once per frame."""
        assert self._colour is not None
        if camera.width not in self._colour_at:
            rgb = self._colour
            if rgb.shape[1] != camera.width:
                rgb = cv2.resize(rgb, (camera.width, camera.height), interpolation=cv2.INTER_AREA)
            self._colour_at[camera.width] = np.ascontiguousarray(rgb, dtype=np.float32)
        return self._colour_at[camera.width]

    def usable(self, scale: float) -> float:
        """``scale``, or the smallest scale whose image is ``min_level_width`` wide when ``scale``'s is not."""
        return min(max(scale, self.cfg.min_level_width / self.camera.width), 1.0)

    def renderer(self, scale: float = 1.0) -> RaycastRenderer:
        """The CAD's ray caster at an image scale (made on first use)."""
        if scale not in self._renderers:
            c = self.camera
            w, h = max(int(round(c.width * scale)), 8), max(int(round(c.height * scale)), 8)
            cam = c if scale == 1.0 else c.scaled(w, h)
            self._renderers[scale] = RaycastRenderer(self._meshes, cam)
        return self._renderers[scale]

    def _level_cfg(self, search_px: float) -> EdgeRefineConfig:
        c = self.cfg
        return EdgeRefineConfig(search_px=search_px, point_step=c.point_step, depth_jump=c.depth_jump,
                                min_contrast=c.min_contrast)

    def fit(self, gray: np.ndarray, T_world_from_cam: Rigid3, levels: tuple[EdgeLevel, ...] | None = None,
            fit_step: int | None = None) -> EdgeFit:
        """Correct ``T_world_from_cam`` (the prediction) against ``gray`` ((H, W) float32, 0-255, the frame's
        full resolution) and judge the result. ``levels``, ``fit_step``: instead of the config's (e.g. a
        restart's wider basin, fitted on every sample).

        Each level renders the CAD once, at the pose it starts from; its rounds move the contour samples' 3-D
        points with the pose and search again (the contour generator hardly moves within a level's
        correction), as model-based edge trackers do. A fit on carried contours (``carry_deg``) whose support
        falls more than ``carry_drop`` below the carried render's is fitted again on fresh renders, and the
        better-supported of the two is kept."""

        carry = self._carry
        step = self.cfg.fit_step if fit_step is None else fit_step
        fit, carried = self._fit(gray, T_world_from_cam, levels, step, use_carry=True)
        if carried and carry is not None and fit.support < carry.support - self.cfg.carry_drop:
            again, _ = self._fit(gray, T_world_from_cam, levels, step, use_carry=False)
            if again.support > fit.support:
                return again
        return fit

    def _fit(self, gray: np.ndarray, T_world_from_cam: Rigid3, levels: tuple[EdgeLevel, ...] | None,
             fit_step: int, use_carry: bool) -> tuple[EdgeFit, bool]:
        """:meth:`fit`'s levels and judgement; and whether a level fitted carried contours."""
        T = T_world_from_cam
        last: tuple[Any, np.ndarray, Any] | None = None
        any_carried = False
        for lv in self.cfg.levels if levels is None else levels:
            if self.usable(lv.scale) != lv.scale:  # too small an image to fit (a small video's coarse levels)
                continue
            r = self.renderer(lv.scale)
            g = gray if lv.scale == 1.0 else cv2.resize(gray, (r.camera.width, r.camera.height),
                                                          interpolation=cv2.INTER_AREA)
            lcfg = self._level_cfg(lv.search_px)
            carried = self._carried(T) if lv.scale == 1.0 and use_carry else None
            if carried is not None:
                X_w, uv0, n, f = carried.X_w, carried.uv, carried.normal, carried.frame
                any_carried = True
            else:
                f = r.render(T, with_full_masks=False, with_normals=False)
                X_cam, uv0, n = contour_samples(f.depth_m, f.rays_cam, f.range_m, lcfg, f.instance)
                X_w = T.apply(X_cam)
            if len(X_w) < self.cfg.min_edges:
                continue  # too few contours to fit six degrees of freedom
            last = (r, X_w, n, f, g) if carried is None else None
            if fit_step > 1:
                X_w, uv0, n = X_w[::fit_step], uv0[::fit_step], n[::fit_step]
            region = self._region_level(r, uv0, n, f.instance)
            T_start, s_start, moved_px = T, None, 0.0
            for _ in range(lv.iterations):
                off, roff = self._both_offsets(T, X_w, n, r, g, lcfg, region, lv.search_px)
                ok, rok = np.isfinite(off), np.isfinite(roff)
                if s_start is None:
                    s_start = _share_within(off, lv.tukey_px / 2) + _share_within(roff, lv.tukey_px / 2)
                if ok.sum() + rok.sum() < self.cfg.min_edges:
                    break
                Xc = T.inverse().apply(X_w)
                c = X_w[ok | rok].mean(axis=0)
                J = edge_jacobian(Xc, T.R.T, X_w - c, r.camera.K, n)
                xi, w = fit_correction([(J[ok], -off[ok]), (J[rok], -roff[rok])], lv.tukey_px,
                                       prior=correction_prior(T_world_from_cam, T, c, self.cfg.prior_px,
                                                              self.cfg.prior_deg, self.cfg.prior_m))
                T = moved_camera(motion(xi, c), T)
                Jw = np.concatenate([J[ok], J[rok]])[w > 0]
                moved = Jw @ xi if len(Jw) else np.zeros(1)
                moved_px += float(np.sqrt(np.mean(moved**2)))
                if float(np.sqrt(np.mean(moved**2))) < self.cfg.converged_px:
                    break
            # a level that leaves fewer contour samples on image edges (and colour boundaries) than it found ran
            # off (a coarse level's long search caught other parts' edges): keep the pose it started from
            if s_start is not None and T is not T_start:
                off, roff = self._both_offsets(T, X_w, n, r, g, lcfg, region, lv.search_px)
                if _share_within(off, lv.tukey_px / 2) + _share_within(roff, lv.tukey_px / 2) < s_start:
                    T, moved_px = T_start, 0.0
        # judged at the final pose (its instance map gives the parts' masks): the last full-resolution level's
        # render serves when that level moved the contours by less than reuse_px, else one more render
        if last is not None and last[0] is self.renderer(1.0) and moved_px < self.cfg.reuse_px:
            return self._judge_last(T, last), any_carried
        return self.judge(gray, T), any_carried

    def _region_level(self, r: RaycastRenderer, uv: np.ndarray, n: np.ndarray, instance: np.ndarray,
                      ) -> tuple[np.ndarray, np.ndarray] | None:
        """(the colour frame at the level's size, each contour sample's part) when the region term is on."""
        if self.colour_frame is None or not self.region.ready:
            return None
        return self.colour_at(r.camera), sample_instances(uv, n, instance)

    def _both_offsets(self, T: Rigid3, X_w: np.ndarray, n: np.ndarray, r: RaycastRenderer, g: np.ndarray,
                      cfg: EdgeRefineConfig, region: tuple[np.ndarray, np.ndarray] | None, search_px: float,
                      ) -> tuple[np.ndarray, np.ndarray]:
        """(edge offsets, region offsets) of contour points ``X_w`` seen from ``T``, pixels of the level (NaN:
        none; all NaN region offsets without the region term)."""
        uv = array_pixels(r.camera.K, T.inverse().apply(X_w)) + 0.5 * n
        off = search_edges(g, uv, n, cfg)
        if region is None:
            return off, np.full(len(off), np.nan)
        return off, self.region.offsets(region[0], uv, n, region[1], search_px)

    def _judge_last(self, T: Rigid3, last: tuple) -> EdgeFit:
        """Judge at the last level's render, its contour points moved to the final pose (no render more)."""
        r, X_w, n, f, g = last
        s = r.camera.width / self.camera.width
        cfg = self._level_cfg(2.0 * self.cfg.support_px * s)
        Xc = T.inverse().apply(X_w)
        uv = array_pixels(r.camera.K, Xc) + 0.5 * n
        return self._support(T, uv, n, g, f.instance, cfg, self.cfg.support_px * s, 1.0 / s, f.depth_m)

    def _carried(self, T: Rigid3) -> _Judged | None:
        """The last judged render when ``T`` is near its pose (``carry_deg``), else None."""
        c = self._carry
        if not self.cfg.carry_deg or c is None:
            return None
        turn = np.degrees(geodesic_angle(c.T_world_from_cam.R, T.R))
        seen_turn = np.degrees(np.linalg.norm(c.T_world_from_cam.t - T.t) / c.depth_m)  # as seen from the contours
        return c if turn <= self.cfg.carry_deg and seen_turn <= self.cfg.carry_deg else None

    def snapshot(self) -> tuple[RegionModel, _Judged | None]:
        """What fits leave for the next frame's: the parts' colours and the last judged render (``carry_deg``); give
        it to :meth:`restore` to undo fits tried aside."""
        return self.region, self._carry

    def restore(self, snapshot: tuple[RegionModel, _Judged | None]) -> None:
        """Back to a :meth:`snapshot`."""
        self.region, self._carry = snapshot

    def judge(self, gray: np.ndarray, T_world_from_cam: Rigid3) -> EdgeFit:
        """Edge support of the CAD's contours at ``T_world_from_cam`` in ``gray`` (full resolution)."""
        r = self.renderer(1.0)
        f = r.render(T_world_from_cam, with_full_masks=False, with_normals=False)
        cfg = self._level_cfg(2.0 * self.cfg.support_px)
        X_cam, uv0, n = contour_samples(f.depth_m, f.rays_cam, f.range_m, cfg, f.instance)
        fit = self._support(T_world_from_cam, array_pixels(r.camera.K, X_cam) + 0.5 * n, n, gray, f.instance, cfg,
                            self.cfg.support_px, 1.0, f.depth_m)
        if self.cfg.carry_deg:
            self._carry = _Judged(T_world_from_cam, T_world_from_cam.apply(X_cam), uv0, n, f,
                                  float(np.median(X_cam[:, 2])) if len(X_cam) else np.inf, fit.support)
        return fit

    def _support(self, T: Rigid3, uv: np.ndarray, n: np.ndarray, g: np.ndarray, instance: np.ndarray,
                 cfg: EdgeRefineConfig, tol_px: float, to_full: float, depth_m: np.ndarray | None = None) -> EdgeFit:
        if len(uv) == 0:
            return EdgeFit(T, 0, 0.0, float("nan"), {}, instance, uv, np.zeros(0, bool), np.zeros(0),
                           depth_m=depth_m)
        off = search_edges(g, uv, n, cfg)
        ok = np.isfinite(off) & (np.abs(np.nan_to_num(off, nan=np.inf)) <= tol_px)
        inst = sample_instances(uv, n, instance)  # the part of each sample's near pixel
        found = np.isfinite(off)
        near = found & (np.abs(np.nan_to_num(off, nan=np.inf)) <= tol_px / 1.5)
        n_k = np.bincount(inst)  # per part (ray-cast instance ids are small non-negative integers)
        ok_k, near_k, found_k = (np.bincount(inst, w, minlength=len(n_k)) for w in (ok, near, found))
        per = {int(k): (int(n_k[k]), float(ok_k[k] / n_k[k]), float(near_k[k] / max(found_k[k], 1)))
               for k in np.flatnonzero(n_k)}
        res = float(np.median(np.abs(off[ok]))) * to_full if ok.any() else float("nan")
        rsup, rper = self._region_support(uv, n, inst, g.shape[:2], to_full)
        return EdgeFit(T, len(off), float(ok.mean()), res, per, instance, uv * to_full, ok, off * to_full, n,
                       inst, rsup, rper, depth_m)


    def _region_support(self, uv: np.ndarray, n: np.ndarray, inst: np.ndarray, shape: tuple[int, ...],
                        to_full: float) -> tuple[float, dict[int, float]]:
        """(share of samples on a colour boundary, the same per instance); NaN, {} without the region term."""
        rgb = self.colour_frame
        if rgb is None or not self.region.ready or rgb.shape[:2] != shape or len(uv) == 0:
            return float("nan"), {}
        tol = self.cfg.region_support_px / to_full
        roff = self.region.offsets(self.colour_at(self.camera), uv, n, inst, 2 * tol)
        rok = np.abs(np.nan_to_num(roff, nan=np.inf)) <= tol
        n_k = np.bincount(inst)
        rok_k = np.bincount(inst, rok, minlength=len(n_k))
        return float(rok.mean()), {int(k): float(rok_k[k] / n_k[k]) for k in np.flatnonzero(n_k)}

    def with_region(self, fit: EdgeFit) -> EdgeFit:
        """``fit`` (full resolution) with its region support read again, e.g. once the colours were learned on
        its own frame (the first frame of a track: an absent part's outline separates nothing even then)."""
        if fit.uv is None or fit.normal is None or fit.sample_instance is None or fit.instance is None:
            return fit
        rsup, rper = self._region_support(fit.uv, fit.normal, fit.sample_instance, fit.instance.shape, 1.0)
        return replace(fit, region_support=rsup, instance_region=rper)


@dataclass(frozen=True)
class _Judged:
    """A judged full-resolution render, kept for the next frame's level (``EdgeTrackConfig.carry_deg``)."""

    T_world_from_cam: Rigid3
    X_w: np.ndarray  # (N, 3) its contour samples' points, world metres
    uv: np.ndarray  # (N, 2) their pixels in the render
    normal: np.ndarray  # (N, 2)
    frame: Any  # the RaycastFrame (its instance map gives the samples' parts)
    depth_m: float  # the samples' median depth
    support: float  # the judgement's edge support


def _share_within(off: np.ndarray, tol_px: float) -> float:
    """Share of samples whose image edge lies within ``tol_px`` (NaN: none found)."""
    return float(np.mean(np.abs(np.nan_to_num(off, nan=np.inf)) <= tol_px)) if len(off) else 0.0


def array_pixels(K: np.ndarray, X_cam: np.ndarray) -> np.ndarray:
    """(N, 2) array-convention pixel positions (centres at integers) of camera-frame points; a point behind the
    camera lands far outside the image."""
    uv, valid = project(K, X_cam)
    # a point behind the camera goes far outside the image, where the search finds no edge
    return np.where(valid[:, None], uv - 0.5, -1e4)


def as_gray(image: np.ndarray, colour: bool = False) -> np.ndarray:
    """The frame as the edge search reads it: (H, W) float32 grey levels 0-255 of an RGB uint8 (or already
    grey) image, or with ``colour`` the (H, W, 3) channels as float32 (each edge sample then takes its strongest
    channel, :func:`~cadalign.align.edge_refine.search_edges`)."""

    if image.ndim == 3 and colour:
        return np.ascontiguousarray(image[..., :3], dtype=np.float32)
    if image.ndim == 3:
        image = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY)
    return image.astype(np.float32)


def with_levels(cfg: EdgeTrackConfig, **changes: Any) -> EdgeTrackConfig:
    """``cfg`` with every level's fields changed as given (e.g. ``iterations=1``)."""
    return replace(cfg, levels=tuple(replace(lv, **changes) for lv in cfg.levels))
