"""How many refinement iterations buy how much accuracy, and at what cost (ms), on a simulated BOP scene.

The starting poses are the oracle's (true pose + seeded noise, see :class:`~cadalign.testing.oracle.OracleDetector`)
with the true visible masks, so the sweep isolates the refinement itself from the detector's mask quality.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cadalign.cad.model import CadModel
from cadalign.formats.bop import BopScene
from cadalign.infer.config import RefineConfig
from cadalign.infer.detect import frame_ids
from cadalign.infer.model_geom import ModelGeometry
from cadalign.infer.refine import icp_points, refine_depth_icp, refine_silhouette
from cadalign.metrics.pose import add, rotation_error_deg, translation_error_m
from cadalign.testing.oracle import OracleConfig, OracleDetector
from cadalign.types import Rigid3


@dataclass(frozen=True)
class SweepRow:
    method: str
    max_iters: int
    n: int
    mean_iters: float
    t_err_m: float
    r_err_deg: float
    add_m: float
    ms: float
    n_eligible: int
    """Instances the method runs on (mask >= min_mask_px / enough depth points); the others keep their pose."""
    t_err_eligible_m: float
    r_err_eligible_deg: float

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def refine_sweep(scene_dir: Path, models: dict[int, CadModel], iters: tuple[int, ...] = (0, 1, 2, 3, 5, 10, 20),
                 oracle: OracleConfig | None = None, cfg: RefineConfig | None = None, max_frames: int = 16,
                 classes: tuple[str, ...] = ("valve", "hot_stab"), min_visib: float = 0.5) -> list[SweepRow]:
    """Mean errors and time of silhouette and depth refinement for each iteration budget in ``iters``."""
    cfg = cfg or RefineConfig()
    det = OracleDetector(scene_dir, oracle or OracleConfig())
    scene = BopScene(scene_dir)
    ids = frame_ids(scene_dir)
    cases = []
    for name in sorted(ids, key=ids.get)[:max_frames]:
        frame = scene.frame(ids[name])
        for d in det.for_frame(name).detect(None, None):
            inst, info = frame.instances[d.gt_idx], frame.info[d.gt_idx]
            if models[inst.obj_id].class_name in classes and info.get("visib_fract", 1.0) >= min_visib:
                cases.append((frame.camera.K, scene.depth_m(ids[name]), d, inst.obj_id, inst.T_cam_from_obj))
    geoms = {k: ModelGeometry.from_cad(m) for k, m in models.items() if m.class_name in classes}
    rows = []
    rng = np.random.default_rng(cfg.seed)
    runs_on = {
        "silhouette": [d.mask.sum() >= cfg.min_mask_px for _, _, d, _, _ in cases],
        "depth": [len(icp_points(depth, d.mask, K, cfg, rng)) >= cfg.min_depth_points for K, depth, d, _, _ in cases],
    }
    runs_on["both"] = [a or b for a, b in zip(runs_on["silhouette"], runs_on["depth"], strict=True)]
    for method in ("silhouette", "depth", "both"):
        for n in iters:
            errs, its, ms = [], [], []
            for K, depth, d, oid, T_gt in cases:
                T0 = Rigid3(d.R_cam_from_obj, d.t_cam_from_obj_m)
                g = geoms[oid]
                t0 = time.perf_counter()
                k = 0
                T = T0
                if method in ("silhouette", "both"):
                    T, k, _ = refine_silhouette(g, T, K, d.mask, cfg, iters=n)
                if method in ("depth", "both"):
                    T, k2, _ = refine_depth_icp(g, T, K, depth, d.mask, cfg, iters=n)
                    k += k2
                ms.append(1e3 * (time.perf_counter() - t0))
                its.append(k)
                errs.append((translation_error_m(T.t, T_gt.t), rotation_error_deg(T.R, T_gt.R, models[oid].symmetry),
                             add(T.R, T.t, T_gt.R, T_gt.t, models[oid].vertices_m)))
            e = np.array(errs).reshape(-1, 3)
            sel = np.array(runs_on[method], dtype=bool)
            rows.append(SweepRow(method, n, len(cases), float(np.mean(its)) if its else 0.0,
                                 *(float(v) for v in e.mean(0)), float(np.mean(ms)) if ms else 0.0, int(sel.sum()),
                                 float(e[sel, 0].mean()) if sel.any() else float("nan"),
                                 float(e[sel, 1].mean()) if sel.any() else float("nan")))
    return rows
