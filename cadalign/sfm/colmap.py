"""The pycolmap steps of the SfM stage: features, matches, mapping, and why frames were left out.

Each step reads and writes COLMAP's own files (``database.db``, ``sparse/``);
:mod:`cadalign.sfm.pipeline` decides which steps to run. pycolmap is imported
lazily so that importing :mod:`cadalign.sfm` stays light.
"""

from __future__ import annotations

import logging
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cadalign.errors import DegenerateGeometryError, InputError
from cadalign.sfm.config import SfMConfig
from cadalign.types import Progress

log = logging.getLogger(__name__)

_EXTRACT_CHUNK = 8  # images per extract_features call, so progress can be shown


def _device() -> Any:
    import pycolmap  # lazy: heavy dependency (pycolmap)

    return pycolmap.Device.cpu


def fixed_while_mapping(cfg: SfMConfig) -> bool:
    """Whether the known calibration is the camera from the start (else it replaces the self-calibrated one
    before refinement, see :func:`cadalign.sfm.refine.refine`)."""
    return cfg.camera.intrinsics is not None and cfg.camera.known_intrinsics_from == "mapping"


def reader_options(cfg: SfMConfig, masks_dir: Path | None, exif_source: Path | None = None) -> Any:
    """``ImageReaderOptions``: camera model or known intrinsics, masks.

    ``exif_source`` is an original input image: when the frames were re-encoded (enhancement drops
    EXIF), its EXIF focal length still seeds the shared camera as a prior.
    """
    import pycolmap  # lazy: heavy dependency (pycolmap)

    opts = pycolmap.ImageReaderOptions()
    if fixed_while_mapping(cfg):
        opts.camera_model = "PINHOLE"
        opts.camera_params = ",".join(f"{v:.10g}" for v in cfg.camera.intrinsics)
    else:
        opts.camera_model = cfg.camera.model
        if exif_source is not None and exif_source.is_file():
            cam = pycolmap.infer_camera_from_image(exif_source, opts)
            if cam.has_prior_focal_length:
                log.info("camera prior from the EXIF of %s: %s %s", exif_source.name, cam.model_name,
                         cam.params_to_string())
                opts.camera_params = cam.params_to_string()
    if masks_dir is not None:
        opts.mask_path = masks_dir
    return opts


def extraction_options(cfg: SfMConfig) -> Any:
    import pycolmap  # lazy: heavy dependency (pycolmap)

    opts = pycolmap.FeatureExtractionOptions()
    opts.num_threads = cfg.num_threads
    opts.use_gpu = False
    opts.max_image_size = cfg.features.max_image_size
    sift = opts.sift
    sift.max_num_features = cfg.features.max_num_features
    sift.peak_threshold = cfg.features.peak_threshold
    sift.first_octave = cfg.features.first_octave
    sift.estimate_affine_shape = cfg.features.estimate_affine_shape
    sift.domain_size_pooling = cfg.features.domain_size_pooling
    return opts


