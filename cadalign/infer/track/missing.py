"""Which parts of a tracked frame to report: each part's checks (its edges, its colours, the structure's contours it
hides) and what the checks remember from frame to frame (:class:`PartMemory`). A part that fails them is reported
missing, not placed (docs/tuning/tracker.md#missing-parts)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from cadalign.infer.pipeline import PoseRecord
from cadalign.infer.track.config import TrackRunConfig
from cadalign.infer.track.hidden import HiddenSeen
from cadalign.infer.track.parts import part_record
from cadalign.infer.track.tracker import TrackStep
from cadalign.sim.structure import Structure


@dataclass
class PartMemory:
    """What the missing-part check remembers of each part (ray-cast instance) from frame to frame."""

    missing: dict[int, bool] = field(default_factory=dict)
    """Whether the part was found missing when last checked (no entry: never checked). Parts too small to check
    in a frame keep this verdict."""
    doubts: dict[int, int] = field(default_factory=dict)
    """Missing verdicts in a row of a part last found present (``TrackRunConfig.confirm_missing``)."""
    deep: dict[int, list[tuple[int, float, float]]] = field(default_factory=dict)
    """Per part, its last frames' deep hidden samples: (count, share with an edge, the frame's edge support)."""

    def note_deep(self, k: int, seen: HiddenSeen | None, support: float, frames: int) -> None:
        """Keep this frame's deep hidden samples of part ``k`` (if any) among its last ``frames``."""
        if seen is not None and seen.deep_samples > 0:
            past = self.deep.setdefault(k, [])
            past.append((seen.deep_samples, seen.deep_seen, support))
            del past[:-frames]

    def absent(self, k: int, cfg: TrackRunConfig) -> bool:
        """Whether the structure's contours part ``k`` hides deep inside its outline, pooled over the frames
        :meth:`note_deep` kept, show as the rest of the structure does (``TrackRunConfig.absent_seen``)."""
        past = self.deep.get(k, [])
        n = sum(d[0] for d in past)
        if n < cfg.absent_samples:
            return False
        shown = sum(d[0] * d[1] for d in past) / n
        return shown >= cfg.absent_seen * float(np.median([d[2] for d in past]))

    def take_over(self, row: dict, structure: Structure) -> None:
        """The verdicts of a ``track.jsonl`` line (an interrupted run's last frame): its missing parts are missing,
        the parts it checked otherwise present."""
        names = {o.name: i + 1 for i, o in enumerate(structure.objects)}
        for name in row.get("part_support") or {}:
            if name in names:
                self.missing[names[name]] = False
        for name in row.get("missing_parts") or []:
            if name in names:
                self.missing[names[name]] = True

    def update(self, k: int, verdict: bool, confirm: int) -> None:
        """One check's verdict: it decides for a part never checked or found missing; a part found present is
        called missing after ``confirm`` missing verdicts in a row."""
        if k not in self.missing or self.missing[k]:
            self.missing[k], self.doubts[k] = verdict, 0
            return
        self.doubts[k] = self.doubts.get(k, 0) + 1 if verdict else 0
        self.missing[k] = self.doubts[k] >= confirm


def part_records(step: TrackStep, frame_index: int, name: str, structure: Structure, cfg: TrackRunConfig,
                 memory: PartMemory | None = None, hidden: dict[int, HiddenSeen] | None = None,
                 ) -> tuple[list[PoseRecord], list[str]]:
    """The records of one tracked frame's visible parts, and the names of parts found missing.

    ``memory``: what earlier frames' checks found (pass the same one for every frame of a video). ``hidden``:
    per part, the structure's contour samples it hides and the share the image shows
    (:meth:`~cadalign.infer.track.hidden.HiddenContours.seen`)."""
    memory = PartMemory() if memory is None else memory
    if step.T_cam_from_world is None or step.fit is None or step.fit.instance is None:
        return [], []
    inst = step.fit.instance
    counts = np.bincount(inst.ravel(), minlength=len(structure.objects) + 1)
    out, missing = [], []
    for i, o in enumerate(structure.objects):
        k = i + 1
        if counts[k] < cfg.min_visible_px:
            continue
        n, share, conc = step.fit.instance_support.get(k, (0, 0.0, 0.0))
        region = step.fit.instance_region.get(k, float("nan"))
        edges_gone = n >= cfg.min_part_samples and (share < cfg.min_part_support or conc < cfg.min_part_concentration)
        behind = (hidden or {}).get(k)
        memory.note_deep(k, behind, step.fit.support, cfg.absent_checks)
        if memory.absent(k, cfg):  # the structure shows where it should be
            memory.update(k, True, cfg.confirm_missing)
        elif behind and behind.samples >= cfg.min_hidden_samples and behind.seen < cfg.hidden_seen * step.fit.support:
            memory.update(k, False, cfg.confirm_missing)  # it hides the structure's contours: it is there
        elif n >= cfg.min_region_samples and np.isfinite(region):
            if memory.missing.get(k):
                memory.update(k, bool(region < cfg.present_part_region or edges_gone), cfg.confirm_missing)
            else:
                memory.update(k, bool((region < cfg.min_part_region and share < cfg.missing_part_edges) or edges_gone),
                              cfg.confirm_missing)
        elif n >= cfg.min_part_samples:
            memory.update(k, bool(edges_gone), cfg.confirm_missing)
        if memory.missing.get(k):
            missing.append(o.name)
            continue
        score = float(share) if n else float(step.fit.support)
        out.append(part_record(structure, k, step.T_cam_from_world, inst == k, score, frame_index, name, "tracked"))
    return out, missing
