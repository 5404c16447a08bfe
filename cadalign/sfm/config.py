"""Configuration of the SfM stage: frame selection, SIFT, matching, camera, mapper; presets.

All knobs live in frozen dataclasses so a config file or ``--set key=value`` is
validated strictly (see :mod:`cadalign.config`). ``PRESETS`` holds the three
named trade-offs; ``balanced`` is what ``cadalign sfm`` runs by default.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from cadalign.config import bounded


@dataclass(frozen=True)
class FrameConfig:
    """Which frames of a video or image folder go to SfM, and how they are pre-processed."""

    sampling: Literal["all", "fps", "motion"] = "fps"
    """Video frame candidates: every frame ('all'), ``fps`` frames per second ('fps'), or every frame but
    kept only once the view moved ``keyframe_motion`` since the last kept frame ('motion'). Image
    folders always use every image as a candidate."""
    fps: float = bounded(2.0, gt=0)
    """Candidate rate for sampling='fps', frames per second of video time."""
    keyframe_motion: float = bounded(0.05, gt=0)
    """For sampling='motion': median feature motion (fraction of the image diagonal) that makes a keyframe."""
    min_motion: float = bounded(0.004, ge=0)
    """A candidate that moved less than this (median feature motion, fraction of the image diagonal) from
    the last kept frame is a near-duplicate and skipped; 0 turns the check off."""
    blur_ratio: float = bounded(0.35, ge=0, le=1)
    """A candidate whose sharpness (variance of the Laplacian) is below this fraction of the median
    sharpness of the recent candidates is skipped as blurred; 0 turns the check off."""
    blur_keep_matches: float = bounded(0.25, ge=0, le=1)
    """A candidate softer than ``blur_ratio`` is kept anyway when its verified ORB matches with the last kept frame
    reach this fraction of those of the last two kept frames: it would register (:mod:`cadalign.sfm.blur`). 0: sharpness
    alone decides (docs/tuning/sfm_config.md#frameconfigblur_keep_matches)."""
    blur_window: int = bounded(15, ge=1)
    """Number of recent candidates whose median sharpness is the reference for ``blur_ratio``."""
    min_sharpness: float = bounded(0.0, ge=0)
    """Absolute sharpness floor (variance of the Laplacian of the 8-bit grey image at analysis size)."""
    max_frames: int = bounded(0, ge=0)
    """Keep at most this many frames (the first ones); 0 means no limit."""
    analysis_width: int = bounded(320, ge=32)
    """Width in pixels the blur and motion checks run at (frames are written at full size)."""
    enhance: Literal["none", "clahe", "clahe_wb"] = "clahe"
    """Pre-processing for murky water: CLAHE on the lightness channel ('clahe'), plus a grey-world white
    balance ('clahe_wb'). On the default simulated scene CLAHE gives ~4x more SIFT features."""
    clahe_clip: float = bounded(2.0, gt=0)
    """CLAHE clip limit (OpenCV's ``clipLimit``)."""
    clahe_tiles: int = bounded(8, ge=1)
    """CLAHE tiles per image side."""
    mask: Path | None = None
    """ROV hardware / overlay mask: one image (applied to every frame) or a folder of per-frame masks named
    like the frames. Non-zero pixels are used, zero pixels get no features."""
    mask_rects: tuple[tuple[int, int, int, int], ...] = ()
    """Extra rectangles ``(x, y, width, height)`` in pixels with no features, e.g. a burnt-in timestamp."""


@dataclass(frozen=True)
class FeatureConfig:
    """SIFT extraction (COLMAP's CPU SIFT)."""

    max_num_features: int = bounded(8192, ge=16)
    """Most SIFT features kept per image."""
    peak_threshold: float = bounded(0.004, gt=0)
    """Difference-of-Gaussians peak threshold; lower finds more features in low-contrast water."""
    max_image_size: int = bounded(1600, ge=64)
    """Images are downscaled so their longest side is at most this many pixels before extraction."""
    first_octave: int = bounded(-1, ge=-1, le=1)
    """First octave of the SIFT pyramid: -1 (COLMAP's default) doubles the image first, for small-scale features; 0
    starts at the image's own size, ~3x faster on 640x480 frames, which keep enough features; small frames need -1
    (docs/tuning/sfm_config.md#featureconfigfirst_octave)."""
    estimate_affine_shape: bool = False
    """Affine-adapted SIFT (more robust to viewpoint change, ~2x slower)."""
    domain_size_pooling: bool = False
    """DSP-SIFT descriptors (more robust, slower)."""
    min_features: int = bounded(64, ge=0)
    """Frames with fewer features are reported as 'too few features'; if fewer than three frames have
    enough, the stage stops with an error naming the frames."""


@dataclass(frozen=True)
class MatchConfig:
    """Which image pairs are matched and how matches are verified."""

    pairing: Literal["sequential", "exhaustive"] = "sequential"
    """'sequential' matches each frame with its next ``overlap`` frames (video order); 'exhaustive' matches
    every pair (unordered photo sets; quadratic cost)."""
    overlap: int = bounded(10, ge=1)
    """Number of following frames each frame is matched with (sequential). Longer is not better on tight orbits:
    on the default scene (5.6 deg per frame) pairs beyond ~6 frames are mostly false matches on repeated parts,
    and 12 folded the model where 10 did not."""
    quadratic_overlap: bool = False
    """Also match frames 2, 4, 8 ... 2^overlap apart (sequential). Off by default: on orbits around
    symmetric subsea structures those far pairs are look-alike views that fold the model."""
    max_ratio: float = bounded(0.8, gt=0, le=1)
    """Lowe's ratio test threshold."""
    max_error_px: float = bounded(4.0, gt=0)
    """RANSAC inlier threshold of the two-view geometry, pixels."""
    min_num_inliers: int = bounded(15, ge=5)
    """Fewest verified matches for a pair to count."""
    max_num_trials: int = bounded(10000, ge=100)
    """Most RANSAC iterations per pair."""
    guided_matching: bool = False
    """Re-match with the estimated two-view geometry as a guide (more matches, slower). Off in every preset: on
    structures with repeated parts a pair's geometry can be false, and guided matching then adds matches that
    agree with it (on the default orbit it tripled the inliers of false pairs and folded the model)."""
    loop_closure: bool = True
    """Sequential pairing only: after a first model, match frames that the model puts close together
    but that are far apart in time (the ROV came back), then map again. Candidates come from the
    model's poses, not from appearance, so look-alike views of symmetric structures are not matched."""
    loop_remap: bool = True
    """After loop pairs are verified, map again from scratch (True), or merge the loop's tracks into the first model and
    re-adjust it globally (False; :mod:`cadalign.sfm.loop_merge`: one global bundle adjustment instead of a second
    mapping pass, cheaper; docs/tuning/sfm_config.md#matchconfigloop_remap)."""
    loop_num_neighbors: int = bounded(8, ge=1)
    """Nearest registered frames (by camera centre) each frame is checked against for loop pairs."""
    loop_max_distance: float = bounded(3.0, gt=0)
    """Loop candidates are at most this many median frame-to-frame steps apart."""
    loop_max_angle_deg: float = bounded(40.0, gt=0, le=180)
    """Loop candidates view directions differ by at most this angle, degrees."""


@dataclass(frozen=True)
class CameraConfig:
    """The single camera all frames share (one ROV camera)."""

    model: Literal["SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"] = "SIMPLE_RADIAL"
    """COLMAP camera model when the intrinsics are estimated."""
    intrinsics: tuple[float, float, float, float] | None = None
    """Known calibration ``(fx, fy, cx, cy)`` in pixels (cadalign/COLMAP pixel-centre convention: pixel
    (0, 0) covers [0, 1)^2). Given, the camera is PINHOLE with these values."""
    distortion_model: Literal["none", "opencv", "fisheye"] = "none"
    """Lens distortion of the known calibration (:mod:`cadalign.formats.calibration`): frames are undistorted
    once, when they are extracted, to the pinhole camera ``intrinsics`` (same K), so every later step and stage
    sees pinhole images. 'opencv': k1, k2, p1, p2[, k3[, k4, k5, k6]]; 'fisheye': k1..k4."""
    distortion: tuple[float, ...] = ()
    """The distortion coefficients in OpenCV's order (empty for 'none')."""
    refine_intrinsics: bool = False
    """With known ``intrinsics``: let bundle adjustment refine the focal length anyway."""
    known_intrinsics_from: Literal["refinement", "mapping"] = "refinement"
    """When known ``intrinsics`` take over: 'refinement' maps with ``model`` self-calibrated, then re-adjusts with the
    known calibration fixed; 'mapping' fixes a PINHOLE camera from the first pair on, which hinged the model on
    constant-height orbits (docs/tuning/sfm_config.md#cameraconfigknown_intrinsics_from)."""


@dataclass(frozen=True)
class MapperConfig:
    """Incremental (COLMAP) or global (GLOMAP) mapping and bundle adjustment."""

    kind: Literal["auto", "incremental", "global"] = "auto"
    """'incremental' registers one image at a time (COLMAP; the most accurate on the simulated orbits); 'global' solves
    all poses at once (GLOMAP; robust to forward motion); 'auto' runs incremental and falls back to global when it
    registers fewer than ``auto_min_registered`` of the frames."""
    auto_min_registered: float = bounded(0.8, ge=0, le=1)
    """For kind='auto': fraction of the frames the incremental model must register to be kept as is."""
    min_num_matches: int = bounded(15, ge=5)
    """Fewest verified matches for a pair to be used by the mapper."""
    init_min_num_inliers: int = bounded(100, ge=10)
    """Fewest inliers of the initial image pair (incremental)."""
    abs_pose_min_num_inliers: int = bounded(30, ge=6)
    """Fewest 2D-3D inliers to register an image (incremental)."""
    filter_max_reproj_error: float = bounded(4.0, gt=0)
    """Observations with a larger reprojection error (pixels) are dropped."""
    ba_global_max_num_iterations: int = bounded(50, ge=1)
    """Most solver iterations of each global bundle adjustment."""
    ba_global_max_refinements: int = bounded(5, ge=1)
    """Most global bundle adjustment + re-triangulation rounds."""
    ba_global_frames_ratio: float = bounded(1.1, gt=1)
    """Incremental mapping adjusts the whole model again once it has this many times the registered frames of the
    last global adjustment (COLMAP's default 1.1; larger: fewer global adjustments while mapping)."""
    ba_global_points_ratio: float = bounded(1.1, gt=1)
    """The same for the model's 3D points (COLMAP's default 1.1)."""
    refine_iterations: int = bounded(4, ge=0)
    """Rounds of robust (Cauchy) bundle adjustment of the kept model, each followed by dropping
    observations above ``refine_max_error_px`` and points below ``refine_min_tri_angle_deg``; 0: none.
    On the murky default scene this halves the rotation error (0.33 -> 0.16 deg)."""
    refine_max_error_px: float = bounded(1.0, gt=0)
    """Reprojection error (pixels) above which an observation is dropped between refinement rounds."""
    refine_loss_scale_px: float = bounded(0.5, gt=0)
    """Cauchy loss scale of the refinement, pixels (about the feature noise)."""
    refine_min_tri_angle_deg: float = bounded(3.0, ge=0)
    """Points triangulated with a smaller angle are dropped between refinement rounds, degrees."""
    refine_max_num_iterations: int = bounded(100, ge=1)
    """Solver iterations per refinement round."""
    multiple_models: bool = True
    """Start a new model when registration stalls (the largest is kept, the rest reported)."""
    attempts: int = bounded(3, ge=1)
    """Mapping attempts (seeds ``seed``, ``seed + 1`` ...) while the model has consistency breaks
    (see :mod:`cadalign.sfm.consistency`); the first sound model, else the one with fewest breaks, is kept.
    On the default scene one seed in three hinged the model (7 deg) and the next one was sound."""
    break_px: float = bounded(2.0, gt=0)
    """Consecutive frames whose verified matches have a median Sampson error above this (pixels, and above
    ``break_ratio`` times the typical pair's) under the model's poses are a break (hinge or fold)."""
    break_ratio: float = bounded(8.0, ge=1)
    """Relative part of the break threshold: multiples of the median error of all consecutive pairs."""
    break_min_matches: int = bounded(50, ge=8)
    """Consecutive pairs with fewer verified matches are not checked."""
    segment_frames: int = bounded(0, ge=0)
    """Long surveys: map windows of this many consecutive frames separately and merge them into one model
    (:mod:`cadalign.sfm.segments`); 0 maps all frames as one model. Mapping time grows faster than
    linearly with the frames, and a weak stretch then hinges one segment, not the whole dive."""
    segment_overlap: int = bounded(8, ge=3)
    """Frames each segment shares with the next (>= 3; the Sim(3) that merges them is fitted on these)."""
    on_break: Literal["repair", "largest_piece", "keep_all"] = "repair"
    """When every attempt has breaks: 'repair' re-maps ``repair_frames`` frames round each break and merges them
    (:mod:`cadalign.sfm.repair`; else the largest piece), 'largest_piece' keeps the largest consistent piece (the other
    frames reported as dropped), 'keep_all' the whole, inconsistent model."""
    repair_frames: int = bounded(16, ge=6)
    """Length of the window re-mapped round a break (on_break='repair'), half before the seam and half
    after; it must share 3 registered frames with each piece. On the default orbit 16 frames (90 deg of
    the orbit) mapped soundly where the whole orbit broke with 3 of 3 seeds."""


@dataclass(frozen=True)
class DepthConfig:
    """Semi-dense SfM depth maps from the sparse points."""

    enabled: bool = True
    """Write ``depth/<frame>.npy`` for every registered frame."""
    splat_radius_px: int = bounded(0, ge=0)
    """Each point fills a (2r+1)^2 square around its pixel (nearest point wins); 0 fills one pixel."""
    min_track_length: int = bounded(2, ge=2)
    """Only points seen in at least this many frames are projected."""


@dataclass(frozen=True)
class SfMConfig:
    """Everything the SfM stage does, from video frames to camera poses and sparse depth."""

    frames: FrameConfig = FrameConfig()
    """Frame selection and pre-processing."""
    features: FeatureConfig = FeatureConfig()
    """SIFT extraction."""
    matching: MatchConfig = MatchConfig()
    """Pairing and verification."""
    camera: CameraConfig = CameraConfig()
    """Shared camera model / known calibration."""
    mapper: MapperConfig = MapperConfig()
    """Mapping and bundle adjustment."""
    depth: DepthConfig = DepthConfig()
    """Projected sparse depth maps."""
    num_threads: int = bounded(2, ge=-1)
    """CPU threads for extraction, matching and bundle adjustment (-1: all cores)."""
    seed: int = bounded(0, ge=0)
    """Seed of COLMAP's RANSAC and mapper randomness (results still vary slightly with threads > 1)."""


def _preset(**sections: dict) -> SfMConfig:
    base = SfMConfig()
    return dataclasses.replace(
        base, **{k: dataclasses.replace(getattr(base, k), **v) for k, v in sections.items()}
    )


PRESETS: dict[str, SfMConfig] = {
    "fast": _preset(
        features={"max_num_features": 640, "max_image_size": 1024, "first_octave": 0},
        matching={"overlap": 5, "max_num_trials": 2000, "loop_remap": False},
        mapper={"ba_global_max_num_iterations": 25, "ba_global_max_refinements": 2, "refine_iterations": 1,
                "refine_max_num_iterations": 30, "ba_global_frames_ratio": 1.4, "ba_global_points_ratio": 1.4},
    ),
    "balanced": SfMConfig(),
    "accurate": _preset(
        features={"peak_threshold": 0.003},
        mapper={"ba_global_max_num_iterations": 100, "refine_iterations": 6},
    ),
}
"""Named trade-offs: 'fast' (SIFT from the image's own size, 640 features, short overlap, loop closure by merging
tracks into the first model, global adjustments only when the model grew by 40 %, one short refinement round: on
the default orbit 0.79-0.80x plain pycolmap's CPU time in the same run (wall 0.54-0.83x), with less than half its
rotation and a third of its centre error; on opensfm_lund 28-29 of 29 frames where plain registers none,
docs/tuning/sfm_speed.md), 'balanced' (default), 'accurate' (more features, longer bundle adjustment, more
refinement rounds). 'accurate' pairs frames like 'balanced': with overlap 12 and guided matching it folded the
default orbit (then 64 frames at 0.5 frame/s) at frames 54/55 with all three seeds (31 frames kept), and with
overlap 12 alone at the same place (55 kept). On that orbit, pairs more than ~6 frames (34 deg) apart are mostly
false matches on repeated parts (in 174 of the 190 verified pairs 7-12 frames apart, over 30 % of the inliers are
off the true epipolar geometry by > 4 px), and guided matching re-matches under the false geometry (3x their
inliers)."""
