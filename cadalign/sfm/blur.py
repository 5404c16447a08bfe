"""Blur judged by what SfM needs: a soft frame that still matches its neighbour is kept.

Sharpness (variance of the Laplacian) only says a frame is softer than its neighbours; whether it would
register depends on whether its features still match theirs. :class:`MatchCheck` counts verified ORB matches
(cross-checked, then inliers of a RANSAC fundamental matrix) between a soft candidate and the last kept frame,
and compares them with the matches of the last two kept frames, so the decision is relative to the sequence
(murky water, low texture) and not to an absolute number. On a textured pan (tests/sfm/test_sfm_frames.py) a
Gaussian blur of sigma 1.5 px keeps 63 % of the sharp pair's matches and sigma 3 px 2 %; a 15 px motion blur
keeps 8 %.
"""

from __future__ import annotations

import cv2
import numpy as np

_ORB_FEATURES = 500
_RANSAC_PX = 1.5  # analysis-size pixels (320 px wide by default)


def verified_matches(a: np.ndarray, b: np.ndarray) -> int:
    """Verified ORB matches between two (H, W) uint8 grey images: cross-checked Hamming matches that are inliers
    of a RANSAC fundamental matrix (all cross-checked matches when fewer than 8)."""
    orb = cv2.ORB_create(_ORB_FEATURES, fastThreshold=10)
    ka, da = orb.detectAndCompute(a, None)
    kb, db = orb.detectAndCompute(b, None)
    if da is None or db is None:
        return 0
    matches = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(da, db)
    if len(matches) < 8:
        return len(matches)
    pa = np.float32([ka[m.queryIdx].pt for m in matches])
    pb = np.float32([kb[m.trainIdx].pt for m in matches])
    _, inliers = cv2.findFundamentalMat(pa, pb, cv2.FM_RANSAC, _RANSAC_PX, 0.99)
    return int(inliers.sum()) if inliers is not None else 0


class MatchCheck:
    """Whether a soft candidate still matches the sequence as well as ``keep_fraction`` of a sharp pair.

    Fed the kept frames in order (:meth:`kept`); :meth:`matches_enough` compares a candidate's verified matches
    with the last kept frame against those of the last two kept frames (computed once per pair, only when a soft
    candidate needs them). Before two frames are kept the reference is the last kept frame matched with itself.
    """

    def __init__(self, keep_fraction: float) -> None:
        self.keep_fraction = keep_fraction
        self._last: np.ndarray | None = None
        self._prev: np.ndarray | None = None
        self._reference: int | None = None

    def kept(self, gray: np.ndarray) -> None:
        self._prev, self._last, self._reference = self._last, gray, None

    def reference(self) -> int:
        """Verified matches of the last two kept frames (the last one with itself while only one is kept)."""
        assert self._last is not None
        if self._reference is None:
            other = self._prev if self._prev is not None else self._last
            self._reference = verified_matches(other, self._last)
        return self._reference

    def matches_enough(self, gray: np.ndarray) -> tuple[bool, int]:
        """``(keep, matches)``: the candidate's verified matches with the last kept frame, and whether they reach
        ``keep_fraction`` of :meth:`reference` (False with nothing kept yet or ``keep_fraction`` 0)."""
        if self._last is None or self.keep_fraction <= 0:
            return False, -1
        n = verified_matches(self._last, gray)
        return n > 0 and n >= self.keep_fraction * self.reference(), n