def extract_features(
    cfg: SfMConfig, database: Path, images_dir: Path, names: Sequence[str], masks_dir: Path | None,
    progress: Progress | None = None, exif_source: Path | None = None,
) -> dict[str, int]:
    """SIFT features of ``names`` into a fresh ``database`` (one shared camera); returns name -> count.

    Raises:
        InputError: fewer than three frames have ``features.min_features`` features; the message names
            the frames that have too few.
    """
    import pycolmap  # lazy: heavy dependency (pycolmap)

    if database.exists():
        database.unlink()  # a half-written database from an interrupted run
    chunks = [list(names[i : i + _EXTRACT_CHUNK]) for i in range(0, len(names), _EXTRACT_CHUNK)]
    reader = reader_options(cfg, masks_dir, exif_source)
    extraction = extraction_options(cfg)
    for k, chunk in enumerate(progress(chunks, "features", len(chunks)) if progress else chunks):
        if k > 0:  # later chunks reuse the camera the first one created: one shared camera
            reader.existing_camera_id = 1
        pycolmap.extract_features(database, images_dir, image_names=chunk, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=extraction, device=_device())
    counts = feature_counts(database)
    few = {n: counts.get(n, 0) for n in names if counts.get(n, 0) < cfg.features.min_features}
    if len(names) < 3:
        raise InputError(
            f"only {len(names)} frame(s) left for SfM after frame selection ({', '.join(names) or 'none'}); SfM "
            "needs at least 3 overlapping frames. See frames.json for why the others were skipped (blurred, "
            "near-duplicate, black): lower frames.min_motion / frames.blur_ratio or give more footage"
        )
    if len(names) - len(few) < 3:
        listed = ", ".join(f"{n} ({c})" for n, c in sorted(few.items())[:20])
        more = f" and {len(few) - 20} more" if len(few) > 20 else ""
        raise InputError(
            f"too few features: {len(few)} of {len(names)} frames have fewer than {cfg.features.min_features} "
            f"SIFT features: {listed}{more}. The frames are blank, too dark or too blurred; check the input, "
            "enable frames.enhance = 'clahe', or lower features.peak_threshold"
        )
    if few:
        log.warning("%d frames have too few features: %s", len(few), ", ".join(sorted(few)))
    return counts


def feature_counts(database: Path) -> dict[str, int]:
    """Image name -> number of keypoints in ``database``."""
    import pycolmap  # lazy: heavy dependency (pycolmap)

    with pycolmap.Database.open(database) as db:
        return {im.name: db.num_keypoints_for_image(im.image_id) for im in db.read_all_images()}


def matching_options(cfg: SfMConfig) -> tuple[Any, Any]:
    """``(FeatureMatchingOptions, TwoViewGeometryOptions)`` of the config."""
    import pycolmap  # lazy: heavy dependency (pycolmap)

    m = cfg.matching
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = cfg.num_threads
    matching.use_gpu = False
    matching.guided_matching = m.guided_matching
    matching.sift.max_ratio = m.max_ratio
    verification = pycolmap.TwoViewGeometryOptions()
    verification.min_num_inliers = m.min_num_inliers
    verification.ransac.max_error = m.max_error_px
    verification.ransac.max_num_trials = m.max_num_trials
    verification.ransac.random_seed = cfg.seed
    return matching, verification


def match(cfg: SfMConfig, database: Path) -> None:
    """Match and verify image pairs in ``database`` (previous matches are dropped first)."""
    import pycolmap  # lazy: heavy dependency (pycolmap)

    with pycolmap.Database.open(database) as db:
        db.clear_matches()
        db.clear_two_view_geometries()
    matching, verification = matching_options(cfg)
    if cfg.matching.pairing == "sequential":
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = cfg.matching.overlap
        pairing.quadratic_overlap = cfg.matching.quadratic_overlap
        pairing.loop_detection = False  # COLMAP's needs a downloaded vocabulary tree; see MatchConfig.loop_closure
        pairing.num_threads = cfg.num_threads
        pycolmap.match_sequential(database, matching_options=matching, pairing_options=pairing,
                                  verification_options=verification, device=_device())
    else:
        pycolmap.match_exhaustive(database, matching_options=matching, verification_options=verification,
                                  device=_device())


def match_pairs(cfg: SfMConfig, database: Path, pairs: Sequence[tuple[str, str]], pairs_file: Path) -> None:
    """Match and verify the listed image pairs (pairs already in ``database`` are skipped by COLMAP)."""
    import pycolmap  # lazy: heavy dependency (pycolmap)

    pairs_file.parent.mkdir(parents=True, exist_ok=True)
    pairs_file.write_text("".join(f"{a} {b}\n" for a, b in pairs))
    matching, verification = matching_options(cfg)
    pairing = pycolmap.ImportedPairingOptions()
    pairing.match_list_path = pairs_file
    pycolmap.match_image_pairs(database, matching_options=matching, pairing_options=pairing,
                               verification_options=verification, device=_device())


