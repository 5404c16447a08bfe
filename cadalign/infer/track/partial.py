"""The files of a tracker run that may be interrupted (:func:`cadalign.infer.track.run.track_video`).

While a run goes on, each finished frame is appended to ``poses.jsonl.partial`` and ``track.jsonl.partial``, and its
overlay picture to ``overlay.partN.mp4``. A run stopped by Ctrl-C, a crash or a kill keeps every finished frame; the
same command takes them over (:func:`take_over`) and resumes after the last one.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cadalign.infer.pipeline import PoseRecord
from cadalign.infer.run import read_poses
from cadalign.infer.track.tracker import StructureTracker
from cadalign.infer.video import overlay_pieces
from cadalign.types import Rigid3

log = logging.getLogger(__name__)

PARTIAL = ".partial"
"""Suffix of ``poses.jsonl`` and ``track.jsonl`` while a run writes them: an interrupted run keeps every finished
frame there, and the same command resumes after the last one (``overlay.partN.mp4``: the overlay's pieces)."""


@dataclass
class Finished:
    """What an interrupted run of the same config left: its finished frames."""

    rows: list[dict] = field(default_factory=list)
    """Their ``track.jsonl`` lines."""
    records: list[PoseRecord] = field(default_factory=list)
    """Their ``poses.jsonl`` records."""
    overlays: list[Path] = field(default_factory=list)
    """Their overlay pieces, in order."""

    def resume(self, tracker: StructureTracker) -> bool:
        """Carry the finished frames' track on in ``tracker`` (:meth:`StructureTracker.resume`); False when none of
        them was tracked (the run starts as a new one)."""
        ok = [i for i, r in enumerate(self.rows) if r["state"] == "ok"]
        if not ok:
            return False
        i = ok[-1]
        poses = [_pose(self.rows[j]) for j in (i - 1, i) if j >= 0 and self.rows[j]["state"] == "ok"]
        tail = [self.rows[j] for j in ok[-tracker.cfg.history:]]
        tracker.resume(poses, [r["support"] for r in tail],
                       [r["region_support"] for r in tail if r.get("region_support") is not None],
                       lost_frames=len(self.rows) - 1 - i)
        return True


def _pose(row: dict) -> Rigid3:
    return Rigid3.from_matrix(np.asarray(row["T_cam_from_world"]))


def take_over(out_dir: Path, same_config: bool) -> Finished:
    """The finished frames of an interrupted run of the same config in ``out_dir`` (a torn last line dropped, the
    poses of frames without a ``track.jsonl`` line too); with another config, its partial files are deleted."""
    track, poses = out_dir / f"track.jsonl{PARTIAL}", out_dir / f"poses.jsonl{PARTIAL}"
    overlays = overlay_pieces(out_dir)
    if not same_config or not track.is_file():
        for p in [track, poses, *overlays]:
            p.unlink(missing_ok=True)
        return Finished()
    rows = whole_lines(track)
    last = rows[-1]["frame"] if rows else -1
    kept = [d for d in whole_lines(poses) if d["frame"] <= last] if poses.is_file() else []
    track.write_text("".join(json.dumps(r) + "\n" for r in rows), encoding="utf-8")
    poses.write_text("".join(json.dumps(d) + "\n" for d in kept), encoding="utf-8")
    return Finished(rows, read_poses(poses), overlays)


def whole_lines(path: Path) -> list[dict]:
    """The JSON lines of a file a killed run may have cut inside its last line (that line is dropped)."""
    out = []
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            out.append(json.loads(line))
        except ValueError:
            break
    return out
