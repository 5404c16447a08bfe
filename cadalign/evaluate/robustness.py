"""Robustness under low visibility (``cadalign bench robustness``): turbidity, marine snow and light level.

The underwater counterpart of the fog / rain / snow / low-light tests of driving benchmarks. Each
condition is the benchmark scene (default scene at 1 frame/s, every water effect on) with one factor made
worse, simulated as a short clip:

* ``turbidity``: the Jerlov water type (clearer ocean I ... coastal 7C);
* ``marine_snow``: particles per cubic metre (the default scene has 20);
* ``light``: the light level, a factor on the ambient light and on both lamps (1 = the default scene).

Per condition: SfM (``fast`` preset, 1 thread) registration rate and rotation errors against the exact
cameras (absolute after the Sim(3) fit, and the gauge-free error between consecutive frames); the image
contrast the simulator's ground truth lets us measure exactly (:func:`contrast_metrics`, structure vs
background from the true class map); and, given trained networks (``models/seg``,
``models/depth``, ``models/pose``: ``cadalign train`` run folders), their mIoU / delta1 on the condition's
frames and the pose errors of ``cadalign infer`` with that detector.

Writes ``robustness.json`` (one row per condition, saved after each, reused on re-run) and one
``robustness_<effect>.png`` per effect (metrics against severity, the unchanged scene as severity 0).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from cadalign.bench.data import bench_scene, simulate_clip, size_spec, write_scene_variant
from cadalign.bench.framework import json_safe, num
from cadalign.bench.sweeps.train import score_net
from cadalign.config import resolve, to_dict
from cadalign.errors import ConfigError
from cadalign.evaluate.sfm import evaluate
from cadalign.infer import detect as det
from cadalign.infer.config import PRESETS as INFER_PRESETS
from cadalign.infer.config import InferConfig
from cadalign.infer.run import calibration_from_scene
from cadalign.infer.run import run as infer_run
from cadalign.io import fingerprint, read_image, read_json, write_json
from cadalign.sfm import PRESETS, SfMConfig, run
from cadalign.sim.spec import load_scene
from cadalign.sim.structure import load_structure
from cadalign.types import Progress

log = logging.getLogger(__name__)
ROBUSTNESS_JSON = "robustness.json"
BASELINE = {"turbidity": "IB", "marine_snow": 20.0, "light": 1.0}
"""The unchanged default scene's value of each factor (severity 0)."""
SEVERITIES: dict[str, tuple[Any, ...]] = {
    "turbidity": ("II", "III", "3C", "7C"),
    "marine_snow": (100.0, 400.0, 1600.0, 4000.0),
    "light": (0.4, 0.15, 0.05, 0.02),
}
"""Values from mild to severe; tiny/small runs take the first three, full all four."""


def condition_scene(base: Path, effect: str, value: Any) -> dict[str, Any]:
    """The changes to the scene ``base`` that set ``effect`` to ``value`` (see the module doc), for
    :func:`cadalign.bench.data.write_scene_variant`; only that factor moves.

    Raises:
        ConfigError: an unknown effect, or a base scene whose factor is not the baseline's (``BASELINE``).
    """

    spec = load_scene(base)
    if effect == "turbidity":
        if spec.water.jerlov != BASELINE["turbidity"]:
            raise ConfigError(f"{base}: the robustness baseline is Jerlov {BASELINE['turbidity']}, the scene has "
                              f"{spec.water.jerlov!r}")
        return {"water": {"jerlov": str(value)}}
    if effect == "marine_snow":
        return {"effect_params": {"marine_snow": {"density_per_m3": float(value)}}}
    if effect == "light":
        if not spec.lights:
            raise ConfigError(f"{base}: the light condition scales the scene's lamps, and it has none")
        return {"ambient": spec.ambient * float(value),  # lists replace the base's: every lamp in full
                "lights": [{**to_dict(lamp), "intensity": lamp.intensity * float(value)} for lamp in spec.lights]}
    raise ConfigError(f"unknown robustness effect {effect!r}; allowed: {', '.join(SEVERITIES)}")


