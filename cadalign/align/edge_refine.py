"""Edge alignment: one rigid correction of all cameras against the CAD's occluding contours in the images.

The CAD-anchored bundle adjustment (:mod:`cadalign.align.camera_refine`) pins SfM points onto the CAD
surface, which fixes them only along the surface normal: the whole camera rig can still slide along the
structure's large planar faces, and on the default orbit it keeps a shared rotation of ~0.08 deg (0.6 px
at 10 m), about as much as each frame's own error. The images themselves do not slide: the structure's
outline against the water and against farther parts is where the CAD says it is only at the right pose.

For a few frames this module renders the CAD, takes the near side of every depth discontinuity (an
occluding contour) with its image-plane normal, and searches the image along that normal (a 1-D search of
the intensity derivative, with the contrast's sign read at the predicted edge, parabolic sub-pixel peak),
as in model-based edge trackers (RAPID, ViSP's moving edges). One rigid motion of the world about the CAD's
centre is then fitted to all frames' edge offsets by iteratively re-weighted least squares (Tukey), and
the frames are re-rendered and searched again for a few rounds. The correction is applied to every frame
when it is small (it corrects a residual, not a failed alignment) and the fit has enough edges.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from cadalign.geometry.camera import project_jacobian
from cadalign.geometry.rotations import axis_angle_to_matrix, geodesic_angle, matrix_to_axis_angle
from cadalign.types import Progress, Rigid3, Sim3

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class EdgeRefineConfig:
    enabled: bool = True
    """Fit the correction (off: the cameras of the CAD-anchored adjustment are used as they are)."""
    frames: int = 24
    """Frames used for the fit, evenly spaced over the verified frames."""
    rounds: int = 4
    """Render -> search -> fit rounds."""
    search_px: float = 3.0
    """Search range along the contour normal, pixels each way (the correction being fitted is sub-pixel
    to a few pixels; longer searches find other parts' edges)."""
    point_step: int = 2
    """Use every n-th contour pixel (in raster order)."""
    depth_jump: float = 0.05
    """A neighbour farther by this fraction of the near depth (or open water) makes an occluding contour."""
    min_contrast: float = 4.0
    """Weakest accepted edge: intensity step (0-255 grey levels) across the contour."""
    tukey_px: float = 1.5
    """Tukey biweight scale of the edge offsets in the last round, pixels; the first round uses twice this, later rounds
    shrink it linearly. Narrower scales keep too few contour samples: the thinnest part's mask IoU fell on two
    default-orbit builds (docs/tuning/align_edge_refine.md#edgerefineconfigtukey_px)."""
    min_edges: int = 500
    """Fewer matched edges than this in all frames together: no correction."""
    max_turn_deg: float = 0.5
    """A fitted rotation larger than this is not applied (it would not be a residual of a good alignment)."""
    max_shift_m: float = 0.05
    """A fitted translation larger than this is not applied, metres."""
    scale: bool = True
    """The shared correction includes a scale (the alignment's scale error shows in every frame)."""
    max_scale_rel: float = 0.02
    """A fitted scale farther than this from 1 is not applied."""
    per_frame: bool = True
    """Then fit each frame's own correction (its pose error after the shared one is about as large)."""
    frame_prior_px: float = 0.0
    """Weight of a frame's starting pose in its own fit, as the image error (pixels, all its contour samples together)
    that a correction of ``frame_prior_deg`` / ``frame_prior_m`` is worth; 0: no prior, since no weight brought every
    part over 0.95 mask IoU on the two-lap capture (docs/tuning/align_edge_refine.md#edgerefineconfigframe_prior_px)."""
    frame_prior_deg: float = 0.05
    """Typical size of a frame's pose error before its own fit (rotation), degrees."""
    frame_prior_m: float = 0.01
    """Typical size of a frame's pose error before its own fit (translation), metres."""
    min_frame_edges: int = 1000
    """A frame with fewer matched edges keeps its pose: one view's six degrees of freedom need many
    contours spread over the image (a few boxes' outlines leave rotation and translation trading off)."""
    max_frame_turn_deg: float = 0.3
    """A frame's own correction turning the camera more than this is not applied (the frame keeps its pose).
    On a few boxes (tests/render) single-view fits that turn more trade rotation for translation."""
    max_frame_shift_m: float = 0.05
    """A frame's own correction moving the centroid of its contours by more than this (camera frame, metres) is not
    applied; 5 cm lets through the 3-4 cm corrections after a repaired SfM model
    (docs/tuning/align_edge_refine.md#edgerefineconfigmax_frame_shift_m)."""


@dataclass(frozen=True)
class EdgeSet:
    """Contour samples of one frame: camera-frame points, their pixels, normals and image offsets."""

    X_cam: np.ndarray  # (N, 3) metres
    offset_px: np.ndarray  # (N,) signed image edge position along the normal minus the predicted one
    normal: np.ndarray  # (N, 2) unit image-plane normal (towards the far side)


def contour_samples(depth: np.ndarray, rays_unit: np.ndarray, range_m: np.ndarray, cfg: EdgeRefineConfig,
                    instance: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Occluding-contour samples of a rendered view.

    Returns (X_cam (N, 3) near-side surface points, uv (N, 2) sub-pixel predicted contour positions: half a
    pixel from the near pixel's centre towards its far neighbour, normal (N, 2) unit, pointing to the far
    side). A pixel counts once even when several neighbours are far (the normal comes from the inverse-depth
    gradient, not from the neighbour). With ``instance``, only pixels of an object (> 0) are near sides:
    background geometry such as the seabed occludes, but its own outline is no CAD edge."""

    z = np.where(depth > 0, depth, np.inf).astype(np.float64)
    H, W = z.shape
    zj = z * (1.0 + cfg.depth_jump)
    # summed direction to the far 4-neighbours; beyond the image border a pixel is its own neighbour (no contour)
    fx = np.zeros((H, W), dtype=np.int8)
    fy = np.zeros((H, W), dtype=np.int8)
    fx[:, :-1] += z[:, 1:] > zj[:, :-1]
    fx[:, 1:] -= z[:, :-1] > zj[:, 1:]
    fy[:-1] += z[1:] > zj[:-1]
    fy[1:] -= z[:-1] > zj[1:]
    near = (fx != 0) | (fy != 0)
    near &= np.isfinite(z)
    if instance is not None:
        near &= instance > 0
    ys, xs = np.nonzero(near)
    keep = slice(None, None, max(int(cfg.point_step), 1))
    ys, xs = ys[keep], xs[keep]
    far = np.stack([fx[ys, xs], fy[ys, xs]], axis=1).astype(np.float64)
    # the inverse depth's Sobel gradient at those pixels only (as cv2.Sobel, reflect-101 border), negated:
    # towards smaller inverse depth, the far side
    # (summed in cv2's order, so the samples are bit for bit those of the whole-image filter; the inverse depth is
    # taken at the samples' neighbours only)
    ym, yp = _reflect(ys - 1, H), _reflect(ys + 1, H)
    xm, xp = _reflect(xs - 1, W), _reflect(xs + 1, W)

    def inv(r: np.ndarray, c: np.ndarray) -> np.ndarray:
        v = z[r, c]
        return np.where(np.isfinite(v), 1.0 / v, 0.0)

    gx = (inv(ym, xp) - inv(ym, xm)) + (inv(yp, xp) - inv(yp, xm)) + 2 * (inv(ys, xp) - inv(ys, xm))
    gy = (inv(yp, xm) + 2 * inv(yp, xs) + inv(yp, xp)) - (inv(ym, xm) + 2 * inv(ym, xs) + inv(ym, xp))
    n = -np.stack([gx, gy], axis=1)
    norm = np.linalg.norm(n, axis=1)
    ok = (norm > 0) & (np.einsum("nk,nk->n", n, far) > 0)
    ys, xs, n, far = ys[ok], xs[ok], n[ok] / norm[ok, None], far[ok]
    # the contour lies between the near pixel's centre and the far one's: half a pixel along the step
    step = far / np.abs(far).sum(axis=1, keepdims=True).clip(1)
    uv = np.stack([xs, ys], axis=1).astype(np.float64) + 0.5 * step
    X = rays_unit[ys, xs].astype(np.float64) * range_m[ys, xs, None]
    return X, uv, n


def _reflect(i: np.ndarray, n: int) -> np.ndarray:
    """Indices one step outside ``[0, n)`` mirrored without repeating the edge (reflect-101, as cv2's border)."""
    return np.where(i < 0, -i, np.where(i >= n, 2 * (n - 1) - i, i))


def search_edges(gray: np.ndarray, uv: np.ndarray, normal: np.ndarray, cfg: EdgeRefineConfig) -> np.ndarray:
    """Signed offset (pixels, along ``normal``) of the image edge nearest in strength to each predicted
    contour point; NaN where no edge of the expected contrast sign and at least ``min_contrast`` is found
    inside the search range (or the peak lies on the range's end). ``gray`` (H, W) or (H, W, C): with several
    channels each sample takes the channel whose edge is strongest (a yellow part on a white desk differs in
    blue, hardly in grey)."""

    S = float(cfg.search_px)
    if len(uv) == 0 or S < 0.5:  # under half a pixel each way there is no far half to read the contrast from
        return np.full(len(uv), np.nan)
    s = np.arange(-S - 1.0, S + 1.0 + 1e-9, 0.5)  # half-pixel samples
    mx = (uv[:, 0, None] + s[None, :] * normal[:, 0, None]).astype(np.float32)
    my = (uv[:, 1, None] + s[None, :] * normal[:, 1, None]).astype(np.float32)
    prof = cv2.remap(gray, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    # derivative over one pixel (samples two half-steps apart), at s[1:-1]; only its part within the range counts
    sd = s[1:-1]
    i0, i1 = np.flatnonzero(np.abs(sd) <= S)[[0, -1]]
    d = np.subtract(prof[:, i0 + 2:i1 + 3], prof[:, i0:i1 + 1], dtype=np.float64)
    # the contrast's sign: the far half of the range against the near half
    f0, f1 = np.flatnonzero((s >= 0.5) & (s <= S))[[0, -1]]
    n0, n1 = np.flatnonzero((s <= -0.5) & (s >= -S))[[0, -1]]
    sign = np.sign(prof[:, f0:f1 + 1].astype(np.float64).mean(axis=1)
                   - prof[:, n0:n1 + 1].astype(np.float64).mean(axis=1))
    score = d * sign[:, None]
    if score.ndim == 3:  # (N, samples, channels): each sample's strongest channel
        best = np.argmax(score.max(axis=1), axis=1)
        rows = np.arange(len(best))
        score, sign = score[rows, :, best], sign[rows, best]
    k = np.argmax(score, axis=1)
    rows = np.arange(len(k))
    peak = score[rows, k]
    # a peak on the range's end (its neighbour outside the range) gives no sub-pixel position
    ok = (peak >= cfg.min_contrast) & (sign != 0) & (k > 0) & (k < score.shape[1] - 1)
    k1 = np.clip(k, 1, score.shape[1] - 2)
    a, b, c = score[rows, k1 - 1], score[rows, k1], score[rows, k1 + 1]
    a, b, c = np.where(ok, a, 0.0), np.where(ok, b, 1.0), np.where(ok, c, 0.0)
    den = a - 2 * b + c  # < 0 at a strict maximum; a plateau (0) keeps the sample
    frac = 0.5 * (a - c) / np.where(den < 0, den, -np.inf)
    off = sd[i0 + k1] + 0.5 * np.clip(frac, -1.0, 1.0)  # samples are half a pixel apart
    return np.where(ok, off, np.nan)


def edge_jacobian(X_cam: np.ndarray, R_cw: np.ndarray, X_w_rel: np.ndarray, K: np.ndarray,
              normal: np.ndarray, with_scale: bool = False) -> np.ndarray:
    """d(normal . u)/d(omega, t[, sigma]) for the world motion X_w -> c + e^sigma exp(omega)(X_w - c) + t,
    (N, 6) or (N, 7)."""
    dn = np.einsum("nk,nkj->nj", normal, project_jacobian(K, X_cam))  # (N, 3): d(n.u)/dX_cam
    p = X_w_rel
    dXw_dw = np.zeros((len(p), 3, 3))  # d(exp(w) p)/dw at w = 0: -[p]x
    dXw_dw[:, 0, 1], dXw_dw[:, 0, 2] = p[:, 2], -p[:, 1]
    dXw_dw[:, 1, 0], dXw_dw[:, 1, 2] = -p[:, 2], p[:, 0]
    dXw_dw[:, 2, 0], dXw_dw[:, 2, 1] = p[:, 1], -p[:, 0]
    J_rot = np.einsum("nj,jk,nkl->nl", dn, R_cw, dXw_dw)
    J_t = dn @ R_cw
    cols = [J_rot, J_t] + ([np.einsum("nk,nk->n", J_t, p)[:, None]] if with_scale else [])
    return np.concatenate(cols, axis=1)


def fit_correction(rows: Sequence[tuple[np.ndarray, np.ndarray]], tukey_px: float, iterations: int = 10,
                   prior: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """IRLS (Tukey) solution of J xi = -r over all frames' (J, r); returns (xi (6,) or (7,), inlier weights).

    ``prior = (a, precision)``: also penalise ``sum(precision * (a + xi)**2)`` (``a``: the correction already
    made, so the prior holds the total one; ``precision`` in units of squared pixels per squared parameter),
    which keeps directions the edges hardly constrain near where they started."""
    J = np.concatenate([j for j, _ in rows])
    r = np.concatenate([v for _, v in rows])
    xi = np.zeros(J.shape[1])
    w = np.ones(len(r))
    scale = np.full(J.shape[1], 1e-3)  # well-conditioned normal equations
    a, prec = prior if prior is not None else (np.zeros(J.shape[1]), np.zeros(J.shape[1]))
    Js = J * scale
    ridge = np.diag(prec * scale**2) + 1e-9 * np.eye(J.shape[1])
    for _ in range(iterations):
        e = r + J @ xi
        u = e / tukey_px
        w = np.where(np.abs(u) < 1, (1 - u**2) ** 2, 0.0)
        A = Js.T @ (Js * w[:, None]) + ridge
        step = np.linalg.solve(A, -(Js.T @ (w * e) + scale * prec * (a + xi)))
        xi = xi + step * scale
        if np.all(np.abs(step) < 1e-8):
            break
    return xi, w


@dataclass(frozen=True)
class EdgeCorrection:
    """The fitted world similarity and what it rests on; :meth:`camera` applies it to a camera pose."""

    H_world: Sim3  # X -> H X moves the CAD to where the images see it
    applied: bool
    summary: dict[str, Any]

    def camera(self, T_world_from_cam: Rigid3) -> Rigid3:
        return moved_camera(self.H_world, T_world_from_cam) if self.applied else T_world_from_cam


def moved_camera(H: Sim3, T_world_from_cam: Rigid3) -> Rigid3:
    """The camera (CAD frame) that sees each point X where ``T_world_from_cam`` sees H(X): the CAD stays
    metric, the cameras take the correction (a scale of the world is a scale of the camera positions)."""
    T_cw = T_world_from_cam.inverse()
    return Rigid3(T_cw.R @ H.R, (T_cw.R @ H.t + T_cw.t) / H.s).inverse()


def _tukey_schedule(cfg: EdgeRefineConfig) -> np.ndarray:
    return np.linspace(2.0, 1.0, max(int(cfg.rounds), 1)) * cfg.tukey_px


def motion(xi: np.ndarray, centre: np.ndarray) -> Sim3:
    R = axis_angle_to_matrix(xi[:3])
    s = float(np.exp(xi[6])) if len(xi) > 6 else 1.0
    return Sim3(s, R, centre - s * (R @ centre) + xi[3:6])


def frame_rows(renderer: Any, gray: np.ndarray, T_wc: Rigid3, centre: np.ndarray | None, cfg: EdgeRefineConfig,
                with_scale: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(J (N, 6), residuals (N,), world points (N, 3)) of one frame's matched contour samples; ``centre``
    None: the samples' own centroid."""
    f = renderer.render(T_wc, with_full_masks=False)
    X_cam, uv, n = contour_samples(f.depth_m, f.rays_cam, f.range_m, cfg, f.instance)
    if len(X_cam) == 0:
        return None
    off = search_edges(gray, uv, n, cfg)
    ok = np.isfinite(off)
    X_cam, n, off = X_cam[ok], n[ok], off[ok]
    if len(X_cam) == 0:
        return None
    X_w = T_wc.apply(X_cam)
    c = X_w.mean(axis=0) if centre is None else centre
    J = edge_jacobian(X_cam, T_wc.R.T, X_w - c, renderer.camera.K, n, with_scale)
    return J, -off, X_w  # residual: predicted minus found position along n


def _frame_prior(T_start: Rigid3, T_now: Rigid3, centre: np.ndarray, cfg: EdgeRefineConfig,
                 ) -> tuple[np.ndarray, np.ndarray] | None:
    """(correction already made since ``T_start`` in ``motion``'s parameters about ``centre``, precision) of a
    frame's own fit, or None when ``cfg.frame_prior_px`` is 0."""
    return correction_prior(T_start, T_now, centre, cfg.frame_prior_px, cfg.frame_prior_deg, cfg.frame_prior_m)


def correction_prior(T_start: Rigid3, T_now: Rigid3, centre: np.ndarray, prior_px: float, prior_deg: float,
                     prior_m: float) -> tuple[np.ndarray, np.ndarray] | None:
    """``prior`` for :func:`fit_correction` holding the correction made since ``T_start`` (camera poses
    ``T_world_from_cam``; ``motion``'s parameters about ``centre``) near zero: moving ``prior_deg`` or ``prior_m``
    costs as much as a residual of ``prior_px`` pixels; None when ``prior_px`` is 0."""
    if prior_px <= 0:
        return None
    H = T_start @ T_now.inverse()  # the world motion with moved_camera(H, T_start) == T_now
    a = np.concatenate([matrix_to_axis_angle(H.R), H.t - centre + H.R @ centre])
    sig = np.array([np.radians(prior_deg)] * 3 + [prior_m] * 3)
    return a, (prior_px / sig) ** 2


def refine_frame(renderer: Any, gray: np.ndarray, T_wc: Rigid3, cfg: EdgeRefineConfig,
                 ) -> tuple[Rigid3, dict[str, Any]]:
    """One frame's own rigid correction against its contours (after the shared one); the input pose is
    returned unchanged when the frame has too few edges or the correction exceeds the limits."""
    T = T_wc
    n_used, med, seen = 0, None, None
    for tukey in _tukey_schedule(cfg):
        got = frame_rows(renderer, gray, T, None, cfg)
        if got is None or len(got[1]) < cfg.min_frame_edges:
            return T_wc, {"applied": False, "edges": 0 if got is None else len(got[1])}
        J, r, X_w = got
        c = X_w.mean(axis=0)
        seen = c if seen is None else seen
        xi, w = fit_correction([(J, r)], tukey, prior=_frame_prior(T_wc, T, c, cfg))
        n_used, med = len(r), float(np.median(np.abs(r[w > 0]))) if np.any(w > 0) else None
        T = moved_camera(motion(xi, c), T)
    turn = float(np.degrees(geodesic_angle(T_wc.R, T.R)))
    # how far the correction moves what the frame sees (its contours' centroid) in the camera: a turn about
    # that point, which moves the camera centre by distance x angle, does not count twice
    shift = float(np.linalg.norm(T.inverse().apply(seen[None])[0] - T_wc.inverse().apply(seen[None])[0]))
    ok = turn <= cfg.max_frame_turn_deg and shift <= cfg.max_frame_shift_m
    info = {"applied": ok, "edges": n_used, "median_abs_offset_px": med, "turn_deg": turn, "shift_m": shift}
    return (T if ok else T_wc), info


def fit_edge_correction(renderers: Sequence[Any], grays: Sequence[np.ndarray], poses: Sequence[Rigid3],
                        centre: np.ndarray, cfg: EdgeRefineConfig) -> EdgeCorrection:
    """Fit one rigid world motion to the contours of the given frames (renderer, grey image, ``T_world_from_cam``
    each; see the module doc)."""
    H = Sim3.identity()
    history = []
    n_used = 0
    for tukey in _tukey_schedule(cfg):
        rows = []
        for renderer, gray, T in zip(renderers, grays, poses, strict=True):
            got = frame_rows(renderer, gray, moved_camera(H, T), centre, cfg, cfg.scale)
            if got is not None:
                rows.append(got[:2])
        n_used = int(sum(len(r) for _, r in rows))
        if n_used < cfg.min_edges:
            break
        xi, w = fit_correction(rows, tukey)
        r_all = np.concatenate([r for _, r in rows])
        history.append({"edges": n_used, "inliers": int((w > 0).sum()),
                        "median_abs_offset_px": float(np.median(np.abs(r_all[w > 0]))) if np.any(w > 0) else None,
                        "step_deg": float(np.degrees(np.linalg.norm(xi[:3]))), "step_m": float(np.linalg.norm(xi[3:]))})
        H = motion(xi, centre) @ H
    turn = float(np.degrees(geodesic_angle(np.eye(3), H.R)))
    shift = float(np.linalg.norm(H.apply(centre[None])[0] - centre))
    scale_rel = abs(H.s - 1.0)
    applied = (bool(history) and n_used >= cfg.min_edges and turn <= cfg.max_turn_deg and shift <= cfg.max_shift_m
               and scale_rel <= cfg.max_scale_rel)
    summary = {"frames": len(poses), "edges": n_used, "rounds": history, "turn_deg": turn, "shift_m": shift,
               "scale": H.s, "applied": applied}
    if not applied:
        log.warning("edge alignment not applied: %d edges, correction %.3f deg / %.4f m / scale %.4f (limits %d "
                    "edges, %.2f deg, %.3f m, %.3f)", n_used, turn, shift, H.s, cfg.min_edges, cfg.max_turn_deg,
                    cfg.max_shift_m, cfg.max_scale_rel)
    else:
        log.info("edge alignment: %.4f deg / %.2f mm from %d edges in %d frames", turn, 1000 * shift, n_used,
                 len(poses))
    return EdgeCorrection(H, applied, summary)


def edge_align_frames(poses: dict[str, Rigid3], renderer_of: Callable[[str], Any],
                      gray_of: Callable[[str], np.ndarray], centre: np.ndarray, cfg: EdgeRefineConfig,
                      progress: Progress | None = None,
                      ) -> tuple[dict[str, Rigid3], dict[str, dict[str, Any]], dict[str, Any]]:
    """The shared correction fitted on ``cfg.frames`` evenly spaced frames of ``poses`` (name ->
    ``T_world_from_cam``), applied to all of them, then each frame's own correction (``cfg.per_frame``).

    Returns (corrected poses, per-frame info, summary). ``renderer_of(name)`` gives a renderer of the frame's
    camera, ``gray_of(name)`` its grey image (float32, 0-255)."""
    names = sorted(poses)
    if not cfg.enabled or not names:
        return dict(poses), {}, {"applied": False, "frames": 0}
    pick = sorted({names[int(i)] for i in np.linspace(0, len(names) - 1, min(cfg.frames, len(names))).round()})
    shared = fit_edge_correction([renderer_of(n) for n in pick], [gray_of(n) for n in pick],
                                 [poses[n] for n in pick], centre, cfg)
    out = {n: shared.camera(poses[n]) for n in names}
    info: dict[str, dict[str, Any]] = {}
    if cfg.per_frame:
        for n in progress(names, "edge alignment", len(names)) if progress else names:
            out[n], info[n] = refine_frame(renderer_of(n), gray_of(n), out[n], cfg)
    applied = [v for v in info.values() if v["applied"]]
    summary = {"shared": shared.summary, "frames": len(names), "frames_refined": len(applied),
               "frame_turn_deg_median": float(np.median([v["turn_deg"] for v in applied])) if applied else None,
               "frame_shift_mm_median": float(1000 * np.median([v["shift_m"] for v in applied])) if applied else None,
               "median_abs_offset_px": float(np.median([v["median_abs_offset_px"] for v in applied]))
               if applied else None}
    return out, info, summary
