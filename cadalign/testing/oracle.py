"""The ground-truth oracle detector, for tests and demos only (``cadalign infer --oracle-gt``).

:class:`OracleDetector` returns the ground-truth instances of a BOP scene (visible masks, exact boxes) with their poses
perturbed by seeded noise, so refinement and temporal fusion can be exercised and measured without a trained
network. It follows the :class:`~cadalign.infer.detect.Detector` protocol; its results are labelled ``oracle``
everywhere.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cadalign.config import bounded
from cadalign.formats.bop import BopScene, mask_bbox
from cadalign.formats.class_map import load_class_map
from cadalign.geometry.rotations import axis_angle_to_matrix
from cadalign.infer.detect import frame_ids
from cadalign.types import Detection

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class OracleDetection(Detection):
    """A :class:`~cadalign.types.Detection` made from ground truth, remembering which instance it came from."""

    gt_idx: int | None = None
    """Oracle only: the ground-truth instance index in the frame (for measurements)."""


@dataclass(frozen=True)
class OracleConfig:
    noise_t_m: float = bounded(0.03, ge=0)
    """RMS of the translation noise added to the true pose (m; isotropic Gaussian)."""
    noise_r_deg: float = bounded(3.0, ge=0)
    """RMS of the rotation noise (deg; rotation vector isotropic Gaussian)."""
    min_visib_fract: float = bounded(0.1, ge=0, le=1)
    """Instances less visible than this are not reported (BOP's default)."""
    min_pixels: int = bounded(1, ge=1)
    """Instances with fewer visible pixels are not reported."""
    give_obj_id: bool = False
    """Report the true model id (a network reports only the class; off = the pipeline must identify it)."""
    seed: int = 0
    """Seed of the pose noise (per frame: seed + frame id)."""


class OracleDetector:
    """Ground-truth detections of a BOP scene with noisy poses (tests and demos only; see module doc)."""

    name = "oracle"

    def __init__(self, scene_dir: Path, cfg: OracleConfig) -> None:
        self.scene = BopScene(scene_dir)
        self.cfg = cfg
        self.classes = load_class_map(scene_dir)
        self.im_id_of = frame_ids(scene_dir)
        self.current: str | None = None

    def for_frame(self, name: str) -> OracleDetector:
        """Select the frame (by name) that the next :meth:`detect` call reports."""
        self.current = name
        return self

    def detect(self, image: np.ndarray, K: np.ndarray) -> list[Detection]:
        im_id = self.im_id_of.get(self.current or "")
        if im_id is None:
            log.debug("oracle: frame %s is not in the ground truth; no detections", self.current)
            return []
        cfg = self.cfg
        frame = self.scene.frame(im_id)
        rng = np.random.default_rng(cfg.seed + im_id)
        out = []
        for g, inst in enumerate(frame.instances):
            info = frame.info[g] if g < len(frame.info) else {}
            if info.get("visib_fract", 1.0) < cfg.min_visib_fract:
                continue
            m = self.scene.mask(im_id, g, visible=True)
            if m.sum() < cfg.min_pixels:
                continue
            x, y, w, h = mask_bbox(m)
            dR = axis_angle_to_matrix(rng.normal(scale=np.radians(cfg.noise_r_deg) / np.sqrt(3), size=3))
            dt = rng.normal(scale=cfg.noise_t_m / np.sqrt(3), size=3)
            T = inst.T_cam_from_obj
            box = np.array([x, y, x + w, y + h], float)
            out.append(OracleDetection(box, self.classes.class_of_obj[inst.obj_id], 1.0, m, dR @ T.R, T.t + dt,
                                       inst.obj_id if cfg.give_obj_id else None, g))
        return out
