"""Plain pycolmap, the baseline every SfM speed claim is measured against.

What a user who skips cadalign would run: SIFT extraction, sequential matching and incremental mapping, each
with pycolmap's defaults (no frame selection, no enhancement, no loop closure, no consistency check, no
refinement), on the same frames folder. :func:`run_plain` times each step so a bench can report cadalign's
seconds as a ratio of these, measured in the same process on the same data (a shared machine makes
absolute times meaningless).
"""

from __future__ import annotations

import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

STEPS = ("features", "matches", "mapping")


@dataclass(frozen=True)
class PlainResult:
    """Plain pycolmap's largest model and its timing.

    Attributes:
        model: the pycolmap Reconstruction registering the most frames (None when mapping found none).
        seconds: wall-clock seconds per step (``STEPS``) and ``total``.
        frames: images in the folder.
    """

    model: Any
    seconds: dict[str, float]
    frames: int

    @property
    def registered(self) -> int:
        return self.model.num_reg_images() if self.model is not None else 0


def run_plain(images_dir: Path, work_dir: Path, *, num_threads: int = -1, image_names: list[str] | None = None,
              seed: int = 0, single_camera: bool = True) -> PlainResult:
    """SIFT + sequential matching + incremental mapping with pycolmap's defaults on ``images_dir``.

    ``work_dir`` is emptied first and receives ``database.db`` and ``sparse/``. ``num_threads`` (-1: all cores,
    pycolmap's default) and ``seed`` are set so the baseline runs on as many cores, and as repeatably, as the run
    it is compared with. ``image_names`` restricts it to those frames (default: all). ``single_camera``: the
    frames share one camera (``CameraMode.SINGLE``, as one video's frames do); False keeps pycolmap's
    ``AUTO`` (a camera per image, unless EXIF says otherwise), with which the mapper found no initial pair on
    the 29 photographs of ``opensfm_lund``.
    """
    import pycolmap  # lazy: heavy dependency (pycolmap)

    images_dir, work_dir = Path(images_dir), Path(work_dir)
    if work_dir.exists():
        shutil.rmtree(work_dir)
    (work_dir / "sparse").mkdir(parents=True)
    db = work_dir / "database.db"
    names = list(image_names or [])
    seconds: dict[str, float] = {}
    pycolmap.set_random_seed(seed)

    t0 = time.perf_counter()
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = num_threads
    mode = pycolmap.CameraMode.SINGLE if single_camera else pycolmap.CameraMode.AUTO
    pycolmap.extract_features(db, images_dir, image_names=names, camera_mode=mode, extraction_options=extraction)
    seconds["features"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    matching, pairing = pycolmap.FeatureMatchingOptions(), pycolmap.SequentialPairingOptions()
    matching.num_threads = pairing.num_threads = num_threads
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = seed
    pycolmap.match_sequential(db, matching_options=matching, pairing_options=pairing,
                              verification_options=verification)
    seconds["matches"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = opts.mapper.num_threads = num_threads
    opts.random_seed = opts.mapper.random_seed = seed
    if names:
        opts.image_names = names
    models = pycolmap.incremental_mapping(db, images_dir, work_dir / "sparse", opts)
    seconds["mapping"] = time.perf_counter() - t0
    seconds["total"] = sum(seconds[s] for s in STEPS)
    best = max(models.values(), key=lambda r: r.num_reg_images(), default=None)
    with pycolmap.Database.open(db) as d:
        n = d.num_images()
    return PlainResult(best, seconds, n)
