"""Start and restart hypotheses of the structure pose: from a trained detector (``cadalign train pose``), and
from points a user picked in the first frame (:func:`pose_from_picks`).

Each confident detection of a class, with its pose head's ``T_cam_from_obj``, proposes the structure pose
``T_cam_from_obj @ inv(T_world_from_obj)`` for every instance of that class in the CAD. The network's part
poses are coarse (tens of centimetres, tens of degrees at 10 m), so each proposal is a rough pose for the
tracker's pan/tilt/roll search and contour fit, which keeps the best-supported result.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from cadalign.build_dataset import Structure
from cadalign.types import Camera, Rigid3


def hypotheses(detections: list, structure: Structure, class_names: tuple[str, ...], max_hypotheses: int = 6,
               ) -> list[tuple[str, Rigid3]]:
    """(name, ``T_cam_from_world``) proposals from detections (best score first), at most ``max_hypotheses``."""
    out: list[tuple[str, Rigid3]] = []
    for d in sorted(detections, key=lambda d: -float(d.score)):
        cls = class_names[d.label] if 0 <= d.label < len(class_names) else None
        T_co = Rigid3(np.asarray(d.R_cam_from_obj), np.asarray(d.t_cam_from_obj_m))
        for o in structure.objects:
            if structure.class_names[o.class_id] != cls or (d.obj_id is not None and d.obj_id != o.obj_id):
                continue
            out.append((f"detector:{cls}:{o.name}", T_co @ o.T_world_from_obj.inverse()))
            if len(out) >= max_hypotheses:
                return out
    return out


def detector_restarts(model: Path | tuple, structure: Structure, camera: Camera, device: str = "cpu",
                      score_thresh: float = 0.7) -> tuple[Callable[[np.ndarray, str], list], dict]:
    """A restart source for :func:`cadalign.infer.track.run.track_video` from a trained pose network (its run
    folder, or ``(network, meta)`` as :func:`~cadalign.models.maskrcnn.detector.load_pose_model` returns them),
    and the record of what it is."""
    from cadalign.data import image_prep
    from cadalign.infer import detect as det
    from cadalign.infer.run import resolve_prep
    from cadalign.models.maskrcnn.detector import load_pose_model

    net, meta = load_pose_model(model, device) if isinstance(model, Path) else model
    class_names = tuple(meta.get("classes", structure.class_names))
    detector = det.TorchDetector(net, score_thresh, device)
    info = {"kind": "network", "run": str(model) if isinstance(model, Path) else meta.get("run"),
            "step": meta.get("step")}
    prep = resolve_prep("auto", info)
    info["images"] = prep

    def source(image: np.ndarray, name: str) -> list[tuple[str, Rigid3]]:
        dets = detector.detect(image_prep.apply(image, prep), camera.K)
        return hypotheses(dets, structure, class_names)

    return source, info


def pose_from_picks(uv_px: np.ndarray, xyz_world_m: np.ndarray, camera: Camera,
                    max_error_px: float = 8.0) -> tuple[Rigid3, float]:
    """``T_cam_from_world`` of a frame from points picked in it: ``uv_px`` (N, 2) pixel positions as image
    viewers give them (column, row; a pixel's centre at integers) and ``xyz_world_m`` (N, 3) the same points
    on the CAD, scene frame, metres (N >= 4; 6 or more spread over the structure are safer). Returns the pose
    and the picks' RMS reprojection error, pixels. Raises ``ValueError`` when the picks are too few, degenerate,
    or disagree by more than ``max_error_px`` RMS (a point picked on the wrong corner)."""
    import cv2  # lazy: cv2 is only needed for this start

    uv = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2) + 0.5  # to the intrinsics' convention
    X = np.asarray(xyz_world_m, dtype=np.float64).reshape(-1, 3)
    if len(uv) != len(X):
        raise ValueError(f"{len(uv)} image points but {len(X)} CAD points")
    if len(uv) < 4:
        raise ValueError(f"{len(uv)} picked points; at least 4 (better 6) are needed")
    if np.linalg.matrix_rank(X - X.mean(axis=0), tol=1e-6) < 2:
        raise ValueError("the CAD points are (nearly) collinear")
    ok, rvec, tvec = cv2.solvePnP(X, uv, camera.K, None, flags=cv2.SOLVEPNP_SQPNP)
    if not ok:
        raise ValueError("no pose fits the picked points")
    rvec, tvec = cv2.solvePnPRefineLM(X, uv, camera.K, None, rvec, tvec)
    R, _ = cv2.Rodrigues(rvec)
    T = Rigid3(R, tvec.ravel())
    Xc = T.apply(X)
    if np.any(Xc[:, 2] <= 0):
        raise ValueError("the pose that fits the picks puts some points behind the camera")
    proj = Xc[:, :2] / Xc[:, 2:] * np.diag(camera.K)[:2] + camera.K[:2, 2]
    rms = float(np.sqrt(np.mean(np.sum((proj - uv) ** 2, axis=1))))
    if rms > max_error_px:
        raise ValueError(f"the picks disagree: {rms:.1f} px RMS reprojection error (limit {max_error_px} px)")
    return T, rms
