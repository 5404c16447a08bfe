"""One reader behind every ``--calib``: a camera's intrinsics, image size and lens distortion.

:func:`read_calibration` recognises the format from the file's content (the suffix only tells XML from the rest):

==========================  ===========================================================  ====================
format                      recognised by                                                pixel centres at
==========================  ===========================================================  ====================
``{"K": ...}`` JSON         a JSON object with ``"K"`` (9 numbers row-major, or 3x3),    +0.5 (cadalign)
                            optional ``width``, ``height``, ``distortion`` (null, a
                            list of OpenCV coefficients, or ``{"model", "coeffs"}``);
                            the ``calibration.json`` that 'cadalign sim' writes
cameras.json                a JSON object with ``"camera"`` and/or ``"frames"`` (sim,    +0.5 (cadalign)
                            sfm, build-dataset); ``camera``'s COLMAP model/params give
                            the distortion, else the first frame's K
COLMAP ``cameras.txt``      text lines ``CAMERA_ID MODEL WIDTH HEIGHT PARAMS...``        +0.5 (COLMAP's own)
OpenCV YAML / XML           ``%YAML:1.0`` / ``<opencv_storage>`` (cv2.FileStorage, as    integers (OpenCV)
                            checkerboard tools write: ``camera_matrix``,
                            ``distortion_coefficients`` | ``dist_coeff(s)`` | ``D``,
                            ``image_width``, ``image_height``), or a plain YAML with
                            ``camera_matrix`` as a 3x3 / 9-number list
ROS CameraInfo YAML         ``camera_matrix: {rows, cols, data}``, ``distortion_model``,  integers (ROS =
                            ``distortion_coefficients: {data}``, ``image_width/height``  OpenCV)
==========================  ===========================================================  ====================

Pixel-centre convention: cadalign (as COLMAP) lets pixel (0, 0) cover [0, 1)^2, so its centre is (0.5, 0.5);
OpenCV and ROS put that centre at (0, 0). Focal lengths agree; ``cx_cadalign = cx_opencv + 0.5`` (same for cy).
:class:`CameraCalibration` always holds K in cadalign's convention.

Distortion models: ``"none"``; ``"opencv"`` (OpenCV's order k1, k2, p1, p2[, k3[, k4, k5, k6]]: ROS plumb_bob /
rational_polynomial, COLMAP SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV); ``"fisheye"`` (k1..k4: OpenCV fisheye,
ROS equidistant, COLMAP OPENCV_FISHEYE). :func:`undistort` removes it once, keeping K (the pinhole truth).
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
import yaml

from cadalign.errors import InputError
from cadalign.types import Rigid3

DistortionModel = Literal["none", "opencv", "fisheye"]
FORMATS = ("K-json", "cameras.json", "colmap-cameras.txt", "opencv", "ros")
"""Names of the formats :func:`read_calibration` reads (:attr:`CameraCalibration.format`)."""
ACCEPTED = ('a {"K": [fx, 0, cx, 0, fy, cy, 0, 0, 1]} JSON (pixel centres at +0.5), a cameras.json, a COLMAP '
            "cameras.txt, an OpenCV calibration YAML/XML (camera_matrix, distortion_coefficients, image_width, "
            "image_height) or a ROS CameraInfo YAML")
_OPENCV_KEYS_DIST = ("distortion_coefficients", "dist_coeff", "dist_coeffs", "distortion_coeffs", "D")
_ROS_MODELS: dict[str, DistortionModel] = {"plumb_bob": "opencv", "rational_polynomial": "opencv",
                                           "equidistant": "fisheye", "fisheye": "fisheye"}


@dataclass(frozen=True, eq=False)
class CameraCalibration:
    """A pinhole camera with optional lens distortion, as read from a calibration file."""

    K: np.ndarray
    """(3, 3) intrinsics in pixels, cadalign convention (pixel (0, 0) covers [0, 1)^2, centre at +0.5)."""
    width: int | None
    """Image width the calibration was made for, pixels; None when the file does not say."""
    height: int | None
    """Image height, pixels; None when the file does not say."""
    distortion_model: DistortionModel
    """'none', 'opencv' (k1, k2, p1, p2[, k3[, k4, k5, k6]]) or 'fisheye' (k1..k4)."""
    distortion: tuple[float, ...]
    """The model's coefficients in OpenCV's order (empty for 'none')."""
    source: Path
    """The file it was read from (named in every error)."""
    format: str
    """Which of :data:`FORMATS` the file was."""

    @property
    def intrinsics(self) -> tuple[float, float, float, float]:
        """``(fx, fy, cx, cy)``, cadalign convention."""
        return float(self.K[0, 0]), float(self.K[1, 1]), float(self.K[0, 2]), float(self.K[1, 2])

    @property
    def distorted(self) -> bool:
        """Whether the lens distortion is not the identity."""
        return self.distortion_model != "none" and any(abs(c) > 0 for c in self.distortion)

    def record(self) -> dict[str, Any]:
        """JSON for reports: where the calibration came from and what it holds."""
        return {"source": str(self.source), "format": self.format, "K": self.K.ravel().tolist(),
                "width": self.width, "height": self.height, "distortion_model": self.distortion_model,
                "distortion": list(self.distortion), "convention": "pixel centres at +0.5 (cadalign/COLMAP)"}

    def check_size(self, width: int, height: int, what: str) -> None:
        """Refuse frames of another size than the calibration's (``what`` names them).

        Raises:
            InputError: naming the calibration file, both sizes and the fix.
        """
        if self.width is None or self.height is None or (int(width), int(height)) == (self.width, self.height):
            return
        raise InputError(
            f"{self.source} is a calibration for {self.width}x{self.height} images but {what} is {width}x{height}; "
            "pass the calibration made for this camera's resolution (a resized video needs fx, fy, cx, cy scaled "
            "by the same factor, and image_width/image_height set to the new size)")


def read_calibration(path: Path) -> CameraCalibration:
    """The calibration in ``path``, any format of the module doc; K in cadalign's pixel convention.

    Raises:
        InputError: the file is missing, in none of the formats, or its K, size or distortion is unusable
            (the message names the file and the fix).
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"calibration file not found: {path}; pass {ACCEPTED}")
    text = path.read_text(errors="replace")
    head = text.lstrip()
    if path.suffix.lower() == ".xml" or head.startswith("<"):
        return _opencv_filestorage(path)
    if head.startswith("{"):
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise InputError(f"{path} is not valid JSON ({exc}); fix it or pass {ACCEPTED}") from None
        return _from_json(path, data)
    if head.startswith("%YAML") or "!!opencv-matrix" in text:
        return _opencv_filestorage(path)
    if _looks_like_colmap(text):
        return _colmap_txt(path, text)
    return _from_yaml(path, text)