def luminance(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 RGB -> (H, W) float64 Rec. 709 luma in [0, 1]."""
    return np.asarray(rgb, dtype=np.float64)[..., :3] @ np.array([0.2126, 0.7152, 0.0722]) / 255.0


def contrast_metrics(rgb: np.ndarray, class_id: np.ndarray) -> dict[str, float]:
    """Contrast of one frame, using the true class map (0 = background: seabed and open water).

    * ``contrast``: Michelson contrast of the structure against the background,
      ``|mean(L_fg) - mean(L_bg)| / (mean(L_fg) + mean(L_bg))`` (0 when either side is empty or both black);
    * ``rms_contrast_fg``: RMS contrast inside the structure, ``std(L_fg) / mean(L_fg)`` (texture and edges
      that features and networks can use; 0 without structure pixels).
    """
    L = luminance(rgb)
    fg = np.asarray(class_id) > 0
    if L.shape != fg.shape:
        raise ValueError(f"image {L.shape} and class map {fg.shape} differ in size")
    if not fg.any() or fg.all():
        return {"contrast": 0.0, "rms_contrast_fg": 0.0 if not fg.any() else float(L.std() / max(L.mean(), 1e-9))}
    mf, mb = float(L[fg].mean()), float(L[~fg].mean())
    michelson = abs(mf - mb) / (mf + mb) if mf + mb > 0 else 0.0
    return {"contrast": michelson, "rms_contrast_fg": float(L[fg].std() / mf) if mf > 0 else 0.0}


def clip_contrast(sim_dir: Path) -> dict[str, float]:
    """Mean :func:`contrast_metrics` over the frames of a simulation folder."""
    scene = Path(sim_dir) / "gt" / "sim" / "000000"
    rows = []
    for f in sorted((Path(sim_dir) / "frames").glob("*.png")):
        rows.append(contrast_metrics(read_image(f), read_image(scene / "class" / f.name, unchanged=True)))
    if not rows:
        raise ConfigError(f"{sim_dir}/frames holds no frame")
    return {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}


def _sfm_scores(sim: Path, work: Path, seed: int) -> dict[str, Any]:
    cfg = resolve(SfMConfig, PRESETS, "fast", overrides={"num_threads": 1, "seed": seed})
    t0 = time.perf_counter()
    try:
        run(cfg, sim / "frames", work, overwrite=True)
        g = evaluate(work, sim)
    except Exception as exc:  # no model at all is the worst registration, not a crash of the sweep
        log.warning("robustness: SfM failed on %s: %s", sim, exc)
        return {"registration_rate": 0.0, "rot_err_deg": float("nan"), "rel_rot_err_deg": float("nan"),
                "sfm_s": time.perf_counter() - t0, "sfm_error": f"{type(exc).__name__}: {exc}"[:300]}
    return {"registration_rate": g["registration_rate"], "rot_err_deg": g["rot_err_deg_mean"],
            "rel_rot_err_deg": g["rel_rot_err_deg_mean"], "centre_rmse_rel": g["centre_rmse_rel"],
            "sfm_s": time.perf_counter() - t0}


def conditions(size: str) -> list[tuple[str, str, Any]]:
    """``(effect, severity name, value)`` of every condition of ``size``, the baseline first."""
    n = 4 if size_spec(size).level >= 2 else 3
    out = [("baseline", "0", None)]
    for effect, values in SEVERITIES.items():
        out += [(effect, str(i + 1), v) for i, v in enumerate(values[:n])]
    return out


def run_robustness(out_dir: Path, *, size: str = "small", seed: int = 0, models: Path | None = None,
                   with_sfm: bool = True, resolution: tuple[int, int] | None = None, frames: int | None = None,
                   progress: Progress | None = None) -> dict[str, Any]:
    """Simulate and score every condition of ``size`` into ``out_dir`` (see the module doc); returns the dict.

    ``resolution`` / ``frames`` override the size's SfM clip (default: ``size_spec(size).sfm_*``)."""
    out_dir = Path(out_dir)
    spec = size_spec(size)
    res, n_frames = tuple(resolution or spec.sfm_resolution), int(frames or spec.sfm_frames)
    path = out_dir / ROBUSTNESS_JSON
    data_dir = out_dir / "data" / f"robustness_{res[0]}x{res[1]}_{n_frames}_s{seed}"
    config = {"size": size, "seed": seed, "sfm": with_sfm, "models": str(models) if models else None,
              "resolution": list(res), "frames": n_frames}
    old = read_json(path) if path.is_file() else {}
    done = {r["key"]: r for r in old.get("rows", [])} if old.get("config") == config else {}
    base = bench_scene(out_dir / "data")
    rows = []
    conds = conditions(size)
    for effect, sev, value in progress(conds, "robustness", len(conds)) if progress else conds:
        key = fingerprint([effect, sev, value, config])
        if key not in done:
            name = f"{effect}_{sev}" if value is None else f"{effect}_{value}"
            changes = {} if effect == "baseline" else condition_scene(base, effect, value)
            scene = write_scene_variant(data_dir / f"{name}.yaml", base, changes)
            sim = simulate_clip(scene, data_dir / name, res, n_frames, seed)
            metrics: dict[str, Any] = clip_contrast(sim)
            if with_sfm:
                metrics.update(_sfm_scores(sim, data_dir / f"{name}_sfm", seed))
            note = metrics.pop("sfm_error", None)
            metrics.update(_model_scores(sim, scene, models))
            done[key] = {"key": key, "effect": effect, "severity": sev, "value": value, "metrics": metrics,
                         "note": note}
        rows.append(done[key])
        _save(path, config, rows, out_dir)
    result = _save(path, config, rows, out_dir, plots=True)
    return result


def _model_scores(sim: Path, scene_toml: Path, models: Path | None) -> dict[str, float]:
    """mIoU / delta1 / pose errors of the networks in ``models/{seg,depth,pose}`` (those present) on ``sim``."""
    if models is None:
        return {}

    scene = sim / "gt" / "sim" / "000000"
    out: dict[str, float] = {}
    for task, key in (("seg", "miou"), ("depth", "delta1")):
        if (Path(models) / task).exists():
            out[key] = score_net(task, scene, Path(models) / task, split="all")[key]
    if (Path(models) / "pose").exists():
        out.update(pose_scores(sim, scene_toml, Path(models) / "pose"))
    return out


def pose_scores(sim: Path, scene_toml: Path, run_dir: Path) -> dict[str, float]:
    """Run ``cadalign infer`` (fast preset, detector = the pose network in ``run_dir``, the clip's exact depth
    for ICP) on a simulation folder and return the fused poses' mean errors and ADD(-S) < 0.1 d recall."""
    from cadalign.models.maskrcnn.detector import load_pose_model  # lazy: pulls torch

    scene = sim / "gt" / "sim" / "000000"
    cfg = resolve(InferConfig, INFER_PRESETS, "fast", overrides={"overlay": False})
    structure = load_structure(scene_toml)
    net, meta = load_pose_model(run_dir, "cpu")
    detector = det.TorchDetector(net, cfg.detector_score_thresh, "cpu", cfg.tiles, cfg.nms_iou)
    out = sim.parent / f"{sim.name}_pose"
    infer_run(cfg, sim / "frames", detector, structure.models, tuple(meta.get("classes", structure.class_names)), out,
        calib=calibration_from_scene(scene), detector_info={"kind": "network", "run": str(run_dir)},
        depth_scene=scene, gt_scene=scene, overwrite=True)
    ov = read_json(out / "eval.json")["fused"]["overall"]
    return {"pose_t_err_m": ov["t_err_m"].get("mean"), "pose_r_err_deg": ov["r_err_deg"].get("mean"),
            "pose_add_s_01d": ov.get("add_s_01d")}


def _save(path: Path, config: dict, rows: list[dict], out_dir: Path, plots: bool = False) -> dict[str, Any]:
    result = {"config": config, "rows": rows, "baseline": BASELINE,
              "description": ("Each condition makes one factor of the default scene worse (turbidity: Jerlov type; "
                              "marine snow: particles per m^3; light: factor on ambient and lamps); "
                              f"{config['frames']} frames at {config['resolution'][0]}x{config['resolution'][1]}. "
                              "SfM: fast preset, 1 thread, vs the exact cameras (a failed SfM counts as 0 "
                              "registered). Contrast: Michelson contrast of structure vs background from the "
                              "true class map.")}
    if plots:
        result["plots"] = plot_robustness(result, out_dir)
    write_json(path, json_safe(result))
    return result


def plot_robustness(result: dict[str, Any], out_dir: Path) -> dict[str, str]:
    """One PNG per effect: each metric against severity (0 = the unchanged scene); returns effect -> file name."""
    # the object API draws without pyplot's backend: matplotlib.use("Agg") here turned a notebook's inline plots off
    from matplotlib.figure import Figure  # lazy: heavy dependency (matplotlib)

    rows = result["rows"]
    base = next((r for r in rows if r["effect"] == "baseline"), None)
    keys = [k for k in ("registration_rate", "rel_rot_err_deg", "rot_err_deg", "contrast", "miou", "delta1",
                        "pose_r_err_deg", "pose_add_s_01d")
            if any(k in r["metrics"] for r in rows)]
    files = {}
    for effect in SEVERITIES:
        sel = ([base] if base else []) + [r for r in rows if r["effect"] == effect]
        if len(sel) < 2:
            continue
        fig = Figure(figsize=(3.2 * len(keys), 3.0))
        axes = fig.subplots(1, len(keys), squeeze=False)
        x = [int(r["severity"]) for r in sel]
        labels = [str(BASELINE[effect]) if r["effect"] == "baseline" else str(r["value"]) for r in sel]
        for ax, k in zip(axes[0], keys, strict=True):
            ax.plot(x, [num(r["metrics"].get(k)) for r in sel], "o-")
            ax.set_xticks(x, labels, fontsize=7)
            ax.set_title(k, fontsize=9)
            ax.grid(alpha=0.3)
        fig.suptitle(f"{effect}: metrics vs severity (left = the default scene)", fontsize=10)
        fig.tight_layout()
        name = f"robustness_{effect}.png"
        fig.savefig(Path(out_dir) / name, dpi=100)
        files[effect] = name
    return files
