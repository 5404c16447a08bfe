"""What the SfM stage writes besides COLMAP's model: ``cameras.json``, report numbers, trajectory plot.

``cameras.json`` has the simulator's ground-truth format
(``{"frames": {name: {"K", "width", "height", "R_cam_from_world", "t_cam_from_world_m"}}}``, K and R
row-major) so the evaluation and later stages read both the same way. SfM translations are in SfM
units (the model's arbitrary scale), which the file says in ``"units"``; ``t_cam_from_world_m`` keeps
its name for format compatibility.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from cadalign.formats.calibration import camera_pose_arrays, read_calibration
from cadalign.io import atomic_path

SFM_UNITS = "sfm"
"""Value of ``cameras.json['units']`` for an unscaled SfM model (metres after alignment: 'm')."""


def camera_K(cam: Any) -> np.ndarray:
    """The (3, 3) pinhole matrix of a pycolmap camera (distortion parameters are not in K)."""
    K = np.eye(3)
    K[0, 0], K[1, 1] = cam.focal_length_x, cam.focal_length_y
    K[0, 2], K[1, 2] = cam.principal_point_x, cam.principal_point_y
    return K


def camera_record(cam: Any) -> dict[str, Any]:
    """The shared camera as JSON: COLMAP model and parameters plus K."""
    return {
        "model": cam.model_name,
        "params": [float(v) for v in cam.params],
        "K": camera_K(cam).ravel().tolist(),
        "width": int(cam.width),
        "height": int(cam.height),
    }


def registered_images(rec: Any) -> list[Any]:
    """Registered images of a reconstruction, sorted by name."""
    return sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)


def cameras_json(rec: Any) -> dict[str, Any]:
    """Per registered frame ``K``, size and ``T_cam_from_world`` in the simulator's format (SfM units)."""
    frames = {}
    for im in registered_images(rec):
        T = im.cam_from_world()
        cam = im.camera
        frames[im.name] = {
            "K": camera_K(cam).ravel().tolist(),
            "width": int(cam.width),
            "height": int(cam.height),
            "R_cam_from_world": T.rotation.matrix().ravel().tolist(),
            "t_cam_from_world_m": [float(v) for v in T.translation],
        }
    cam = next(iter(rec.cameras.values()))
    return {
        "units": SFM_UNITS,
        "note": "t_cam_from_world_m is in SfM units (arbitrary scale) until the CAD alignment fixes it",
        "camera": camera_record(cam),
        "frames": frames,
    }


def model_stats(rec: Any) -> dict[str, Any]:
    """Size and quality numbers of one reconstruction."""
    n = rec.num_points3D()
    return {
        "registered": int(rec.num_reg_images()),
        "points": int(n),
        "observations": int(rec.compute_num_observations()) if n else 0,
        "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error()) if n else None,
        "mean_track_length": float(rec.compute_mean_track_length()) if n else None,
        "mean_observations_per_frame": float(rec.compute_mean_observations_per_reg_image()) if n else None,
    }


def intrinsics_from_cameras_json(path: Path) -> tuple[float, float, float, float]:
    """``(fx, fy, cx, cy)`` (pixel centres at +0.5) of a calibration file in any ``--calib`` format
    (:func:`cadalign.formats.calibration.read_calibration`)."""

    return read_calibration(path).intrinsics


def camera_centres(cameras: dict[str, Any]) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Names, (N, 3) centres ``-R^T t`` and (N, 3, 3) ``R_cam_from_world`` of a cameras.json dict."""
    names, R, t = camera_pose_arrays(cameras, sorted(cameras["frames"]))
    C = -np.einsum("nji,nj->ni", R, t)
    return names, C, R


def plot_trajectory(
    path: Path, est_xy: np.ndarray, gt_xy: np.ndarray | None = None, points_xy: np.ndarray | None = None,
    title: str = "", units: str = "SfM units", errors: dict[str, np.ndarray] | None = None,
) -> Path:
    """Top-down plot of camera centres (estimated, optionally ground truth and sparse points), PNG.

    Uses matplotlib's object API with the Agg canvas, so no global backend is switched.

    Args:
        path: output PNG.
        est_xy: (N, 2) estimated centres (already in the plot frame).
        gt_xy: (N, 2) true centres in the same order, or None.
        points_xy: (M, 2) sparse points to draw faintly, or None; the view is cropped to the
            2nd-98th percentile of the points so a few far outliers do not shrink the trajectory.
        title: figure title (may contain a newline).
        units: axis unit label.
        errors: optional per-frame series, e.g. ``{"rotation [deg]": (N,), "centre [m]": (N,)}``,
            drawn in a second panel against the frame index.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # lazy: heavy dependency (matplotlib)
    from matplotlib.figure import Figure  # lazy: heavy dependency (matplotlib)

    fig = Figure(figsize=(12.0 if errors else 6.4, 6.0), dpi=110)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 2 if errors else 1, 1)
    if points_xy is not None and len(points_xy):
        ax.scatter(points_xy[:, 0], points_xy[:, 1], s=0.5, c="0.75", label="sparse points", rasterized=True)
        lo = np.minimum(np.percentile(points_xy, 2, axis=0), est_xy.min(0))
        hi = np.maximum(np.percentile(points_xy, 98, axis=0), est_xy.max(0))
        pad = 0.05 * float(np.max(hi - lo))
        ax.set_xlim(lo[0] - pad, hi[0] + pad)
        ax.set_ylim(lo[1] - pad, hi[1] + pad)
    if gt_xy is not None:
        ax.plot(gt_xy[:, 0], gt_xy[:, 1], "-o", ms=3, c="tab:green", label="ground truth")
        for a, b in zip(est_xy, gt_xy, strict=True):
            ax.plot([a[0], b[0]], [a[1], b[1]], c="tab:red", lw=0.8)
    label = "SfM (Sim(3) aligned)" if gt_xy is not None else "SfM"
    ax.plot(est_xy[:, 0], est_xy[:, 1], "-x", ms=4, c="tab:blue", label=label)
    ax.plot(est_xy[:1, 0], est_xy[:1, 1], "s", c="k", ms=6, label="first frame")
    ax.set_aspect("equal", adjustable="box" if points_xy is not None and len(points_xy) else "datalim")
    ax.set_xlabel(f"x [{units}]")
    ax.set_ylabel(f"y [{units}]")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    if errors:
        ax2 = fig.add_subplot(1, 2, 2)
        for name, values in errors.items():
            ax2.plot(np.arange(len(values)), values, "-o", ms=2.5, label=name)
        ax2.set_xlabel("evaluated frame (capture order)")
        ax2.set_title("per-frame error after the Sim(3) fit", fontsize=10)
        ax2.grid(alpha=0.3)
        ax2.legend(loc="best", fontsize=8)
    fig.suptitle(title or "camera trajectory (top-down)", fontsize=10)
    fig.tight_layout()
    with atomic_path(Path(path)) as tmp:
        fig.savefig(tmp, format="png")
    return Path(path)


def topdown_frame(centres: np.ndarray) -> np.ndarray:
    """A (3, 3) rotation whose first two rows span the best-fit plane of the camera centres (PCA).

    SfM has no notion of 'up'; for a survey trajectory the cameras roughly lie in a plane, so
    looking along its normal gives the top-down view.
    """
    c = centres - centres.mean(0)
    if len(c) < 3:
        return np.eye(3)
    _, _, Vt = np.linalg.svd(c, full_matrices=True)
    if np.linalg.det(Vt) < 0:
        Vt[2] *= -1
    return Vt
