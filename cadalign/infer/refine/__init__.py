"""Refinement of a 6-DoF pose against the CAD model: silhouette/contour alignment and depth ICP.

(a) :func:`refine_silhouette`: damped Gauss-Newton (Levenberg-Marquardt with step acceptance) on the signed
distance transform of the predicted mask, sampled at the projections of the model's outline points: points
on the occluding contour (edges between a front- and a back-facing face) that also lie on the outline of
the model's own rendered silhouette. Each residual is the signed distance (px) of a projected outline point
to the mask boundary, so the outline is pulled onto the zero level set from both sides (a shrunken or
grown silhouette is penalised, unlike a one-sided chamfer); residuals are Huber-weighted and truncated.

(b) :func:`refine_depth_icp`: point-to-plane ICP of surface samples of the CAD to the back-projected depth
inside the (eroded) mask, Huber-weighted, correspondences found in the model frame (one k-d tree per model).

Both update the pose by ``(omega, v)`` (:func:`apply_twist`): a turn about the object's origin in camera axes
and a shift. A point moves as ``X' = X + omega x (X - t) + v``; its projection's Jacobian is
``du/dX [-[X - t]_x, I]``. A Gaussian prior on the deviation from the detector's pose fixes directions the
data do not observe.

The silhouette alignment lives in :mod:`~cadalign.infer.refine.contour_fit`, the depth ICP in
:mod:`~cadalign.infer.refine.depth_icp`, their shared update/solve in :mod:`~cadalign.infer.refine.refine_math`,
:func:`refine` (the two in order, the yaw restarts and the half-turn check) in :mod:`~cadalign.infer.refine.core`;
the yaw restarts are :mod:`~cadalign.infer.refine.hypotheses`, the half-turn check
:mod:`~cadalign.infer.refine.half_turn`, and the multi-frame refit of a static part's world pose
:mod:`~cadalign.infer.refine.track_fit`. The configs are in :mod:`cadalign.infer.config`. This package re-exports
the public functions.
"""

from cadalign.infer.config import REFINE_PRESETS as PRESETS
from cadalign.infer.config import RefineConfig
from cadalign.infer.refine.contour_fit import SignedDistance, refine_silhouette, silhouette_iou
from cadalign.infer.refine.core import RefineResult, pick_fit, refine
from cadalign.infer.refine.depth_icp import (
    ICP_DAMPING,
    depth_along_ray,
    depth_fit,
    icp_points,
    masked_depth_points,
    refine_depth_icp,
)
from cadalign.infer.refine.refine_math import apply_twist

__all__ = [
    "ICP_DAMPING", "PRESETS", "RefineConfig", "RefineResult", "SignedDistance", "apply_twist", "depth_along_ray",
    "depth_fit", "icp_points", "masked_depth_points", "pick_fit", "refine", "refine_depth_icp", "refine_silhouette",
    "silhouette_iou",
]
