"""The prediction from the image: model-based visual odometry between the last tracked frame and this one.

Corners inside the parts' silhouettes at the last tracked pose get their 3-D points from the CAD's depth there;
pyramidal Lucas-Kanade follows them into the new frame (checked forward and backward), and PnP with RANSAC
turns the 2-D/3-D pairs into the new camera pose. Unlike a constant-velocity guess, this follows a hand-held
jerk or a survey's 60 px steps between frames, which the contour fit's search range (~24 px) does not reach.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from cadalign.geometry.camera import backproject
from cadalign.types import Rigid3


@dataclass(frozen=True)
class FlowConfig:
    """Sparse flow from the last tracked frame and PnP (see the module doc)."""

    enabled: bool = True
    """Predict each frame's pose from the flow when it succeeds (else: constant velocity)."""
    max_points: int = 400
    """Corners followed per frame."""
    min_distance_px: float = 8.0
    """Least distance between two corners, pixels."""
    quality: float = 0.001
    """Corner quality relative to the strongest (OpenCV ``goodFeaturesToTrack``); low, because specks of marine
    snow are the strongest corners of a turbid frame and would silence the structure's texture."""
    inset_px: int = 3
    """Corners lie at least this far inside a part's silhouette: the depth at an outline belongs to either side."""
    window_px: int = 21
    """Lucas-Kanade window, pixels."""
    pyramid_levels: int = 4
    """Pyramid levels above the frame: motions of ~2^levels x window / 2 pixels are followed."""
    lk_iterations: int = 30
    """Lucas-Kanade iterations per pyramid level at most (OpenCV's termination count)."""
    lk_eps_px: float = 0.01
    """... or fewer once an iteration moves a corner by less than this, pixels (OpenCV's epsilon)."""
    max_fb_px: float = 1.0
    """A corner followed forward then backward must land within this of where it started, pixels."""
    ransac_px: float = 2.0
    """PnP RANSAC inlier threshold, pixels."""
    min_inliers: int = 20
    """Fewer PnP inliers: no prediction from the flow."""
    min_inlier_share: float = 0.5
    """... or fewer than this share of the followed corners."""


class FlowPredictor:
    """Keeps the last tracked frame (grey image, corners, their world points) and predicts the next pose."""

    def __init__(self, K: np.ndarray, cfg: FlowConfig) -> None:
        self.cfg = cfg
        self.K = np.asarray(K, dtype=np.float64)
        self._gray: np.ndarray | None = None
        self._pts: np.ndarray | None = None  # (N, 2) float32, array convention (centres at integers)
        self._X_w: np.ndarray | None = None  # (N, 3) world points

    @property
    def ready(self) -> bool:
        return self._gray is not None and self._pts is not None and len(self._pts) >= self.cfg.min_inliers

    def remember(self, gray: np.ndarray, depth_m: np.ndarray, instance: np.ndarray,
                 T_world_from_cam: Rigid3) -> None:
        """Keep a tracked frame: ``gray`` (H, W), the CAD's z-depth and instance map at its pose (same size)."""
        if not self.cfg.enabled or depth_m.shape != gray.shape:
            self._gray = None
            return
        inside = (instance > 0) & (depth_m > 0)
        mask = cv2.erode(inside.astype(np.uint8), np.ones((2 * self.cfg.inset_px + 1,) * 2, np.uint8))
        img = np.clip(gray, 0, 255).astype(np.uint8)
        pts = cv2.goodFeaturesToTrack(img, self.cfg.max_points, self.cfg.quality, self.cfg.min_distance_px,
                                      mask=mask)
        if pts is None:
            self._gray = None
            return
        pts = pts.reshape(-1, 2)
        x, y = np.round(pts[:, 0]).astype(int), np.round(pts[:, 1]).astype(int)
        z = depth_m[y, x].astype(np.float64)
        ok = z > 0
        X_cam, _ = backproject(self.K, pts[ok].astype(np.float64) + 0.5, z[ok])  # + 0.5: to K's convention
        self._gray, self._pts, self._X_w = img, pts[ok].astype(np.float32), T_world_from_cam.apply(X_cam)

    def predict(self, gray: np.ndarray, guess: Rigid3 | None) -> Rigid3 | None:
        """``T_world_from_cam`` of ``gray`` from the flow, or None (no kept frame, too few corners followed, or
        PnP found too few inliers). ``guess``: a prior pose for PnP (e.g. the constant-velocity one)."""
        if not self.ready:
            return None
        assert self._gray is not None and self._pts is not None and self._X_w is not None
        img = np.clip(gray, 0, 255).astype(np.uint8)
        lk = {"winSize": (self.cfg.window_px, self.cfg.window_px), "maxLevel": self.cfg.pyramid_levels,
              "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, self.cfg.lk_iterations, self.cfg.lk_eps_px)}
        p0 = self._pts.reshape(-1, 1, 2)
        p1, st, _ = cv2.calcOpticalFlowPyrLK(self._gray, img, p0, None, **lk)
        if p1 is None:
            return None
        back, st2, _ = cv2.calcOpticalFlowPyrLK(img, self._gray, p1, None, **lk)
        fb = np.linalg.norm(back.reshape(-1, 2) - self._pts, axis=1)
        ok = (st.ravel() == 1) & (st2.ravel() == 1) & (fb <= self.cfg.max_fb_px)
        if ok.sum() < self.cfg.min_inliers:
            return None
        obj = self._X_w[ok]
        img_pts = p1.reshape(-1, 2)[ok].astype(np.float64) + 0.5  # to K's convention
        kw: dict = {}
        if guess is not None:
            T_cw = guess.inverse()
            kw = {"rvec": cv2.Rodrigues(T_cw.R)[0], "tvec": T_cw.t.reshape(3, 1).copy(), "useExtrinsicGuess": True}
        found, rvec, tvec, inl = cv2.solvePnPRansac(obj, img_pts, self.K, None, iterationsCount=200,
                                                   reprojectionError=self.cfg.ransac_px, confidence=0.999,
                                                   flags=cv2.SOLVEPNP_ITERATIVE, **kw)
        n_in = 0 if inl is None else len(inl)
        if not found or n_in < self.cfg.min_inliers or n_in < self.cfg.min_inlier_share * ok.sum():
            return None
        R, _ = cv2.Rodrigues(rvec)
        return Rigid3(R, tvec.ravel()).inverse()