def _fail(path: Path, what: str) -> InputError:
    return InputError(f"{path}: {what}; fix the calibration file (it must be {ACCEPTED})")


def _matrix(path: Path, value: Any, key: str) -> np.ndarray:
    """A 3x3 K from 9 numbers / nested 3x3, checked."""
    try:
        K = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        K = np.full(1, np.nan)
    if K.size != 9 or not np.isfinite(K).all() or K[0] <= 0 or K[4] <= 0 or abs(K[8] - 1) > 1e-9:
        raise _fail(path, f"'{key}' must be 9 finite numbers (3x3, row-major: fx 0 cx 0 fy cy 0 0 1) with fx, fy > 0, "
                          f"got {np.asarray(K).tolist()}")
    return K.reshape(3, 3)


def _size(path: Path, width: Any, height: Any) -> tuple[int | None, int | None]:
    if width is None and height is None:
        return None, None
    try:
        w, h = int(width), int(height)
    except (TypeError, ValueError):
        raise _fail(path, f"image width/height must be positive integers, got {width!r} x {height!r}") from None
    if w <= 0 or h <= 0 or w != float(width) or h != float(height):
        raise _fail(path, f"image width/height must be positive integers, got {width!r} x {height!r}")
    return w, h


def _coeffs(path: Path, model: DistortionModel, values: Any) -> tuple[float, ...]:
    try:
        c = tuple(float(v) for v in np.asarray(values if values is not None else [], dtype=np.float64).reshape(-1))
    except (TypeError, ValueError):
        raise _fail(path, f"distortion coefficients must be numbers, got {values!r}") from None
    if not all(np.isfinite(c)):
        raise _fail(path, f"distortion coefficients must be finite, got {list(c)}")
    allowed = {"none": (0,), "opencv": (0, 4, 5, 8, 12, 14), "fisheye": (4,)}[model]
    if model == "opencv" and len(c) in (1, 2):  # radial only (k1[, k2])
        c = c + (0.0,) * (4 - len(c))
    if len(c) not in allowed:
        raise _fail(path, f"a {model!r} distortion takes {' or '.join(map(str, allowed))} coefficients, got {len(c)}")
    if model == "opencv" and len(c) > 8:
        raise _fail(path, "the thin-prism/tilted OpenCV distortion terms (12 or 14 coefficients) are not supported")
    if model == "opencv" and len(c) > 4 and not any(c[4:]):  # one lens, one tuple: k3 (.. k6) = 0 dropped
        c = c[:4]
    if model == "opencv" and len(c) == 8 and not any(c[5:]):
        c = c[:5]
    return c


