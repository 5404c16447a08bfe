"""``run``: align a CAD structure to an SfM point cloud on disk and write ``align.json`` (+ ``align.png``).

Output layout (``OUT``)::

    OUT/align.json            cad_from_sfm (4x4 and s/R/t), metrics, every gate, seconds, ICP history,
                              the resolved config, inputs and the package version
    OUT/align.png             top and side views of the aligned points over the CAD, coloured by residual
    OUT/cadalign_stage.json   the resolved config and version (the stage manifest)

``align.json`` is written last, so its presence marks a finished run. A run whose alignment fails a gate
raises :class:`~cadalign.align.gates.AlignmentGateError` and writes nothing (a stale manifest it created
is removed, so the next attempt may use another config in the same directory).
"""

from __future__ import annotations

import hashlib
import logging
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from cadalign._version import __version__
from cadalign.align.config import AlignConfig
from cadalign.align.core import align
from cadalign.align.figure import render_png
from cadalign.align.gates import gate_distances
from cadalign.align.picks import Picks, read_picks
from cadalign.align.result import AlignResult
from cadalign.align.surface import CadPart, sample_surface
from cadalign.cad import CadModel, load_cad
from cadalign.config import to_dict
from cadalign.errors import CadalignError, InputError
from cadalign.geometry import sim3_from_matrix
from cadalign.io import MANIFEST_NAME, prepare_stage_dir, read_json, write_bytes, write_json
from cadalign.types import Rigid3, Sim3

log = logging.getLogger(__name__)

STAGE = "align"
ALIGN_JSON = "align.json"
ALIGN_PNG = "align.png"
POINT_CLOUD_SUFFIXES = (".ply", ".pcd", ".xyz", ".xyzn", ".xyzrgb", ".pts")

CadInput = CadPart | str | Path | tuple[CadModel | str | Path, Rigid3]
"""A CAD part for :func:`run`: a model or mesh file (in world metres), or either with its ``world_from_part``."""


def load_points(source: str | Path | np.ndarray) -> np.ndarray:
    """SfM points (N, 3) from an array, a ``.npy`` file, a point-cloud file (PLY, PCD, XYZ) or a COLMAP
    sparse model (a folder with ``points3D.bin``/``.txt``, or that file).

    Raises:
        InputError: missing or unreadable file, or no points in it.
    """
    return load_cloud(source)[0]


def load_cloud(source: str | Path | np.ndarray, views: np.ndarray | None = None,
               ) -> tuple[np.ndarray, np.ndarray | None]:
    """:func:`load_points` and the number of images each point is seen in: ``views`` when given (for an array of
    points), a COLMAP model's own, else None."""
    if isinstance(source, np.ndarray):
        return source, views
    path = Path(source)
    if not path.exists():
        raise InputError(f"SfM points not found: {path}")
    if path.is_dir() or path.stem == "points3D":
        pts, model_views = _colmap_points(path if path.is_dir() else path.parent)
        views = model_views if views is None else views
    elif path.suffix.lower() == ".npy":
        pts = np.load(path, allow_pickle=False)
    elif path.suffix.lower() in POINT_CLOUD_SUFFIXES:
        import open3d as o3d  # lazy: heavy dependency (open3d)

        pts = np.asarray(o3d.io.read_point_cloud(str(path)).points)
    else:
        raise InputError(f"{path}: unsupported point file; use .npy, {', '.join(POINT_CLOUD_SUFFIXES)} or a COLMAP "
                         "sparse model folder")
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        raise InputError(f"{path}: expected N x 3 points, got an array of shape {pts.shape}")
    return pts, views


def _colmap_points(folder: Path) -> tuple[np.ndarray, np.ndarray]:
    import pycolmap  # lazy: heavy dependency (pycolmap)

    if not ((folder / "points3D.bin").is_file() or (folder / "points3D.txt").is_file()):
        raise InputError(f"{folder} is not a COLMAP sparse model (no points3D.bin or points3D.txt)")
    try:
        rec = pycolmap.Reconstruction(str(folder))
    except Exception as exc:  # pycolmap raises bare RuntimeErrors for corrupt models
        raise InputError(f"{folder}: could not read the COLMAP model ({exc}); re-run SfM") from exc
    points = list(rec.points3D.values())
    return (np.array([p.xyz for p in points], dtype=np.float64).reshape(-1, 3),
            np.array([p.track.length() for p in points], dtype=np.int64))


def load_cad_parts(cad: Sequence[CadInput]) -> list[CadPart]:
    """Models (loading files with :func:`~cadalign.cad.load_cad`, unit detected) paired with their poses."""
    parts: list[CadPart] = []
    for item in cad:
        model, pose = item if isinstance(item, tuple) else (item, None)
        if isinstance(model, (str, Path)):
            model = load_cad(model)
        parts.append(model if pose is None else (model, pose))
    return parts


def read_sim3(path: str | Path) -> Sim3:
    """``cad_from_sfm`` from an ``align.json`` or from a JSON object ``{"matrix": 4x4}`` (a prior pose)."""
    data = read_json(Path(path))
    node = data.get("cad_from_sfm", data) if isinstance(data, dict) else None
    if not isinstance(node, dict) or "matrix" not in node:
        raise InputError(f"{path}: expected an align.json or a JSON object with a 4x4 'matrix' (cad_from_sfm)")
    try:
        return sim3_from_matrix(np.asarray(node["matrix"], dtype=np.float64))
    except (InputError, ValueError, TypeError) as exc:
        raise InputError(f"{path}: 'matrix' is not a 4x4 similarity: {exc}") from exc


