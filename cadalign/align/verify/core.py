"""Image verification of a CAD alignment: judge each placement by the images, not by the sparse cloud alone.

Near a small CAD the sparse SfM cloud also holds the table, the seabed and clutter, so a wrong placement can fit
the cloud as well as the right one (fitness, RMSE and the symmetry margin all pass). The images cannot be fooled
the same way. Every hypothesis (the refined global candidates, see :class:`~cadalign.align.AlignResult`) is first
moved to its nearest fit of the image contours (:func:`refine_locally`), then scored:

(a) Edges, as a contrast. The CAD is rendered from a few registered cameras; its occluding contours
    (:func:`~cadalign.align.edge_refine.contour_samples`) are searched for an image edge of the right sign within
    ``near_px`` (:func:`~cadalign.align.edge_refine.search_edges`). The same search is repeated with every
    contour displaced along its normal by ``shifts_px`` (a slightly wrong pose, without a render). Clutter raises
    both hit rates alike, so the score is the lift ``(h0 - h_shifted) / (1 - h_shifted)``: near 0 for a CAD
    drawn over texture where it is not, clearly positive where the images have its outline. It is computed per
    CAD part and averaged over the parts, so a big symmetric part cannot outvote the small asymmetric ones.
(b) Free space. An SfM point is seen by its track's cameras; if the ray from such a camera to the point meets the
    placed CAD well before the point, the point was seen *through* the CAD: a violation. The share of violating
    rays among those meeting the CAD is near 0 at the right pose.
(c) Photo-consistency of the CAD surface across views (:func:`photo_consistency`): reported, not gated.

The hypotheses are ranked by ``edge * (1 - free_violation)``; look-alikes (hypotheses placing the CAD on the same
points, e.g. the turns of a symmetric structure) count once. The chosen one gets an outcome: ``ok``,
``uncertain`` (weak evidence, or a runner-up within the margin) or ``wrong`` (the images contradict it).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from cadalign.align.verify.config import VerifyConfig
from cadalign.align.verify.evidence import (
    FreeSpaceRays,
    View,
    cad_scene,
    edge_evidence,
    free_space_evidence,
    free_space_rays,
    part_lift,
    photo_consistency,
    refine_locally,
    surface_samples,
)
from cadalign.config import to_dict
from cadalign.errors import InputError
from cadalign.raycast.core import RaycastRenderer, RenderMesh
from cadalign.types import Sim3

__all__ = ["FreeSpaceRays", "HypothesisEvidence", "Verification", "VerifyConfig", "View", "decide", "free_space_rays",
           "score_hypotheses", "verify"]

log = logging.getLogger(__name__)

@dataclass(frozen=True)
class HypothesisEvidence:
    """The image evidence of one hypothesis ``cad_from_sfm``.

    Attributes:
        index: its position in the alignment's hypothesis list (``--hypothesis N``).
        cloud_score: the alignment's final fit F-score (the cloud's verdict).
        edge: edge lift ``(h0 - h_shifted) / (1 - h_shifted)``, the mean over the CAD's parts (see
            :func:`part_lift`), 0 without enough samples.
        hit_rate: ``h0``, share of contour samples with an image edge where the CAD predicts one.
        hit_rate_shifted: the same with the contour displaced (chance level in this clutter).
        samples: contour samples over all frames.
        parts: CAD parts (instances) with enough contour samples to be scored.
        photo: photo-consistency of the CAD surface across the views (:func:`photo_consistency`); reported, not
            part of the decision (a uniform or shaded surface gives no evidence; not measured enough to gate).
        photo_points: surface samples seen in 3+ views behind ``photo``.
        refined: whether the local contour fit moved it before scoring (``cad_from_sfm`` is then the moved one).
        free_violation: share of rays meeting the CAD that meet it before their point (0 without evidence).
        free_rays: rays meeting the CAD.
        score: ``edge * (1 - free_violation)``, the ranking score.
        same_as: index of a better-ranked look-alike hypothesis, or -1.
    """

    index: int
    cloud_score: float
    edge: float
    hit_rate: float
    hit_rate_shifted: float
    samples: int
    free_violation: float
    free_rays: int
    score: float
    same_as: int = -1
    refined: bool = False
    parts: int = 0
    photo: float = 0.0
    photo_points: int = 0


@dataclass(frozen=True)
class Verification:
    """The verdict on an alignment: the chosen hypothesis, the outcome with its reasons, and all evidence."""

    outcome: str
    chosen: int
    cad_from_sfm: Sim3
    margin: float | None
    """(chosen score - best distinct runner-up's) / chosen score; None with a single hypothesis."""
    runner_up: int | None
    evidence: tuple[HypothesisEvidence, ...]
    reasons: tuple[str, ...]
    fix: str
    frames: tuple[str, ...]
    user_choice: bool = False
    seconds: dict[str, float] = field(default_factory=dict)
    hypotheses: tuple[Sim3, ...] = ()
    """Every hypothesis as scored (moved by the local contour fit), by index."""

    def summary(self) -> dict[str, Any]:
        return {"outcome": self.outcome, "chosen": self.chosen, "user_choice": self.user_choice,
                "margin": self.margin, "runner_up": self.runner_up, "reasons": list(self.reasons), "fix": self.fix,
                "cad_from_sfm": self.cad_from_sfm.matrix().tolist(), "frames": list(self.frames),
                "hypotheses": [to_dict(e) for e in self.evidence], "seconds": self.seconds}


def _look_alikes(hyps: Sequence[Sim3], cad_points_m: np.ndarray, tol_m: float) -> list[list[bool]]:
    """same[i][j]: hypotheses i and j put the CAD samples on (nearly) the same SfM-frame points."""

    placed = [T.inverse().apply(cad_points_m) * T.s for T in hyps]  # SfM frame, scaled to metres
    trees = [cKDTree(p) for p in placed]
    n = len(hyps)
    same = [[i == j for j in range(n)] for i in range(n)]
    for i in range(n):
        for j in range(i + 1, n):
            dij = trees[j].query(placed[i])[0].mean()
            dji = trees[i].query(placed[j])[0].mean()
            same[i][j] = same[j][i] = bool(max(dij, dji) <= tol_m)
    return same


def score_hypotheses(views: Sequence[View], meshes: Sequence[RenderMesh], hyps: Sequence[Sim3],
                     cloud_scores: Sequence[float], rays: FreeSpaceRays, cfg: VerifyConfig, inlier_m: float,
                     ) -> tuple[list[HypothesisEvidence], list[Sim3]]:
    """The image evidence of each hypothesis (see the module doc), in the order given, and the hypotheses as
    scored (moved by the local contour fit when :attr:`VerifyConfig.refine`)."""
    renderers: dict[tuple, RaycastRenderer] = {}
    scene, origin = cad_scene(meshes)
    cad = [m for m in meshes if m.instance > 0]
    pts = np.concatenate([m.vertices_m for m in cad])
    diameter = float(np.linalg.norm(pts.max(0) - pts.min(0)))

    def renderer_of(v: View) -> RaycastRenderer:
        key = (v.camera.width, v.camera.height, tuple(np.round(v.camera.K.ravel(), 6)))
        if key not in renderers:
            renderers[key] = RaycastRenderer(cad, v.camera, rays_cam=v.rays_cam)
        return renderers[key]

    moved = [refine_locally(views, renderer_of, T, 0.5 * (pts.min(0) + pts.max(0)), diameter, cfg) if cfg.refine
             else (T, False) for T in hyps]
    hyps = [T for T, _ in moved]
    sub = pts[:: max(1, len(pts) // 3000)]
    same = _look_alikes(hyps, sub, cfg.same_rel * diameter)
    surface = surface_samples(cad, cfg.photo_points, cfg.seed)
    out = []
    for k, (T, cs) in enumerate(zip(hyps, cloud_scores, strict=True)):
        rows = np.concatenate([edge_evidence(renderer_of(v), v.gray, v.pose(T), cfg) for v in views])
        edge, hit, base, n, n_parts = part_lift(rows, cfg.min_part_samples)
        edge = edge if n >= cfg.min_samples else 0.0
        meets, viol = free_space_evidence(scene, origin, rays, T, inlier_m, cfg.free_margin_rel)
        free = viol / meets if meets >= cfg.min_free_rays else 0.0
        photo, n_photo = photo_consistency(views, scene, origin, T, surface)
        out.append(HypothesisEvidence(k, float(cs), float(edge), float(hit), float(base), int(n), float(free),
                                      int(meets), float(max(edge, 0.0) * (1.0 - free)), refined=moved[k][1],
                                      parts=n_parts, photo=photo, photo_points=n_photo))
    ranked = sorted(range(len(out)), key=lambda i: -out[i].score)
    for pos, i in enumerate(ranked):
        better = [j for j in ranked[:pos] if same[i][j]]
        if better:
            out[i] = _with_same(out[i], better[0])
    return out, hyps


def _with_same(e: HypothesisEvidence, j: int) -> HypothesisEvidence:
    return replace(e, same_as=j)


FIX = ("give 3+ picked point pairs on distinctive CAD features (--init picks.json, see cadalign.align.picks), or "
       "choose a hypothesis from verify/hypotheses.png with --hypothesis N; if the CAD is a small part of the "
       "scene, crop the cloud to it; a longer capture that circles the structure (more frames, more views) "
       "gives more edges and more points on it")


def decide(evidence: Sequence[HypothesisEvidence], hyps: Sequence[Sim3], cfg: VerifyConfig,
           choice: int | None = None) -> tuple[str, int, int | None, float | None, tuple[str, ...]]:
    """(outcome, chosen index, runner-up index, margin, reasons) from the evidence.

    ``choice``: a hypothesis a person chose (``--hypothesis N``): the margin to the others is not required, its
    own evidence is (a wrong pose a person picked by mistake is refused all the same)."""
    ranked = sorted(evidence, key=lambda e: -e.score)
    best = ranked[0] if choice is None else evidence[choice]
    others = [e for e in ranked if e.index != best.index and e.same_as < 0 and best.same_as != e.index
              and not (e.same_as == best.index)]
    runner = others[0] if others else None
    margin = None if runner is None else ((best.score - runner.score) / best.score if best.score > 0 else 0.0)
    wrong, unsure = [], []
    if best.samples < cfg.min_samples:
        unsure.append(f"too little edge evidence: {best.samples} CAD contour samples in the checked frames "
                      f"(need {cfg.min_samples}); the CAD is small or mostly out of view")
    elif best.edge < cfg.wrong_edge:
        wrong.append(f"the CAD's outline is not in the images: edge lift {best.edge:.3f} < {cfg.wrong_edge} "
                     f"(edges at {100 * best.hit_rate:.0f} % of its contour, {100 * best.hit_rate_shifted:.0f} % "
                     "when displaced)")
    elif best.edge < cfg.ok_edge:
        unsure.append(f"weak edge evidence: edge lift {best.edge:.3f} < {cfg.ok_edge}")
    if best.free_violation > cfg.wrong_free:
        wrong.append(f"SfM points were seen through the placed CAD: {100 * best.free_violation:.0f} % of "
                     f"{best.free_rays} rays meeting it (> {100 * cfg.wrong_free:.0f} %)")
    elif best.free_violation > cfg.ok_free:
        unsure.append(f"free-space violations {100 * best.free_violation:.0f} % of {best.free_rays} rays "
                      f"(> {100 * cfg.ok_free:.0f} %)")
    if choice is None and margin is not None and margin < cfg.min_margin:
        unsure.append(f"hypothesis {runner.index} is nearly as likely: margin {margin:.3f} < {cfg.min_margin} "
                      f"(scores {best.score:.3f} vs {runner.score:.3f})")
    outcome = "wrong" if wrong else "uncertain" if unsure else "ok"
    return outcome, best.index, None if runner is None else runner.index, margin, tuple(wrong + unsure)


def verify(views: Sequence[View], meshes: Sequence[RenderMesh], hyps: Sequence[Sim3], cloud_scores: Sequence[float],
           rays: FreeSpaceRays, cfg: VerifyConfig, inlier_m: float, choice: int | None = None) -> Verification:
    """Score every hypothesis by the images and decide (see the module doc)."""
    if choice is not None and not 0 <= choice < len(hyps):
        raise InputError(f"--hypothesis {choice}: the alignment has hypotheses 0..{len(hyps) - 1}; see "
                         "verify/verify.json or verify/hypotheses.png")
    t0 = time.perf_counter()
    ev, hyps = score_hypotheses(views, meshes, hyps, cloud_scores, rays, cfg, inlier_m)
    outcome, chosen, runner, margin, reasons = decide(ev, hyps, cfg, choice)
    log.info("verification: %s, hypothesis %d (edge %.3f, free-space %.3f), margin %s", outcome, chosen,
             ev[chosen].edge, ev[chosen].free_violation, "n/a" if margin is None else f"{margin:.3f}")
    return Verification(outcome, chosen, hyps[chosen], margin, runner, tuple(ev), reasons,
                        "" if outcome == "ok" else FIX, tuple(v.name for v in views), choice is not None,
                        {"verify": time.perf_counter() - t0}, tuple(hyps))
