"""Restart hypotheses of the structure pose from a trained detector (``cadalign train pose``).

Each confident detection of a class, with its pose head's ``T_cam_from_obj``, proposes the structure pose
``T_cam_from_obj @ inv(T_world_from_obj)`` for every instance of that class in the CAD. The network's part
poses are coarse (tens of centimetres, tens of degrees at 10 m), so each proposal is a rough pose for the
tracker's pan/tilt/roll search and contour fit, which keeps the best-supported result.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from cadalign.infer import detect as det
from cadalign.infer.run import resolve_prep
from cadalign.sfm import image_prep
from cadalign.sim.structure import Structure
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
        return hypotheses(dets, structure, class_names)

    return source, info
