"""pycolmap's synthetic SfM models for the SfM tests (exact matches, a known camera)."""

from __future__ import annotations

from pathlib import Path

import pycolmap


def synthetic_model(db_path: Path, *, frames: int = 8, points: int = 400, seed: int = 3) -> pycolmap.Reconstruction:
    """A synthetic model of ``frames`` images of a 320x240 SIMPLE_RADIAL camera (f 300, no distortion) and
    ``points`` points; its exact verified matches are written to a new database at ``db_path``."""
    opts = pycolmap.SyntheticDatasetOptions()
    opts.num_rigs, opts.num_frames_per_rig, opts.num_points3D = 1, frames, points
    opts.camera_width, opts.camera_height = 320, 240
    opts.camera_model_id = pycolmap.CameraModelId.SIMPLE_RADIAL
    opts.camera_params = [300.0, 160.0, 120.0, 0.0]
    opts.inlier_match_ratio = 1.0
    pycolmap.set_random_seed(seed)
    with pycolmap.Database.open(db_path) as db:
        return pycolmap.synthesize_dataset(opts, db)