def incremental_options(cfg: SfMConfig, image_names: list[str]) -> Any:
    import pycolmap  # lazy: heavy dependency (pycolmap)

    mp = cfg.mapper
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = cfg.num_threads
    opts.random_seed = cfg.seed
    opts.image_names = image_names
    opts.min_num_matches = mp.min_num_matches
    opts.multiple_models = mp.multiple_models
    opts.ba_global_max_num_iterations = mp.ba_global_max_num_iterations
    opts.ba_global_max_refinements = mp.ba_global_max_refinements
    opts.ba_global_frames_ratio = mp.ba_global_frames_ratio
    opts.ba_global_points_ratio = mp.ba_global_points_ratio
    opts.mapper.init_min_num_inliers = mp.init_min_num_inliers
    opts.mapper.abs_pose_min_num_inliers = mp.abs_pose_min_num_inliers
    opts.mapper.filter_max_reproj_error = mp.filter_max_reproj_error
    opts.mapper.num_threads = cfg.num_threads
    opts.mapper.random_seed = cfg.seed
    opts.triangulation.random_seed = cfg.seed
    if fixed_while_mapping(cfg) and not cfg.camera.refine_intrinsics:
        opts.ba_refine_focal_length = False
        opts.ba_refine_principal_point = False
        opts.ba_refine_extra_params = False
        opts.mapper.abs_pose_refine_focal_length = False
        opts.mapper.abs_pose_refine_extra_params = False
    return opts


def _global_options(cfg: SfMConfig, image_names: list[str]) -> Any:
    import pycolmap  # lazy: heavy dependency (pycolmap)

    opts = pycolmap.GlobalPipelineOptions()
    opts.num_threads = cfg.num_threads
    opts.random_seed = cfg.seed
    opts.image_names = image_names
    opts.min_num_matches = cfg.mapper.min_num_matches
    opts.multiple_models = cfg.mapper.multiple_models
    opts.mapper.num_threads = cfg.num_threads
    opts.mapper.random_seed = cfg.seed
    ba = opts.mapper.bundle_adjustment
    ba.ceres.use_gpu = False
    ba.ceres.solver_options.max_num_iterations = cfg.mapper.ba_global_max_num_iterations
    opts.mapper.global_positioning.use_gpu = False
    if fixed_while_mapping(cfg) and not cfg.camera.refine_intrinsics:
        ba.refine_focal_length = False
        ba.refine_principal_point = False
        ba.refine_extra_params = False
    return opts


@dataclass(frozen=True)
class MappingResult:
    """The models the mapper produced, largest first.

    Attributes:
        models: pycolmap Reconstructions sorted by registered images, descending.
        mapper: the mapper that made them ('incremental' or 'global').
    """

    models: list[Any]
    mapper: str


def reconstruct(
    cfg: SfMConfig, database: Path, images_dir: Path, work_dir: Path, image_names: list[str],
    progress: Progress | None = None,
) -> MappingResult:
    """Run the configured mapper; returns all models, largest first.

    With ``mapper.kind = 'auto'`` the incremental mapper runs first; when its largest model holds
    fewer than ``mapper.auto_min_registered`` of the frames, the global mapper runs too and the
    result registering more frames is kept (incremental on a tie).

    Raises:
        DegenerateGeometryError: no model could be initialised (no pair with enough matches and baseline).
    """
    kind = cfg.mapper.kind
    first = "global" if kind == "global" else "incremental"
    result = _run_mapper(first, cfg, database, images_dir, work_dir, image_names, progress)
    best = result.models[0].num_reg_images() if result.models else 0
    if kind == "auto" and best < cfg.mapper.auto_min_registered * len(image_names):
        log.warning("incremental mapping registered %d of %d frames; trying the global mapper", best,
                    len(image_names))
        other = _run_mapper("global", cfg, database, images_dir, work_dir, image_names, progress)
        if other.models and other.models[0].num_reg_images() > best:
            result = other
    if not result.models:
        raise DegenerateGeometryError(
            f"SfM found no model in {len(image_names)} frames: no frame pair has enough verified matches "
            f"(>= {cfg.mapper.min_num_matches}) and baseline to start. Check that consecutive frames overlap, "
            "try frames.enhance = 'clahe', or lower mapper.init_min_num_inliers"
        )
    return result


