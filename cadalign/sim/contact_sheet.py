"""A contact sheet PNG: the clean render, each declared effect alone, and all effects together."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from cadalign.io import write_image
from cadalign.sim.effects_chain import build_chain, run_chain
from cadalign.sim.render import GroundTruthCaster, RGBRenderer
from cadalign.sim.scene import SimScene
from cadalign.sim.trajectory import pose_at

TILE_W = 320


def _label(img: np.ndarray, text: str) -> np.ndarray:
    out = img.copy()
    cv2.rectangle(out, (0, 0), (out.shape[1], 22), (0, 0, 0), -1)
    cv2.putText(out, text, (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def contact_sheet_tiles(scene: SimScene, frame: int | None = None) -> list[tuple[str, np.ndarray]]:
    """(label, uint8 RGB tile) for clean, each effect alone, and all effects, on one frame."""

    spec = scene.spec
    k = spec.trajectory.frames // 2 if frame is None else frame
    T = pose_at(spec.trajectory, k / spec.trajectory.fps, spec.seed)
    renderer = RGBRenderer(scene)
    try:
        clean = renderer.render(T)
    finally:
        renderer.close()
    gt = GroundTruthCaster(scene).cast(T, with_full_masks=False)
    chain = build_chain(spec)
    variants = [("clean", [])] + [(name, [(name, p)]) for name, p in chain]
    if len(chain) > 1:
        variants.append(("all effects", chain))
    tiles = []
    h = round(TILE_W * scene.camera.height / scene.camera.width)
    for label, sub in variants:
        rgb, _ = run_chain(sub, clean, gt, spec, k, T, scene.camera)
        img = (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
        tiles.append((label, _label(cv2.resize(img, (TILE_W, h), interpolation=cv2.INTER_AREA), label)))
    return tiles


def write_contact_sheet(scene: SimScene, path: Path, columns: int = 4) -> Path:
    tiles = [t for _, t in contact_sheet_tiles(scene)]
    blank = np.zeros_like(tiles[0])
    while len(tiles) % columns:
        tiles.append(blank)
    rows = [np.concatenate(tiles[i:i + columns], axis=1) for i in range(0, len(tiles), columns)]
    return write_image(path, np.concatenate(rows, axis=0))