def _calibration(path: Path, fmt: str, K: np.ndarray, size: tuple[int | None, int | None], model: DistortionModel,
                 coeffs: tuple[float, ...], *, opencv_centres: bool) -> CameraCalibration:
    K = np.array(K, dtype=np.float64)
    if opencv_centres:
        K[0, 2] += 0.5
        K[1, 2] += 0.5
    if not any(abs(c) > 0 for c in coeffs):
        model, coeffs = "none", ()
    return CameraCalibration(K, size[0], size[1], model, coeffs, path, fmt)


# --- JSON: {"K"} and cameras.json ---------------------------------------------------------------------------------

def _from_json(path: Path, data: Any) -> CameraCalibration:
    if not isinstance(data, dict):
        raise _fail(path, "the JSON is not an object")
    if "K" in data:
        model, coeffs = _json_distortion(path, data.get("distortion"))
        return _calibration(path, "K-json", _matrix(path, data["K"], "K"),
                            _size(path, data.get("width"), data.get("height")), model, coeffs, opencv_centres=False)
    if "camera" in data or "frames" in data:
        return _cameras_json(path, data)
    raise _fail(path, "this JSON has neither 'K' nor 'camera'/'frames'")


def _json_distortion(path: Path, value: Any) -> tuple[DistortionModel, tuple[float, ...]]:
    if value is None:
        return "none", ()
    if isinstance(value, dict):
        model = str(value.get("model", "opencv")).lower()
        model = _ROS_MODELS.get(model, model)
        if model not in ("none", "opencv", "fisheye"):
            raise _fail(path, f"unknown distortion model {value.get('model')!r}; use 'opencv' or 'fisheye'")
        return model, _coeffs(path, model, value.get("coeffs"))  # type: ignore[arg-type]
    return "opencv", _coeffs(path, "opencv", value)


def _cameras_json(path: Path, data: dict[str, Any]) -> CameraCalibration:
    cam = data.get("camera") if isinstance(data.get("camera"), dict) else None
    frames = data.get("frames") if isinstance(data.get("frames"), dict) else {}
    if cam is not None and "model" in cam and "params" in cam:
        K, model, coeffs = colmap_camera(path, str(cam["model"]), cam["params"])
        return _calibration(path, "cameras.json", K, _size(path, cam.get("width"), cam.get("height")), model,
                            coeffs, opencv_centres=False)
    rec = cam if cam is not None and "K" in cam else next(iter(frames.values()), None)
    if not isinstance(rec, dict) or "K" not in rec:
        raise _fail(path, "this cameras.json has no 'camera' with K or params and no frame with 'K'")
    return _calibration(path, "cameras.json", _matrix(path, rec["K"], "K"),
                        _size(path, rec.get("width"), rec.get("height")), "none", (), opencv_centres=False)


def frame_pose(entry: dict[str, Any]) -> Rigid3:
    """``T_cam_from_world`` of one frame of a cameras.json (``R_cam_from_world``, ``t_cam_from_world_m``; the file's
    ``"units"``)."""
    return Rigid3(np.reshape(entry["R_cam_from_world"], (3, 3)), np.asarray(entry["t_cam_from_world_m"], np.float64))


def posed_frames(cameras: Mapping[str, Any]) -> dict[str, Rigid3]:
    """``T_cam_from_world`` of each frame of a cameras.json dict that has a pose (in the file's ``"units"``); frames
    with intrinsics only are left out."""
    return {n: frame_pose(f) for n, f in (cameras.get("frames") or {}).items() if "R_cam_from_world" in f}


