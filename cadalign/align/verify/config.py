"""The image verification's configuration (its own module: the evidence and the decision both read it)."""

from __future__ import annotations

from dataclasses import dataclass

OUTCOMES = ("ok", "uncertain", "wrong")


@dataclass(frozen=True)
class VerifyConfig:
    """Knobs of the image verification (thresholds chosen on the simulated scenes, see docs/tuning/verify.md)."""

    enabled: bool = True
    """Verify the alignment against the images before writing a dataset (off: trust the cloud gates alone)."""
    frames: int = 12
    """Registered frames used for the edge evidence, evenly spaced over the capture."""
    near_px: float = 1.5
    """An image edge within this distance of the predicted contour (pixels, each way) is a hit; the alignment
    before camera refinement is good to about a pixel."""
    shifts_px: tuple[float, ...] = (4.0, 8.0)
    """The contour displaced by these distances (pixels, both ways) along its normals gives the chance hit rate
    that clutter and texture alone produce."""
    min_contrast: float = 6.0
    """Weakest edge counted as a hit, grey levels (0-255) across one pixel."""
    min_part_samples: int = 50
    """A CAD part (instance) with fewer contour samples over all checked frames is not scored on its own."""
    min_samples: int = 300
    """Fewer contour samples than this over all frames is too little edge evidence to accept a pose."""
    ok_edge: float = 0.45
    """Smallest edge lift (see the module doc) of an accepted pose: between the right poses' (~0.75) and those turned
    180 degrees (~0.28), per-part mean after the local contour fit (docs/tuning/verify.md#verifyconfigok_edge)."""
    wrong_edge: float = 0.1
    """Below this edge lift the images contradict the pose (its outline is no likelier than a displaced one)."""
    ok_free: float = 0.1
    """Largest share of free-space violations (rays meeting the CAD before their point) of an accepted pose
    (right pose 0.01, the 180-degree turn 0.08, a 10-degree turn 0.39, wrong global poses 0.21-0.44)."""
    wrong_free: float = 0.3
    """Above this share the pose is wrong: the cameras saw points through the placed CAD."""
    min_free_rays: int = 50
    """Fewer rays meeting the CAD than this gives no free-space evidence (the share is not used)."""
    free_points: int = 4000
    """SfM points whose rays are cast (a seeded subset), each through at most ``free_obs`` of its cameras."""
    free_obs: int = 3
    """Observations per point cast for the free-space check."""
    free_margin_rel: float = 0.03
    """A ray meeting the CAD closer than its point by more than this fraction of the range (or the alignment's
    inlier distance, whichever is larger) is a violation; less is noise of a point on the surface."""
    refine: bool = True
    """Before scoring, move each hypothesis to its nearest fit of the image contours (:mod:`cadalign.align.edge_refine`,
    ``refine_search_px`` wide): a right placement from the sparse cloud can be pixels off on a real capture, where the
    ``near_px`` search misses its edges (docs/tuning/verify.md#verifyconfigrefine)."""
    refine_search_px: float = 8.0
    """Search range of that correction, pixels each way."""
    refine_max_turn_deg: float = 10.0
    """A correction turning the CAD more than this, degrees (or moving it more than ``refine_max_shift_rel`` of its
    diameter, or scaling it by more than 10 %), is not local: the hypothesis is scored where it was. 10 admits the ViSP
    desk's correction (docs/tuning/verify.md#verifyconfigrefine_max_turn_deg)."""
    refine_max_shift_rel: float = 0.1
    """See ``refine_max_turn_deg``: largest shift of the correction, fraction of the CAD diameter."""
    min_margin: float = 0.25
    """The chosen hypothesis's score must beat the best distinct runner-up by this fraction of its own score."""
    same_rel: float = 0.02
    """Two hypotheses whose placed CAD samples lie within this fraction of the CAD diameter of each other
    (mean, both ways) are look-alikes (a symmetric structure's turns): the images cannot and need not tell them
    apart."""
    photo_points: int = 3000
    """CAD surface samples of the photo-consistency evidence (reported only)."""
    picture_frames: int = 3
    """Frames drawn in the picture of the best two hypotheses."""
    seed: int = 0
    """Seed of the free-space subset."""
