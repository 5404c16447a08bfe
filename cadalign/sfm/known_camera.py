"""A calibration file (any ``--calib`` format, :mod:`cadalign.formats.calibration`) as SfM camera settings."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from cadalign.formats.calibration import CameraCalibration, read_calibration
from cadalign.sfm.config import SfMConfig
from cadalign.sfm.frames import first_frame_size


def camera_settings(calib: CameraCalibration) -> dict[str, Any]:
    """``{"camera": {...}}`` settings (nested keys of :class:`SfMConfig`) of a read calibration."""
    return {"camera": {"intrinsics": list(calib.intrinsics), "distortion_model": calib.distortion_model,
                       "distortion": list(calib.distortion)}}


def checked_calibration(path: Path, source: Path) -> CameraCalibration:
    """The calibration in ``path``, its image size checked against the first frame of ``source``.

    Raises:
        InputError: unreadable calibration, or made for another image size (naming the file and the fix).
    """
    calib = read_calibration(path)
    width, height = first_frame_size(source)
    calib.check_size(width, height, f"the first frame of {source}")
    return calib


def with_calibration(cfg: SfMConfig, path: Path, source: Path) -> SfMConfig:
    """``cfg`` with the known camera (intrinsics and lens distortion) of calibration file ``path``."""
    calib = checked_calibration(path, source)
    return dataclasses.replace(cfg, camera=dataclasses.replace(
        cfg.camera, intrinsics=calib.intrinsics, distortion_model=calib.distortion_model,
        distortion=calib.distortion))