def camera_pose_arrays(cameras: Mapping[str, Any], names: list[str] | None = None,
                       ) -> tuple[list[str], np.ndarray, np.ndarray]:
    """The camera poses of a cameras.json dict (``{"frames": {name: {"R_cam_from_world", "t_cam_from_world_m"}}}``,
    in the file's ``"units"``): the names of the frames with a pose (sorted; or ``names``), (N, 3, 3)
    ``R_cam_from_world`` and (N, 3) ``t_cam_from_world``."""
    if names is None:
        posed = posed_frames(cameras)
        names = sorted(posed)
        poses = [posed[n] for n in names]
    else:
        names = list(names)
        poses = [frame_pose(cameras["frames"][n]) for n in names]
    return names, np.array([T.R for T in poses]).reshape(-1, 3, 3), np.array([T.t for T in poses]).reshape(-1, 3)


# --- COLMAP cameras.txt -----------------------------------------------------------------------------------------

_COLMAP_LINE = re.compile(r"^\s*\d+\s+[A-Z_]+\s+\d+\s+\d+(\s+[-+0-9.eE]+)+\s*$")


def _looks_like_colmap(text: str) -> bool:
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    return bool(lines) and all(_COLMAP_LINE.match(ln) for ln in lines)


def colmap_camera(path: Path, model: str, params: Any) -> tuple[np.ndarray, DistortionModel, tuple[float, ...]]:
    """K (COLMAP = cadalign convention), distortion model and OpenCV-ordered coefficients of a COLMAP camera."""
    p = [float(v) for v in params]
    layout = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "SIMPLE_RADIAL": 4, "RADIAL": 5, "OPENCV": 8, "FULL_OPENCV": 12,
              "OPENCV_FISHEYE": 8}
    if model not in layout:
        raise _fail(path, f"COLMAP camera model {model} is not supported (use one of {', '.join(layout)})")
    if len(p) != layout[model]:
        raise _fail(path, f"COLMAP model {model} takes {layout[model]} parameters, got {len(p)}")
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        fx = fy = p[0]
        cx, cy, rest = p[1], p[2], p[3:]
    else:
        fx, fy, cx, cy, rest = p[0], p[1], p[2], p[3], p[4:]
    K = _matrix(path, [fx, 0, cx, 0, fy, cy, 0, 0, 1], f"{model} parameters")
    if model == "OPENCV_FISHEYE":
        return K, "fisheye", _coeffs(path, "fisheye", rest)
    if model in ("SIMPLE_PINHOLE", "PINHOLE"):
        return K, "none", ()
    return K, "opencv", _coeffs(path, "opencv", rest)


