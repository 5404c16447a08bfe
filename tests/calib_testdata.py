"""Write one camera's calibration in each format ``--calib`` reads (as the tools that make them write them)."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np


def write_all(folder: Path, K: np.ndarray, width: int, height: int, dist: Sequence[float] = ()) -> dict[str, Path]:
    """``K`` in cadalign's convention (pixel centres at +0.5); ``dist`` OpenCV k1, k2, p1, p2[, k3] or empty.
    Returns {format name: path} for the five formats."""
    import cv2

    folder.mkdir(parents=True, exist_ok=True)
    K = np.asarray(K, dtype=np.float64)
    K_cv = K.copy()
    K_cv[0, 2] -= 0.5
    K_cv[1, 2] -= 0.5
    d5 = list(dist) + [0.0] * (5 - len(dist)) if dist else [0.0] * 5
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    out = {}
    out["K-json"] = folder / "calibration.json"
    out["K-json"].write_text(json.dumps({"K": K.ravel().tolist(), "width": width, "height": height,
                                         "distortion": {"model": "opencv", "coeffs": d5} if dist else None}))
    out["cameras.json"] = folder / "cameras.json"
    if not dist:
        cam = {"model": "PINHOLE", "params": [fx, fy, cx, cy]}
    elif d5[4]:  # COLMAP's OPENCV model has no k3
        cam = {"model": "FULL_OPENCV", "params": [fx, fy, cx, cy, *d5, 0.0, 0.0, 0.0]}
    else:
        cam = {"model": "OPENCV", "params": [fx, fy, cx, cy, *d5[:4]]}
    out["cameras.json"].write_text(json.dumps({"units": "m", "camera": {**cam, "K": K.ravel().tolist(),
                                                                        "width": width, "height": height},
                                               "frames": {}}))
    out["colmap-cameras.txt"] = folder / "cameras.txt"
    out["colmap-cameras.txt"].write_text(
        "# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
        f"1 {cam['model']} {width} {height} {' '.join(repr(float(v)) for v in cam['params'])}\n")
    out["opencv"] = folder / "opencv_calib.yaml"
    fs = cv2.FileStorage(str(out["opencv"]), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", width)
    fs.write("image_height", height)
    fs.write("camera_matrix", K_cv)
    fs.write("distortion_coefficients", np.array(d5, dtype=np.float64).reshape(1, 5))
    fs.release()
    out["ros"] = folder / "ros_camera_info.yaml"
    P = np.hstack([K_cv, np.zeros((3, 1))])
    out["ros"].write_text(
        f"image_width: {width}\nimage_height: {height}\ncamera_name: rov_cam\n"
        f"camera_matrix:\n  rows: 3\n  cols: 3\n  data: [{', '.join(repr(float(v)) for v in K_cv.ravel())}]\n"
        "distortion_model: plumb_bob\n"
        f"distortion_coefficients:\n  rows: 1\n  cols: 5\n  data: [{', '.join(repr(float(v)) for v in d5)}]\n"
        "rectification_matrix:\n  rows: 3\n  cols: 3\n  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]\n"
        f"projection_matrix:\n  rows: 3\n  cols: 4\n  data: [{', '.join(repr(float(v)) for v in P.ravel())}]\n")
    return out
