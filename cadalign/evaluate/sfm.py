"""SfM accuracy against a simulation's ground truth: poses after a Sim(3) fit, registration, depth.

Metrics (all over the frames registered in both):

- ``Sim(3)``: Umeyama with scale from the estimated camera centres to the true ones
  (``gt_from_sfm``); its scale converts SfM units to metres.
- rotation error: geodesic angle between ``R_cam_from_world_sfm @ R_fit^T`` and the true
  ``R_cam_from_world`` (degrees; mean and max). The fit's rotation comes from the centres alone, so
  on a short, nearly straight path its roll about the path is poorly determined and this error
  grows; the gauge-free *relative* rotation error of consecutive frames (``R_j R_i^T`` estimated vs
  true) does not depend on the fit.
- centre error: distance between the mapped and true centres (metres; RMSE), also relative to the
  *median scene distance*: the median of all valid ground-truth depth pixels (BOP depth PNGs times
  ``depth_scale`` of scene_camera.json) over all frames, i.e. the typical camera-to-surface distance.
- registration rate: registered frames / ground-truth frames.
- ATE / RPE as evo computes them (``evo_ape`` / ``evo_rpe`` with ``--align --correct_scale``, RPE over consecutive
  evaluated frames, ``--delta 1`` frame): ``ate_m`` the RMSE of the centre errors after the Sim(3) fit (in the
  ground truth's metres); ``rpe_m`` / ``rpe_deg`` the RMSE of the translation / rotation angle of
  ``inv(Q_i^-1 Q_j) (P_i^-1 P_j)`` with ``Q`` true and ``P`` the fitted estimated poses (camera-in-world).
  ``trajectory.tum`` (SfM) and the simulation's ``trajectory.tum`` feed evo directly; tests check the match.
- SfM depth: coverage (fraction of pixels with a value) and AbsRel ``mean(|s d - d_gt| / d_gt)`` over
  pixels valid in both, with ``s`` the Sim(3) scale (also its median and the fraction within 5 %:
  points on thin structures land on background pixels of the GT map and dominate the mean).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cadalign.errors import InputError
from cadalign.formats.tum import frame_stamps
from cadalign.geometry import geodesic_angle, umeyama
from cadalign.io import read_image, read_json, write_json
from cadalign.sfm.report import camera_centres, plot_trajectory
from cadalign.types import Sim3

log = logging.getLogger(__name__)
GT_SCENE = Path("gt") / "sim" / "000000"


@dataclass(frozen=True)
class PoseErrors:
    """Pose accuracy of an SfM model after the Sim(3) fit.

    Attributes:
        gt_from_sfm: the fitted similarity (SfM -> ground-truth world, metres).
        names: frames evaluated (registered and in the ground truth), sorted.
        rot_err_deg: (N,) rotation error per frame, degrees.
        centre_err_m: (N,) centre error per frame, metres.
        rel_rot_err_deg: (N-1,) relative rotation error of consecutive evaluated frames, degrees.
        rpe_m: (N-1,) translation of evo's relative pose error of consecutive evaluated frames (after the fit's
            scale), metres.
    """

    gt_from_sfm: Sim3
    names: list[str]
    rot_err_deg: np.ndarray
    centre_err_m: np.ndarray
    rel_rot_err_deg: np.ndarray
    rpe_m: np.ndarray


def pose_errors(est: dict, gt: dict) -> PoseErrors:
    """Compare two cameras.json dicts (estimated in SfM units, ground truth in metres).

    Raises:
        InputError: fewer than three frames in common.
    """
    names_e, C_e, R_e = camera_centres(est)
    names_g, C_g, R_g = camera_centres(gt)
    common = sorted(set(names_e) & set(names_g))
    common = [common[i] for i in np.argsort(frame_stamps(common), kind="stable")]  # evo's (timestamp) order
    if len(common) < 3:
        raise InputError(f"only {len(common)} registered frames have ground truth; need 3 to fit a Sim(3). "
                         "Check that --gt is the simulation the frames came from")
    ie = [names_e.index(n) for n in common]
    ig = [names_g.index(n) for n in common]
    S = umeyama(C_e[ie], C_g[ig], with_scale=True)
    rot = np.degrees(geodesic_angle(R_e[ie] @ S.R.T, R_g[ig]))
    centre = np.linalg.norm(S.apply(C_e[ie]) - C_g[ig], axis=1)
    Re, Rg = R_e[ie], R_g[ig]
    rel = np.degrees(geodesic_angle(Re[1:] @ np.swapaxes(Re[:-1], 1, 2), Rg[1:] @ np.swapaxes(Rg[:-1], 1, 2)))
    return PoseErrors(S, common, rot, centre, rel, _rpe_translation(S, C_e[ie], Re, C_g[ig], Rg))


def _rpe_translation(S: Sim3, C_e: np.ndarray, R_e: np.ndarray, C_g: np.ndarray, R_g: np.ndarray) -> np.ndarray:
    """(N-1,) ``|t|`` of ``inv(Q_i^-1 Q_{i+1}) (P_i^-1 P_{i+1})`` (evo's RPE, translation part) for camera-in-world
    poses ``P`` (estimate mapped by ``S``) and ``Q`` (truth), from centres (N, 3) and R_cam_from_world (N, 3, 3)."""
    def rel(R_wc: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        R_i_T = R_wc[:-1].swapaxes(1, 2)
        return R_i_T @ R_wc[1:], np.einsum("nij,nj->ni", R_i_T, C[1:] - C[:-1])

    Rq, tq = rel(R_g.swapaxes(1, 2), C_g)
    _, tp = rel(S.R @ R_e.swapaxes(1, 2), S.apply(C_e))  # the rotation part is rel_rot_err_deg
    return np.linalg.norm(np.einsum("nji,nj->ni", Rq, tp - tq), axis=1)


def _gt_depths(scene_dir: Path, names: list[str]) -> dict[str, np.ndarray]:
    cams = read_json(scene_dir / "scene_camera.json")
    out = {}
    for name in names:
        stem = Path(name).stem
        path = scene_dir / "depth" / f"{stem}.png"
        entry = cams.get(str(int(stem))) if stem.isdigit() else None
        if entry is None or not path.is_file():
            continue
        out[name] = read_image(path, unchanged=True).astype(np.float64) * float(entry["depth_scale"]) / 1000.0
    return out


def median_scene_distance(depths: dict[str, np.ndarray]) -> float:
    """Median of all valid (> 0) ground-truth depth pixels of all frames, metres."""
    vals = [d[d > 0] for d in depths.values()]
    vals = [v for v in vals if v.size]
    if not vals:
        raise InputError("the ground-truth depth maps have no valid pixel")
    return float(np.median(np.concatenate(vals)))


def depth_errors(sfm_depth_dir: Path, gt_depths: dict[str, np.ndarray], scale: float) -> dict[str, float]:
    """Coverage and AbsRel of the SfM depth maps (scaled by ``scale``) against ground truth."""
    coverage, rel = [], []
    for name, gt in gt_depths.items():
        path = sfm_depth_dir / f"{Path(name).stem}.npy"
        if not path.is_file():
            continue
        d = np.load(path).astype(np.float64) * scale
        if d.shape != gt.shape:
            raise InputError(f"{path} is {d.shape} but the ground truth of {name} is {gt.shape}")
        coverage.append(float(np.mean(d > 0)))
        both = (d > 0) & (gt > 0)
        rel.append(np.abs(d[both] - gt[both]) / gt[both])
    r = np.concatenate(rel) if rel else np.zeros(0)
    return {
        "frames": len(coverage),
        "coverage_mean": float(np.mean(coverage)) if coverage else 0.0,
        "abs_rel": float(r.mean()) if r.size else float("nan"),
        "abs_rel_median": float(np.median(r)) if r.size else float("nan"),
        "within_5pct": float(np.mean(r < 0.05)) if r.size else float("nan"),
        "pixels_compared": int(r.size),
    }


def evaluate(sfm_dir: Path, sim_dir: Path) -> dict:
    """All metrics of an SfM output folder against a simulation folder, as a JSON-ready dict."""
    sfm_dir, sim_dir = Path(sfm_dir), Path(sim_dir)
    scene = sim_dir / GT_SCENE
    if not (scene / "cameras.json").is_file():
        raise InputError(f"{sim_dir} is not a simulation output (no {GT_SCENE / 'cameras.json'}); "
                         "pass the folder written by 'cadalign sim'")
    gt = read_json(scene / "cameras.json")
    est = read_json(sfm_dir / "cameras.json")
    pe = pose_errors(est, gt)
    depths = _gt_depths(scene, sorted(gt["frames"]))
    dist = median_scene_distance(depths)
    rmse = float(np.sqrt(np.mean(pe.centre_err_m**2)))
    result = {
        "gt_dir": str(sim_dir),
        "frames_gt": len(gt["frames"]),
        "registered_with_gt": len(pe.names),
        "registration_rate": len(pe.names) / len(gt["frames"]),
        "sim3_scale_m_per_sfm_unit": pe.gt_from_sfm.s,
        "rot_err_deg_mean": float(pe.rot_err_deg.mean()),
        "rot_err_deg_median": float(np.median(pe.rot_err_deg)),
        "rot_err_deg_max": float(pe.rot_err_deg.max()),
        "rel_rot_err_deg_mean": float(pe.rel_rot_err_deg.mean()),
        "rel_rot_err_deg_max": float(pe.rel_rot_err_deg.max()),
        "centre_rmse_m": rmse,
        "ate_m": rmse,
        "rpe_m": float(np.sqrt(np.mean(pe.rpe_m**2))) if len(pe.rpe_m) else None,
        "rpe_deg": float(np.sqrt(np.mean(pe.rel_rot_err_deg**2))) if len(pe.rel_rot_err_deg) else None,
        "ate_rpe_def": "as evo_ape / evo_rpe --align --correct_scale (RPE: consecutive frames, delta 1), RMSE",
        "centre_err_m_max": float(pe.centre_err_m.max()),
        "median_scene_distance_m": dist,
        "median_scene_distance_def": "median of valid GT depth pixels over all frames",
        "centre_rmse_rel": rmse / dist,
        "sfm_depth": depth_errors(sfm_dir / "depth", depths, pe.gt_from_sfm.s),
        "per_frame": {n: {"rot_err_deg": float(r), "centre_err_m": float(c)}
                      for n, r, c in zip(pe.names, pe.rot_err_deg, pe.centre_err_m, strict=True)},
    }
    _plot_vs_gt(sfm_dir / "trajectory_vs_gt.png", est, gt, pe, result)
    return result


def _plot_vs_gt(path: Path, est: dict, gt: dict, pe: PoseErrors, result: dict) -> None:
    names_e, C_e, _ = camera_centres(est)
    names_g, C_g, _ = camera_centres(gt)
    est_w = pe.gt_from_sfm.apply(C_e[[names_e.index(n) for n in pe.names]])
    true_w = C_g[[names_g.index(n) for n in pe.names]]
    title = (f"SfM vs ground truth, top-down (world x-y): {len(pe.names)}/{result['frames_gt']} frames registered\n"
             f"rotation {result['rot_err_deg_mean']:.3f} deg mean / {result['rot_err_deg_max']:.3f} max, centre RMSE "
             f"{100 * result['centre_rmse_rel']:.2f}% of {result['median_scene_distance_m']:.2f} m")
    errors = {"rotation error [deg]": pe.rot_err_deg, "centre error [% of scene distance]":
              100 * pe.centre_err_m / result["median_scene_distance_m"]}
    plot_trajectory(path, est_w[:, :2], true_w[:, :2], title=title, units="m", errors=errors)


def run(sfm_dir: Path, sim_dir: Path) -> Path:
    """Evaluate ``sfm_dir`` against ``sim_dir``; adds a ``gt`` section to sfm_report.json, writes
    ``trajectory_vs_gt.png``; returns the report path."""
    report_path = Path(sfm_dir) / "sfm_report.json"
    report = read_json(report_path)
    report["gt"] = evaluate(sfm_dir, sim_dir)
    write_json(report_path, report)
    g = report["gt"]
    log.info("SfM vs GT: %d/%d registered, rotation %.3f deg mean (max %.3f), centre RMSE %.2f%% of %.2f m, "
             "depth coverage %.4f AbsRel %.4f", g["registered_with_gt"], g["frames_gt"], g["rot_err_deg_mean"],
             g["rot_err_deg_max"], 100 * g["centre_rmse_rel"], g["median_scene_distance_m"],
             g["sfm_depth"]["coverage_mean"], g["sfm_depth"]["abs_rel"])
    return report_path


__all__ = ["PoseErrors", "depth_errors", "evaluate", "median_scene_distance", "pose_errors", "run"]
