"""Movable parts: each part the scene declares ``movable`` is tracked on its own, beside the structure.

A movable part (a hot stab tool in an ROV's grip) is not where the CAD layout puts it, so it is left out of the
structure's rigid assembly and gets a :class:`~cadalign.infer.track.tracker.StructureTracker` of its own: the
same prediction, contour and region correction and quality gates, with the part's mesh at its CAD placement as
the "structure". What that tracker follows is the camera relative to the part's CAD placement, so the part's
pose is ``T_cam_from_placement @ T_world_from_obj``. It starts (and restarts when lost) from the detector's poses
of that part, and from the part's CAD place at the structure's pose (a tool that has not moved yet).
"""

from __future__ import annotations

import numpy as np

from cadalign.infer.pipeline import PoseRecord
from cadalign.infer.track.config import MovableConfig
from cadalign.infer.track.tracker import StructureTracker, TrackStep
from cadalign.sim.structure import Structure
from cadalign.types import Camera, Rigid3


def part_record(structure: Structure, k: int, T_cam_from_world: Rigid3, mask: np.ndarray, score: float,
                frame_index: int, frame_name: str, source: str) -> PoseRecord:
    """The pose record of part ``k`` (ray-cast instance, object ``k - 1``) placed by ``T_cam_from_world`` (the
    structure's, or a movable part's placement), with its visible ``mask`` (H, W) and its box."""
    o = structure.objects[k - 1]
    T = T_cam_from_world @ o.T_world_from_obj
    return PoseRecord(frame_index, frame_name, o.obj_id, k, o.class_id, structure.class_names[o.class_id], score,
                      mask_box(mask), T, T, T, {}, mask, source)


def mask_box(mask: np.ndarray) -> np.ndarray:
    """(4,) ``[x0, y0, x1, y1]`` pixel-edge box of a non-empty (H, W) mask."""
    ys, xs = np.nonzero(mask)
    return np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], dtype=np.float64)


def split_hypotheses(hypotheses: list[tuple[str, Rigid3]], structure: Structure,
                     ) -> tuple[list[tuple[str, Rigid3]], dict[str, list[tuple[str, Rigid3]]]]:
    """Restart hypotheses named ``detector:CLASS:PART`` -> (those for the structure, those per movable part)."""
    rigid: list[tuple[str, Rigid3]] = []
    parts: dict[str, list[tuple[str, Rigid3]]] = {n: [] for n in structure.movable}
    for name, T in hypotheses:
        part = name.rsplit(":", 1)[-1]
        (parts[part] if part in parts else rigid).append((name, T))
    return rigid, parts


class MovableParts:
    """The trackers of a structure's movable parts (empty when it declares none)."""

    def __init__(self, structure: Structure, camera: Camera, cfg: MovableConfig | None = None) -> None:
        self.cfg = cfg or MovableConfig()
        self.structure = structure
        self.trackers = {m.instance: StructureTracker([m], camera, self.cfg.tracker)
                         for m in structure.render_meshes(movable=True)}

    @property
    def lost(self) -> bool:
        """Whether any movable part has no track (the detector is worth running)."""
        return any(t.lost for t in self.trackers.values())

    def step(self, gray: np.ndarray, rgb: np.ndarray | None, structure_pose: Rigid3 | None,
             hypotheses: dict[str, list[tuple[str, Rigid3]]]) -> dict[int, TrackStep]:
        """Track every movable part in one frame. ``structure_pose``: the structure's ``T_cam_from_world`` this
        frame (None while lost); ``hypotheses``: the detector's, per part name (``T_cam_from_world`` of the
        part's placement, as :func:`split_hypotheses` gives them)."""
        out = {}
        for k, tr in self.trackers.items():
            name = self.structure.objects[k - 1].name
            restarts = list(hypotheses.get(name, [])) if tr.lost else []
            if tr.lost and structure_pose is not None:
                restarts.append(("cad_place", structure_pose))
            out[k] = tr.step(gray, restarts, rgb)
        return out

    def records(self, steps: dict[int, TrackStep], frame_index: int, frame_name: str,
                min_visible_px: int) -> list[PoseRecord]:
        """The pose records (``source``: ``tracked_part``) of the parts tracked in this frame."""
        out = []
        for k, step in steps.items():
            f = step.fit
            if step.T_cam_from_world is None or f is None or f.instance is None:
                continue
            mask = f.instance == k
            if int(mask.sum()) < min_visible_px:
                continue
            out.append(part_record(self.structure, k, step.T_cam_from_world, mask, float(f.support), frame_index,
                                   frame_name, "tracked_part"))
        return out

    def summary(self, steps: dict[int, TrackStep]) -> dict[str, dict]:
        """Per movable part, for track.jsonl: state, source, support and ``T_cam_from_obj``."""
        out = {}
        for k, s in steps.items():
            o = self.structure.objects[k - 1]
            out[o.name] = {"state": s.state, "source": s.source or None,
                           "support": None if s.fit is None else round(float(s.fit.support), 4),
                           "T_cam_from_obj": None if s.T_cam_from_world is None
                           else (s.T_cam_from_world @ o.T_world_from_obj).matrix().tolist()}
        return out
