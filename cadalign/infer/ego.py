"""Camera poses from the static parts themselves, for video without camera poses (temporal mode ``ego``).

A part that does not move fixes the camera: an observation ``T_cam_from_obj`` of a part whose world pose a
track holds gives ``T_world_from_cam = T_world_from_obj T_cam_from_obj^-1``. Every (observation, compatible
track) pair, with every discrete symmetric equivalent of the observation, is a hypothesis. The hypothesis that
puts the most observations within their gate of a compatible track wins (ties: nearest to the constant-velocity
prediction of the camera, else the smaller summed distance), and the camera pose is the robust mean of the
hypotheses of its inliers, each observation taking the symmetric equivalent closest to the winner. A flipped or
misplaced part (a network's 180 deg ball valve) outvotes nothing and is down-weighted in the mean. Parts with a
continuous symmetry make no hypotheses (their spin, hence the camera's position about their axis, is unknown)
but count as inliers and join the mean.

The "world" of such a video is the camera frame of its first frame with observations. The camera itself follows a
constant-velocity model on SE(3) (:func:`predict_camera`): the prediction breaks ties, and stands in for a frame
that no known part registers (:class:`cadalign.infer.temporal.TemporalFuser` decides for how long).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from cadalign.cad.symmetry import Symmetry
from cadalign.errors import DegenerateGeometryError
from cadalign.geometry.umeyama import kabsch
from cadalign.infer.pose_math import Observation, apply_twist_camera, canonicalize, robust_mean, twist_between
from cadalign.infer.refine.refine_math import huber_weights
from cadalign.types import Rigid3


def fixed_point(symmetry: Symmetry | None) -> np.ndarray:
    """(3,) a model-frame point every symmetry transform keeps: a point on the continuous axis, the centroid of
    the origin's orbit under a discrete group, the origin without symmetry. Its world position does not depend on
    which symmetric equivalent a pose is, so it compares poses before they are canonicalised."""
    if symmetry is None or symmetry.kind == "none":
        return np.zeros(3)
    if symmetry.kind == "continuous":
        return np.asarray(symmetry.offset_m, float)
    return np.mean([np.zeros(3), *[np.asarray(S)[:3, 3] for S in symmetry.discrete]], axis=0)


def _equivalents(T: Rigid3, symmetry: Symmetry) -> list[Rigid3]:
    if symmetry.kind == "continuous":
        return []
    M = T.matrix()
    return [T, *[Rigid3.from_matrix(M @ np.asarray(S)) for S in symmetry.discrete]]


def register_camera(obs: Sequence[Observation], cands: Sequence[Sequence[int]], track_T: Sequence[Rigid3],
                    gates: Sequence[float], huber_t_m: float, huber_r_rad: float,
                    C_pred: Rigid3 | None = None, min_spread: float = 0.1) -> tuple[Rigid3 | None, list[int]]:
    """``T_world_from_cam`` of a frame from its observations of static parts whose world poses are known.

    ``obs``: the frame's observations; ``cands[i]``: indices into ``track_T`` (world-from-obj poses) of the tracks
    observation ``i`` may belong to (same class / model); ``gates[i]``: its association distance (m). Returns the
    camera pose and the indices of the inlier observations, or ``(None, [])`` when no hypothesis has an inlier.
    The pose is then refitted to the inliers' positions (:func:`_fit_positions`, ``min_spread``).
    """

    fixed = [fixed_point(o.symmetry) for o in obs]
    pair_i = np.array([i for i in range(len(obs)) for _ in cands[i]], dtype=np.int64)
    pair_k = [k for i in range(len(obs)) for k in cands[i]]
    hyps = [track_T[k] @ T_eq.inverse() for i, k in zip(pair_i, pair_k, strict=True)
            for T_eq in _equivalents(obs[i].T_cam_from_obj, obs[i].symmetry)]
    if not hyps:
        return None, []
    p_cam = np.array([o.T_cam_from_obj.apply(fixed[i][None])[0] for i, o in enumerate(obs)])  # (n, 3)
    p_world = np.array([track_T[k].apply(fixed[i][None])[0] for i, k in zip(pair_i, pair_k, strict=True)])  # (P, 3)
    R = np.stack([C.R for C in hyps])  # (H, 3, 3)
    t = np.stack([C.t for C in hyps])  # (H, 3)
    placed = np.einsum("hab,nb->hna", R, p_cam) + t[:, None]  # every observation placed by every hypothesis
    d = np.linalg.norm(placed[:, pair_i] - p_world[None], axis=2)  # (H, P)
    starts = np.flatnonzero(np.r_[True, pair_i[1:] != pair_i[:-1]])  # pairs are grouped by observation
    obs_with = pair_i[starts]
    d_min = np.minimum.reduceat(d, starts, axis=1)  # (H, observations with a candidate)
    ok = d_min < np.asarray(gates, float)[obs_with][None]
    count = ok.sum(1)
    tie = np.linalg.norm(t - C_pred.t, axis=1) if C_pred is not None else np.where(ok, d_min, 0.0).sum(1)
    b = int(np.lexsort((tie, -count))[0])
    if count[b] == 0:
        return None, []
    C_best = hyps[b]
    ins = obs_with[ok[b]].tolist()
    per_obs, p_c, p_w = [], [], []
    for i in ins:
        o = obs[i]
        j = np.flatnonzero(pair_i == i)
        j = int(j[np.argmin(d[b, j])])  # the nearest candidate track under the winner
        T_wo = track_T[pair_k[j]]
        M = canonicalize(C_best @ o.T_cam_from_obj, o.symmetry, T_wo.R)  # world-from-obj, nearest equivalent
        per_obs.append(T_wo @ M.inverse() @ C_best)  # the camera pose this observation alone implies
        p_c.append(p_cam[i])
        p_w.append(p_world[j])
    C = robust_mean(per_obs, huber_t_m, huber_r_rad)
    return _fit_positions(C, np.array(p_c), np.array(p_w), huber_t_m, min_spread), ins


def _fit_positions(C: Rigid3, p_cam: np.ndarray, p_world: np.ndarray, huber_t_m: float, min_spread: float,
                   iters: int = 5) -> Rigid3:
    """``C`` refitted to the parts' positions (N, 3) in camera and world: Huber-IRLS Kabsch when at least three
    parts spread beyond a line (second principal spread >= ``min_spread`` times the first), else only the
    translation (the rotation of ``C`` kept).

    A part's position is known far better than its orientation (the default orbit's refined valves: 1 mm vs
    0.2 deg median at 10 m), and a camera pose taken from one part's orientation is off by that angle times
    the distance at the other parts: the mean of such poses put them 4 cm off."""
    w = np.ones(len(p_cam))
    x = p_cam - p_cam.mean(0)
    sv = np.linalg.svd(x, compute_uv=False) if len(x) >= 3 else np.zeros(2)
    rotate = len(x) >= 3 and sv[0] > 0 and sv[1] >= min_spread * sv[0]
    R = C.R
    for _ in range(iters):
        if rotate:
            try:
                R = kabsch(p_cam, p_world, w).R
            except DegenerateGeometryError:  # the correspondences do not fix a rotation: keep the last one
                rotate = False
        r = p_world - p_cam @ R.T
        t = (w[:, None] * r).sum(0) / w.sum()
        w = huber_weights(np.linalg.norm(r - t, axis=1), huber_t_m)
    return Rigid3(R, t)


def predict_camera(history: Sequence[tuple[int, Rigid3]], frame: int) -> Rigid3 | None:
    """The constant-velocity prediction of ``T_world_from_cam`` at ``frame`` from the last two (frame, pose)
    entries of ``history`` (the last pose alone with one entry; None with none). The per-frame motion is the
    left twist between them (:func:`cadalign.infer.temporal.twist_between`) scaled by the frame gap."""

    if not history:
        return None
    f1, C1 = history[-1]
    if len(history) < 2:
        return C1
    f0, C0 = history[-2]
    xi = twist_between(C0, C1) / max(f1 - f0, 1)
    return apply_twist_camera(xi * (frame - f1), C1) if math.isfinite(float(xi.sum())) else C1
