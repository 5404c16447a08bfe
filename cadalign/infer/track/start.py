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

import cv2
import numpy as np

from cadalign.geometry.camera import project
from cadalign.infer import detect as det
from cadalign.infer.run import resolve_prep
from cadalign.sfm import image_prep
from cadalign.sim.structure import Structure
from cadalign.types import Camera, Rigid3


def hypotheses(detections: list, structure: Structure, class_names: tuple[str, ...], max_hypotheses: int = 6,
               ) -> list[tuple[str, Rigid3]]:
    """(name, ``T_cam_from_world``) proposals from detections (best score first), at most ``max_hypotheses``,
    named ``detector:CLASS:PART``. A movable part's proposal is of its own CAD placement, not the structure's
    (:func:`cadalign.infer.track.parts.split_hypotheses` tells them apart)."""
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


def centre_hypotheses(detections: list, structure: Structure, class_names: tuple[str, ...], camera: Camera,
                      iterations: int = 300, inlier_px: float | None = None, seed: int = 0,
                      ) -> list[tuple[str, Rigid3]]:
    """A structure pose from where the parts were detected, not from the pose head: PnP with RANSAC of the
    detections' centres (mask centroid, else box centre) against the CAD's part centres of the same class. A
    class with several instances makes each detection ambiguous, so each RANSAC sample also draws which
    instance each of its 4 detections is. Returns ``[("detector:centres", T_cam_from_world)]`` when at least 4
    detections agree within ``inlier_px`` (default: 4 % of the image width), else ``[]``."""
    tol = 0.04 * camera.width if inlier_px is None else inlier_px
    uv, cls = [], []
    for d in detections:
        name = class_names[d.label] if 0 <= d.label < len(class_names) else None
        m = np.asarray(d.mask) if d.mask is not None else np.zeros((0, 0), bool)
        if m.any():
            ys, xs = np.nonzero(m)
            c = np.array([xs.mean(), ys.mean()]) + 0.5  # array convention -> the intrinsics'
        else:
            b = np.asarray(d.box_xyxy, dtype=np.float64)
            c = np.array([(b[0] + b[2]) / 2, (b[1] + b[3]) / 2])  # box edges are pixel boundaries already
        uv.append(c)
        cls.append(name)
    centres = {}
    for o in structure.objects:
        if o.name in structure.movable:  # not where the CAD puts it
            continue
        v = structure.models[o.obj_id].vertices_m
        centres.setdefault(structure.class_names[o.class_id], []).append(
            o.T_world_from_obj.apply(((v.min(axis=0) + v.max(axis=0)) / 2)[None])[0])
    usable = [i for i, c in enumerate(cls) if c in centres]
    if len(usable) < 4:
        return []
    U = np.array([uv[i] for i in usable])
    C = [np.array(centres[cls[i]]) for i in usable]
    rng = np.random.default_rng(seed)
    best: tuple[int, float, Rigid3] | None = None
    for _ in range(iterations):
        pick = rng.choice(len(usable), 4, replace=False)
        X = np.array([C[j][rng.integers(len(C[j]))] for j in pick])
        if np.linalg.matrix_rank(X - X.mean(axis=0), tol=1e-3) < 2:
            continue
        ok, rvec, tvec = cv2.solvePnP(X, U[pick], camera.K, None, flags=cv2.SOLVEPNP_SQPNP)
        if not ok:
            continue
        T = Rigid3(cv2.Rodrigues(rvec)[0], tvec.ravel())
        n, err, _ = _centre_inliers(T, U, C, camera, tol)
        if best is None or (n, -err) > (best[0], -best[1]):
            best = (n, err, T)
    if best is None or best[0] < 4:
        return []
    n, _, T = best
    _, _, pairs = _centre_inliers(T, U, C, camera, tol)  # refit on every agreeing detection
    X = np.array([p[1] for p in pairs])
    if len(pairs) >= 4 and np.linalg.matrix_rank(X - X.mean(axis=0), tol=1e-3) >= 2:
        ok, rvec, tvec = cv2.solvePnP(X, np.array([p[0] for p in pairs]), camera.K, None, flags=cv2.SOLVEPNP_SQPNP)
        if ok:
            T = Rigid3(cv2.Rodrigues(rvec)[0], tvec.ravel())
    return [("detector:centres", T)]


def _centre_inliers(T: Rigid3, U: np.ndarray, C: list[np.ndarray], camera: Camera, tol: float,
                    ) -> tuple[int, float, list[tuple[np.ndarray, np.ndarray]]]:
    """(inliers, their mean error in pixels, (image centre, CAD centre) pairs) of a pose: each detection's
    nearest projected CAD centre of its class in front of the camera."""
    n, err, pairs = 0, 0.0, []
    for u, cands in zip(U, C, strict=True):
        Xc = T.apply(cands)
        front = Xc[:, 2] > 1e-6
        if not front.any():
            continue
        p, _ = project(camera.K, Xc[front])
        d = np.linalg.norm(p - u, axis=1)
        k = int(np.argmin(d))
        if d[k] <= tol:
            n, err = n + 1, err + float(d[k])
            pairs.append((u, cands[front][k]))
    return n, err / max(n, 1), pairs


def detector_restarts(model: Path | tuple, structure: Structure, camera: Camera, device: str = "cpu",
                      score_thresh: float = 0.7) -> tuple[Callable[[np.ndarray, str], list], dict]:
    """A restart source for :func:`cadalign.infer.track.run.track_video` from a trained pose network (its run
    folder, or ``(network, meta)`` as :func:`~cadalign.models.maskrcnn.detector.load_pose_model` returns them),
    and the record of what it is."""
    from cadalign.models.maskrcnn.detector import load_pose_model  # lazy: pulls torch

    net, meta = load_pose_model(model, device) if isinstance(model, Path) else model
    class_names = tuple(meta.get("classes", structure.class_names))
    detector = det.TorchDetector(net, score_thresh, device)
    info = {"kind": "network", "run": str(model) if isinstance(model, Path) else meta.get("run"),
            "step": meta.get("step")}
    prep = resolve_prep("auto", info)
    info["images"] = prep

    def source(image: np.ndarray, name: str) -> list[tuple[str, Rigid3]]:
        dets = detector.detect(image_prep.apply(image, prep), camera.K)
        return centre_hypotheses(dets, structure, class_names, camera) + hypotheses(dets, structure, class_names)

    return source, info


def pose_from_picks(uv_px: np.ndarray, xyz_world_m: np.ndarray, camera: Camera,
                    max_error_px: float = 8.0) -> tuple[Rigid3, float]:
    """``T_cam_from_world`` of a frame from points picked in it: ``uv_px`` (N, 2) pixel positions as image
    viewers give them (column, row; a pixel's centre at integers) and ``xyz_world_m`` (N, 3) the same points
    on the CAD, scene frame, metres (N >= 4; 6 or more spread over the structure are safer). Returns the pose
    and the picks' RMS reprojection error, pixels. Raises ``ValueError`` when the picks are too few, degenerate,
    or disagree by more than ``max_error_px`` RMS (a point picked on the wrong corner)."""
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
    proj, _ = project(camera.K, Xc)
    rms = float(np.sqrt(np.mean(np.sum((proj - uv) ** 2, axis=1))))
    if rms > max_error_px:
        raise ValueError(f"the picks disagree: {rms:.1f} px RMS reprojection error (limit {max_error_px} px)")
    return T, rms