def _digest(*arrays: np.ndarray) -> str:
    h = hashlib.sha256()
    for a in arrays:
        h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
    return h.hexdigest()[:16]


def _inputs_record(points: np.ndarray, parts: list[CadPart], picks: Picks | None, prior: Sim3 | None) -> dict:
    cad = []
    for p in parts:
        model, pose = p if isinstance(p, tuple) else (p, Rigid3())
        cad.append({"name": model.name, "source": str(model.source) if model.source else None, "unit": model.unit,
                    "mesh": _digest(model.vertices_m, model.faces), "world_from_part": pose.matrix()})
    return {
        "points_sfm": {"n": len(points), "digest": _digest(points)},
        "cad": cad,
        "picks": None if picks is None else {"source": picks.source, "names": list(picks.names),
                                             "digest": _digest(picks.sfm, picks.cad_m)},
        "prior": None if prior is None else prior.matrix(),
    }


def sim3_record(T: Sim3) -> dict[str, Any]:
    """A Sim3 as JSON: the 4x4 matrix and its parts, with the convention spelled out."""
    return {"matrix": T.matrix(), "s": T.s, "R": T.R, "t": T.t, "convention": "x_cad_m = s * R @ x_sfm + t"}


def result_record(result: AlignResult, cfg: AlignConfig, inputs: dict, sample_s: float = 0.0) -> dict[str, Any]:
    """The content of ``align.json`` (``sample_s``: CAD sampling time when done outside :func:`align`)."""
    return {
        "version": __version__,
        "cad_from_sfm": sim3_record(result.cad_from_sfm),
        "sfm_from_cad": sim3_record(result.cad_from_sfm.inverse()),
        "coarse": {"method": result.coarse_from, **sim3_record(result.coarse),
                   "global_scores": result.global_scores},
        "metrics": to_dict(result.metrics),
        "hypotheses": [{"score": sc, **sim3_record(T)} for T, sc in result.hypotheses],
        "gates": [{k: v for k, v in to_dict(g).items() if k != "hint"} for g in result.gates],
        "seconds": {**result.seconds, "sample": result.seconds.get("sample", 0.0) + sample_s},
        "history": [to_dict(h) for h in result.history],
        "config": to_dict(cfg),
        "inputs": inputs,
    }


def _clear_outputs(out_dir: Path) -> None:
    for name in (ALIGN_JSON, ALIGN_PNG):
        (out_dir / name).unlink(missing_ok=True)


def run(
    cfg: AlignConfig,
    points_sfm: str | Path | np.ndarray,
    cad: Sequence[CadInput],
    out_dir: str | Path,
    *,
    picks: str | Path | Picks | None = None,
    prior: Sim3 | str | Path | None = None,
    overwrite: bool = False,
    views: np.ndarray | None = None,
) -> Path:
    """Align, gate and write ``OUT/align.json`` (+ ``align.png``); returns the path of ``align.json``.

    A finished run with the same config and inputs is reused; another config in the same directory is
    refused unless ``overwrite``.

    Args:
        cfg: the resolved config (see :data:`~cadalign.align.config.PRESETS`).
        points_sfm: SfM points: array, ``.npy``, PLY/PCD/XYZ or a COLMAP sparse model (see :func:`load_points`).
        cad: the structure's parts (see :data:`CadInput`).
        out_dir: output folder.
        picks: point correspondences (a picks JSON file or :class:`Picks`).
        prior: a prior ``cad_from_sfm`` (a Sim3, or a JSON file read by :func:`read_sim3`).
        overwrite: replace results made with another config.
        views: for an array of points, the number of images each is seen in (a COLMAP model gives its own).

    Raises:
        AlignmentGateError: the alignment failed a quality gate (nothing is written).
        InputError, DegenerateGeometryError, ConfigError: unusable inputs or directory.
    """
    out_dir = Path(out_dir)
    points, views = load_cloud(points_sfm, views)
    parts = load_cad_parts(cad)
    picks_obj = read_picks(picks) if isinstance(picks, (str, Path)) else picks
    prior_obj = read_sim3(prior) if isinstance(prior, (str, Path)) else prior
    inputs = _inputs_record(points, parts, picks_obj, prior_obj)
    record = {"align": to_dict(cfg), "inputs": inputs}
    if overwrite:
        _clear_outputs(out_dir)
    out_json = out_dir / ALIGN_JSON
    if prepare_stage_dir(out_dir, STAGE, record, overwrite=overwrite) and out_json.is_file():
        log.info("alignment in %s is complete; reusing it", out_dir)
        return out_json
    context = str(points_sfm) if not isinstance(points_sfm, np.ndarray) else f"{len(points)} SfM points"
    t0 = time.perf_counter()
    surface = sample_surface(parts, cfg.cad_samples, cfg.seed)
    sample_s = time.perf_counter() - t0
    try:
        result = align(points, surface, cfg, picks=picks_obj, prior=prior_obj, context=context, views=views)
    except CadalignError:
        (out_dir / MANIFEST_NAME).unlink(missing_ok=True)  # nothing was written: free the directory
        raise
    if cfg.figure:
        inlier_m = gate_distances(surface, cfg.gates)[0]
        png = render_png(points, surface, result, inlier_dist_m=inlier_m, title=context, seed=cfg.seed)
        write_bytes(out_dir / ALIGN_PNG, png)
    write_json(out_json, result_record(result, cfg, inputs, sample_s))
    log.info("wrote %s (scale %.6g m per SfM unit, fitness %.3f, inlier RMSE %.2f cm)", out_json, result.scale,
             result.fitness, result.inlier_rmse_m * 100)
    return out_json