def _run_mapper(
    kind: str, cfg: SfMConfig, database: Path, images_dir: Path, work_dir: Path, image_names: list[str],
    progress: Progress | None,
) -> MappingResult:
    import pycolmap  # lazy: heavy dependency (pycolmap)

    if work_dir.exists():
        shutil.rmtree(work_dir)
    work_dir.mkdir(parents=True)
    pycolmap.set_random_seed(cfg.seed)
    if kind == "incremental":
        ticker = _Ticker(progress, len(image_names))
        try:
            opts = incremental_options(cfg, image_names)
            models = pycolmap.incremental_mapping(database, images_dir, work_dir, opts, next_image_callback=ticker.tick)
        finally:
            ticker.close()
    else:
        models = pycolmap.global_mapping(database, images_dir, work_dir, _global_options(cfg, image_names))
    recs = sorted(models.values(), key=lambda r: r.num_reg_images(), reverse=True)
    return MappingResult([r for r in recs if r.num_reg_images() > 0], kind)


class _Ticker:
    """Drive a generator-style progress bar from the mapper's per-image callback."""

    def __init__(self, progress: Progress | None, total: int) -> None:
        self._it = iter(progress(range(total), "mapping", total)) if progress else None
        self._done = 0
        self._total = total

    def tick(self) -> None:
        if self._it is not None and self._done < self._total:
            next(self._it, None)
            self._done += 1

    def close(self) -> None:
        if self._it is not None and hasattr(self._it, "close"):
            self._it.close()


def unregistered_reasons(
    cfg: SfMConfig, database: Path, names: Sequence[str], models: Sequence[Any]
) -> dict[str, str]:
    """Why each frame of ``names`` missing from the kept model ``models[0]`` is missing."""
    import pycolmap  # lazy: heavy dependency (pycolmap)

    registered = [{im.name for im in rec.images.values() if im.has_pose} for rec in models]
    with pycolmap.Database.open(database) as db:
        ids = {im.image_id: im.name for im in db.read_all_images()}
        n_feat = {name: db.num_keypoints_for_image(i) for i, name in ids.items()}
        pair_ids, geoms = db.read_two_view_geometries()
    best: dict[str, int] = {}
    for pid, geom in zip(pair_ids, geoms, strict=True):
        for i in pycolmap.pair_id_to_image_pair(pid):
            best[ids[i]] = max(best.get(ids[i], 0), len(geom.inlier_matches))
    return classify_unregistered(names, registered, n_feat, best, cfg)


def classify_unregistered(
    names: Sequence[str], registered: Sequence[set[str]], n_features: dict[str, int], best_inliers: dict[str, int],
    cfg: SfMConfig,
) -> dict[str, str]:
    """Reason per frame not in ``registered[0]`` (the kept model); ``registered[k]``: frames of model k.

    In order of precedence: too few features, no verified matches, in another (disconnected) model,
    otherwise the mapper could not localise it.
    """
    reasons = {}
    for name in names:
        if name in registered[0]:
            continue
        nf, ni = n_features.get(name, 0), best_inliers.get(name, 0)
        other = [k for k in range(1, len(registered)) if name in registered[k]]
        if nf < cfg.features.min_features:
            reasons[name] = f"too few features ({nf} < {cfg.features.min_features})"
        elif ni < cfg.mapper.min_num_matches:
            reasons[name] = f"no matches (best pair has {ni} verified matches)"
        elif other:
            reasons[name] = f"in disconnected model {other[0]} ({len(registered[other[0]])} frames)"
        else:
            reasons[name] = "not registered (the mapper could not localise it)"
    return reasons