def _colmap_txt(path: Path, text: str) -> CameraCalibration:
    cams = [ln.split() for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    distinct = {tuple(c[1:]) for c in cams}
    if len(distinct) > 1:
        raise _fail(path, f"it lists {len(distinct)} different cameras; cadalign expects one camera per video "
                          "(keep the line of the camera that filmed it)")
    c = cams[0]
    K, model, coeffs = colmap_camera(path, c[1], c[4:])
    return _calibration(path, "colmap-cameras.txt", K, _size(path, c[2], c[3]), model, coeffs, opencv_centres=False)


# --- OpenCV FileStorage and YAML (OpenCV plain / ROS CameraInfo) ---------------------------------------------------

def _opencv_filestorage(path: Path) -> CameraCalibration:
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as exc:
        raise _fail(path, f"OpenCV cannot read it ({str(exc).strip().splitlines()[-1]})") from None
    try:
        if not fs.isOpened():
            raise _fail(path, "OpenCV cannot open it as YAML/XML FileStorage")
        node = fs.getNode("camera_matrix")
        if node.empty():
            raise _fail(path, "no 'camera_matrix' in this OpenCV file (the 3x3 K as !!opencv-matrix)")
        K = node.mat() if node.isMap() else np.array([node.at(i).real() for i in range(node.size())])
        if K is None:
            raise _fail(path, "'camera_matrix' is not a matrix")
        dist = None
        for key in _OPENCV_KEYS_DIST:
            d = fs.getNode(key)
            if not d.empty():
                dist = d.mat() if d.isMap() else [d.at(i).real() for i in range(d.size())]
                break
        model_node = fs.getNode("distortion_model")
        model = model_node.string() if not model_node.empty() else "opencv"
        w, h = fs.getNode("image_width"), fs.getNode("image_height")
        size = _size(path, None if w.empty() else w.real(), None if h.empty() else h.real())
    finally:
        fs.release()
    dist_model = _ROS_MODELS.get(model.lower(), "opencv" if model.lower() in ("opencv", "radtan") else None)
    if dist_model is None:
        raise _fail(path, f"unknown distortion_model {model!r}; use plumb_bob / rational_polynomial / equidistant")
    return _calibration(path, "opencv", _matrix(path, K, "camera_matrix"), size, dist_model,
                        _coeffs(path, dist_model, dist), opencv_centres=True)


def _from_yaml(path: Path, text: str) -> CameraCalibration:
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise _fail(path, f"the file is in no known format (not JSON, COLMAP text or YAML: {str(exc).splitlines()[0]})"
                    ) from None
    if not isinstance(data, dict):
        raise _fail(path, "the file is in no known calibration format")
    if "camera_matrix" not in data:
        keys = ", ".join(sorted(map(str, data))[:8])
        raise _fail(path, f"this YAML has no 'camera_matrix' (keys: {keys}); an OpenCV or ROS calibration names the "
                          "3x3 K 'camera_matrix'")
    cm = data["camera_matrix"]
    ros = isinstance(cm, dict)
    K = _matrix(path, cm.get("data") if ros else cm, "camera_matrix")
    dist: Any = None
    for key in _OPENCV_KEYS_DIST:
        if key in data:
            dist = data[key]
            break
    if isinstance(dist, dict):
        dist = dist.get("data")
    model_name = str(data.get("distortion_model", "plumb_bob")).lower()
    model = _ROS_MODELS.get(model_name, "opencv" if model_name in ("opencv", "radtan") else None)
    if model is None:
        raise _fail(path, f"unknown distortion_model {model_name!r}; use plumb_bob / rational_polynomial / "
                          "equidistant")
    return _calibration(path, "ros" if ros else "opencv", K, _size(path, data.get("image_width"),
                        data.get("image_height")), model, _coeffs(path, model, dist), opencv_centres=True)


# --- undistortion ---------------------------------------------------------------------------------------------------

def undistort_maps(K: np.ndarray, model: DistortionModel, coeffs: tuple[float, ...], width: int,
                   height: int) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.remap`` maps (two (H, W) float32) that undo a lens distortion, keeping ``K`` ((3, 3), cadalign
    convention): the output is the pinhole image of the same camera (what every later stage assumes)."""

    K_cv = np.array(K, dtype=np.float64)
    K_cv[0, 2] -= 0.5  # OpenCV's maps index pixels by their centres
    K_cv[1, 2] -= 0.5
    D = np.asarray(coeffs, dtype=np.float64)
    if model == "fisheye":
        return cv2.fisheye.initUndistortRectifyMap(K_cv, D, np.eye(3), K_cv, (int(width), int(height)),
                                                   cv2.CV_32FC1)
    return cv2.initUndistortRectifyMap(K_cv, D, None, K_cv, (int(width), int(height)), cv2.CV_32FC1)


class Undistorter:
    """Undistorts frames of one camera (maps built once per image size); the identity without distortion."""

    def __init__(self, K: np.ndarray, model: DistortionModel, coeffs: tuple[float, ...]) -> None:
        self.K, self.model, self.coeffs = np.asarray(K, dtype=np.float64), model, tuple(coeffs)
        self._maps: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}

    @classmethod
    def of(cls, calib: CameraCalibration) -> Undistorter:
        return cls(calib.K, calib.distortion_model, calib.distortion)

    @property
    def active(self) -> bool:
        """Whether images change (a distortion that is not the identity)."""
        return self.model != "none" and any(abs(c) > 0 for c in self.coeffs)

    def record(self) -> dict[str, Any]:
        """JSON for a stage's report: what was undone."""
        return {"model": self.model, "coeffs": list(self.coeffs), "K_kept": self.K.ravel().tolist(),
                "method": "cv2.initUndistortRectifyMap + remap (bilinear), output K = input K"}

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """(H, W[, C]) image -> the same camera's pinhole image (bilinear; outside the lens: black)."""

        if not self.active:
            return image
        h, w = image.shape[:2]
        if (w, h) not in self._maps:
            self._maps[(w, h)] = undistort_maps(self.K, self.model, self.coeffs, w, h)
        m1, m2 = self._maps[(w, h)]
        return cv2.remap(image, m1, m2, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
