"""The camera and the metric scale of a single photograph (GenLaM from any photo).

Intrinsics, first found wins: ``--calib`` (a calibration JSON ``{"K": [...]}`` or a ``cameras.json``),
``--hfov``, the photo's EXIF 35 mm-equivalent focal length, a fit of GenLaM eq. (1) to a point map
(:func:`cadalign.geometry.recover_focal_shift`: focal length and z-shift, with its RMS reprojection residual
reported), else a stated default field of view with a warning. A depth-only network (Depth Anything, DPT)
gives no point map or rays, so the focal length is not observable from its output: eq. (1) applies only where
a point map is given. When ``--calib``, ``--hfov`` or EXIF gives the camera, a point map is taken as it is
(z-shift 0).

Convention: ours puts pixel centres at integer + 0.5, so the principal point of a W x H photo is
``(W/2, H/2)`` and ``f = (W/2) / tan(hfov/2)``. GenLaM's Algorithm 1 writes ``c = (W-1)/2`` with pixel
centres at integers; it is the same camera (both put c at the middle of the image), only the pixel
indices differ by 0.5.

Scale (``--scale-from``) of relative depth, or a check / override of metric depth:
``distance:D`` (the median depth of the photo is D metres, e.g. the ROV's stand-off), ``pixel:U,V:D``
(the pixel at column U, row V is D metres away, z-depth), ``depth:PATH`` (a sparse depth map in metres,
``.npz`` key ``depth_m`` or a uint16 PNG in millimetres, e.g. a sensor's ranges) or ``cad:SCENE:POSE`` (the
CAD scene spec rendered from the camera pose POSE, a JSON with ``T_world_from_cam`` or ``x,y,z,r,p,y``, e.g.
from ``cadalign align``). A single distance fixes a scale only (the median ratio); a reference depth map
(``depth``, ``cad``) with relative *disparity* fixes scale and shift: ``1 / ref = a * disparity + b`` by
least squares (:func:`fit_disparity`), the affine ambiguity of Depth Anything / MiDaS outputs.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from PIL import Image, UnidentifiedImageError

from cadalign.emulate.run import parse_pose
from cadalign.emulate.sources import scene_mesh
from cadalign.emulate.views import render
from cadalign.errors import DegenerateGeometryError, InputError
from cadalign.geometry import recover_focal_shift
from cadalign.io import read_image, read_json
from cadalign.sfm.report import intrinsics_from_cameras_json
from cadalign.types import Camera

log = logging.getLogger(__name__)
FovSource = Literal["calib", "hfov", "exif", "point_map", "default"]
_EXIF_IFD, _FOCAL_35MM = 0x8769, 0xA405


@dataclass(frozen=True)
class PhotoCamera:
    """Intrinsics of a photo and where they came from.

    Attributes:
        K: (3, 3) intrinsics (pixel centres at integer + 0.5).
        source: ``calib``, ``hfov``, ``exif``, ``point_map`` (eq. 1 fit) or ``default``.
        residual_px: RMS reprojection residual of the eq. (1) fit, pixels (None for other sources).
        shift: the eq. (1) z-shift in the point map's unit (0 for other sources).
    """

    K: np.ndarray
    source: FovSource
    residual_px: float | None = None
    shift: float = 0.0

    @property
    def hfov_deg(self) -> float:
        return float(np.degrees(2 * np.arctan2(self.K[0, 2], self.K[0, 0])))


def K_from_hfov(width: int, height: int, hfov_deg: float) -> np.ndarray:
    """(3, 3) intrinsics of square pixels, principal point at the centre ``(W/2, H/2)``."""
    if not 0 < hfov_deg < 180:
        raise InputError(f"--hfov {hfov_deg}: a horizontal field of view must lie in (0, 180) degrees")
    f = 0.5 * width / np.tan(np.radians(hfov_deg) / 2)
    return np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])


def exif_focal_px(path: Path, width: int, height: int) -> float | None:
    """Focal length in pixels from the EXIF 35 mm-equivalent focal length (36 mm = the long side); None when the
    photo has no such tag (PNG, stripped EXIF)."""
    try:
        with Image.open(path) as im:
            f35 = im.getexif().get_ifd(_EXIF_IFD).get(_FOCAL_35MM)
    except (OSError, UnidentifiedImageError):
        return None
    if not f35 or float(f35) <= 0:
        return None
    return float(f35) * max(width, height) / 36.0


def fit_point_map(points: np.ndarray) -> tuple[float, float, float]:
    """GenLaM eq. (1) on an (H, W, 3) point map: ``(f_px, dz, rms_residual_px)``.

    Raises:
        InputError: the point map does not determine the focal length (flat, too few points, not a pinhole).
    """
    P = np.asarray(points, dtype=np.float64)
    try:
        f, dz = recover_focal_shift(P)
    except DegenerateGeometryError as exc:
        raise InputError(f"point map: eq. (1) cannot recover the focal length ({exc}); pass --hfov or --calib") \
            from exc
    h, w = P.shape[:2]
    u, v = np.meshgrid(np.arange(w) + 0.5 - 0.5 * w, np.arange(h) + 0.5 - 0.5 * h)
    ok = np.all(np.isfinite(P), -1)
    pred = f * P[ok][:, :2] / (P[ok][:, 2:] + dz)
    res = float(np.sqrt(np.mean(np.sum((pred - np.stack([u[ok], v[ok]], 1)) ** 2, 1))))
    return f, dz, res


def calib_K(path: Path, width: int, height: int) -> np.ndarray:
    """K of a calibration file (``{"K": [9 values], "width", "height"}`` as ``cadalign sim`` writes, or a
    cameras.json), rescaled to the photo when the file names another image size (a resized photo)."""
    fx, fy, cx, cy = intrinsics_from_cameras_json(path)
    data = read_json(path)
    cw, ch = (data.get("width"), data.get("height")) if isinstance(data, dict) else (None, None)
    sx, sy = (width / cw, height / ch) if cw and ch else (1.0, 1.0)
    if (sx, sy) != (1.0, 1.0):
        log.warning("%s is for %sx%s px, the photo %dx%d: K rescaled", path, cw, ch, width, height)
    return np.array([[fx * sx, 0, cx * sx], [0, fy * sy, cy * sy], [0, 0, 1.0]])


def photo_camera(width: int, height: int, *, calib: Path | None = None, hfov_deg: float | None = None,
                 photo: Path | None = None, points: np.ndarray | None = None,
                 default_hfov_deg: float = 70.0) -> PhotoCamera:
    """The intrinsics of a photo, first found wins (see the module docstring)."""
    if calib is not None:
        return PhotoCamera(calib_K(Path(calib), width, height), "calib")
    if hfov_deg is not None:
        return PhotoCamera(K_from_hfov(width, height, hfov_deg), "hfov")
    f = exif_focal_px(photo, width, height) if photo is not None else None
    if f is not None:
        return PhotoCamera(np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]]), "exif")
    if points is not None:
        f, dz, res = fit_point_map(points)
        log.info("eq. (1) fit: f = %.1f px, dz = %.3g, RMS residual %.3g px", f, dz, res)
        return PhotoCamera(np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]]), "point_map", res, dz)
    log.warning("no calibration, --hfov, EXIF focal length or point map: assuming a %.0f deg horizontal field of "
                "view (a depth-only network cannot tell the focal length); pass --hfov or --calib to fix it",
                default_hfov_deg)
    return PhotoCamera(K_from_hfov(width, height, default_hfov_deg), "default")


@dataclass(frozen=True)
class ScaleFrom:
    """A metric scale constraint (see the module docstring for the text forms)."""

    kind: Literal["distance", "pixel", "depth", "cad"]
    value_m: float = 0.0
    pixel: tuple[int, int] = (0, 0)
    path: Path | None = None
    pose: str = ""


def parse_scale(text: str) -> ScaleFrom:
    """``distance:D``, ``pixel:U,V:D`` or ``depth:PATH`` -> :class:`ScaleFrom`."""
    kind, _, rest = text.partition(":")
    try:
        if kind == "distance":
            d = float(rest)
            if d > 0 and np.isfinite(d):
                return ScaleFrom("distance", d)
        elif kind == "pixel":
            uv, _, d_text = rest.rpartition(":")
            u, v = (int(x) for x in uv.split(","))
            d = float(d_text)
            if d > 0 and np.isfinite(d):
                return ScaleFrom("pixel", d, (u, v))
        elif kind == "depth" and rest:
            return ScaleFrom("depth", path=Path(rest))
        elif kind == "cad" and ":" in rest:
            scene, _, pose = rest.rpartition(":")
            return ScaleFrom("cad", path=Path(scene), pose=pose)
    except ValueError:
        pass
    raise InputError(f"--scale-from {text!r}: give 'distance:METRES' (median depth), 'pixel:U,V:METRES' or "
                     "'depth:PATH' (sparse metric depth, .npz depth_m or uint16 PNG in mm) or 'cad:SCENE.toml:POSE' "
                     "(the CAD seen from the camera pose POSE: a JSON or x,y,z,roll,pitch,yaw)")


def _sparse_depth(path: Path, shape: tuple[int, int]) -> np.ndarray:
    if not Path(path).is_file():
        raise InputError(f"--scale-from depth: {path} not found")
    if Path(path).suffix.lower() == ".npz":
        with np.load(path) as z:
            if "depth_m" not in z.files:
                raise InputError(f"--scale-from depth: {path} has no 'depth_m' array")
            d = np.asarray(z["depth_m"], np.float64)
    else:
        d = read_image(Path(path), unchanged=True).astype(np.float64) / 1000.0
    if d.shape != shape:
        raise InputError(f"--scale-from depth: {path} is {d.shape}, the photo {shape}")
    return d


def scale_factor(depth: np.ndarray, spec: ScaleFrom, K: np.ndarray | None = None) -> float:
    """The factor that makes ``depth`` (z-depth up to scale, <= 0 / NaN invalid) satisfy ``spec``.

    Raises:
        InputError: the constraint falls on pixels without depth, or outside the photo.
    """
    ok = np.isfinite(depth) & (np.nan_to_num(depth) > 0)
    if spec.kind == "distance":
        if not ok.any():
            raise InputError("--scale-from distance: the depth map has no valid pixel")
        return spec.value_m / float(np.median(depth[ok]))
    if spec.kind == "pixel":
        u, v = spec.pixel
        if not (0 <= v < depth.shape[0] and 0 <= u < depth.shape[1]) or not ok[v, u]:
            raise InputError(f"--scale-from pixel:{u},{v}: outside the {depth.shape[1]}x{depth.shape[0]} photo or "
                             "without predicted depth there; pick another pixel")
        return spec.value_m / float(depth[v, u])
    ref = reference_depth(spec, depth.shape, K)
    both = ok & np.isfinite(ref) & (np.nan_to_num(ref) > 0)
    if both.sum() < 1:
        raise InputError(f"--scale-from {spec.kind}:{spec.path}: no pixel has both a reference and a predicted "
                         "depth")
    return float(np.median(ref[both] / depth[both]))


def reference_depth(spec: ScaleFrom, shape: tuple[int, ...], K: np.ndarray | None) -> np.ndarray:
    """(H, W) metric reference z-depth of a ``depth`` or ``cad`` constraint (0 = none); ``K`` for ``cad``."""
    assert spec.path is not None and spec.kind in ("depth", "cad")
    if spec.kind == "depth":
        return _sparse_depth(spec.path, tuple(shape))
    if K is None:
        raise InputError("--scale-from cad: the camera intrinsics are needed to render the CAD")
    if not spec.path.is_file():
        raise InputError(f"--scale-from cad: scene spec {spec.path} not found")
    view = render(scene_mesh(spec.path), Camera(K, shape[1], shape[0]), parse_pose(spec.pose))
    return np.asarray(view.depth_m, np.float64)


def fit_disparity(disparity: np.ndarray, ref_depth_m: np.ndarray) -> tuple[float, float]:
    """``(a, b)`` with ``1 / ref = a * disparity + b`` (least squares over pixels valid in both).

    Raises:
        InputError: fewer than 2 common pixels, or one disparity value only (then only a scale is defined).
    """
    ok = np.isfinite(disparity) & np.isfinite(ref_depth_m) & (np.nan_to_num(ref_depth_m) > 0)
    x, y = disparity[ok], 1.0 / ref_depth_m[ok]
    if len(x) < 2 or np.ptp(x) <= 1e-12 * max(float(np.abs(x).max()), 1e-300):
        raise InputError("--scale-from: the reference depth overlaps the prediction on too few distinct pixels "
                         "to fit scale and shift; give a denser reference or 'distance:METRES'")
    a, b = np.polyfit(x, y, 1)
    return float(a), float(b)
