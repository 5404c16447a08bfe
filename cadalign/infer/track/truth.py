"""Tracked part poses against reference camera poses: per-frame errors and their plot (``infer --gt-poses``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cadalign.errors import InputError
from cadalign.geometry.rotations import geodesic_angle
from cadalign.io import read_json, read_jsonl, write_json
from cadalign.sim.structure import Structure
from cadalign.types import Rigid3


def read_frame_poses(path: Path, what: str = "reference poses") -> dict[str, Rigid3]:
    """Camera poses by frame name from JSON ``{"frames": {frame name: T_cam_from_world 4x4}}`` (metres, the
    scene file's world frame): a real capture's reference poses (e.g. from a fiducial board), or rough
    navigation poses per frame (``infer --nav``)."""
    data = read_json(path)
    try:
        out = {str(k): Rigid3.from_matrix(np.asarray(v, dtype=np.float64)) for k, v in data["frames"].items()}
    except (KeyError, ValueError, TypeError, AttributeError) as exc:
        raise InputError(f"{path}: not {what} ({exc}); write {{\"frames\": {{\"<frame name>\": 4x4 "
                         "T_cam_from_world, metres}}}}") from exc
    if not out:
        raise InputError(f"{path}: no frames in it; write {{\"frames\": {{\"<frame name>\": 4x4 T_cam_from_world, "
                         "metres}}}}")
    return out


ACCURATE = (10.0, 0.5)
"""(mm, deg): a tracked frame whose every part is within both is counted accurate (issue 43's per-class mean)."""
WRONG = (100.0, 5.0)
"""(mm, deg): a tracked frame with a part off by more than either is counted wrong (a pose no user should get)."""


def truth_report(out_dir: Path, structure: Structure, truth: dict[str, Rigid3]) -> dict:
    """Per-frame errors of each part's tracked pose against reference camera poses (``truth_errors.json``) and
    their plot (``truth_errors.png``): the part's centre in the camera (mm) and its rotation (deg), and each
    tracked frame's worst part; a lost frame has none. The summary counts the tracked frames that are
    :data:`ACCURATE` and :data:`WRONG`."""

    rows = []
    for d in read_jsonl(Path(out_dir) / "track.jsonl"):
        T_ref = truth.get(d["frame_name"])
        if T_ref is None:
            continue
        row: dict = {"frame": d["frame"], "frame_name": d["frame_name"], "state": d["state"], "parts": {}}
        if d["T_cam_from_world"] is not None:
            T = Rigid3.from_matrix(np.asarray(d["T_cam_from_world"]))
            for o in structure.objects:
                c = structure.models[o.obj_id].vertices_m.mean(axis=0)
                A, B = T @ o.T_world_from_obj, T_ref @ o.T_world_from_obj
                row["parts"][o.name] = {
                    "centre_err_mm": 1e3 * float(np.linalg.norm(A.apply(c[None]) - B.apply(c[None]))),
                    "rot_err_deg": float(np.degrees(geodesic_angle(A.R, B.R)))}
            row["worst_mm"] = max(v["centre_err_mm"] for v in row["parts"].values())
            row["worst_deg"] = max(v["rot_err_deg"] for v in row["parts"].values())
        rows.append(row)
    worst = [(r["worst_mm"], r["worst_deg"]) for r in rows if "worst_mm" in r]
    summary: dict = {"frames": len(rows), "tracked": sum(r["state"] == "ok" for r in rows),
                     "accurate": sum(mm <= ACCURATE[0] and deg <= ACCURATE[1] for mm, deg in worst),
                     "wrong": sum(mm > WRONG[0] or deg > WRONG[1] for mm, deg in worst), "parts": {}}
    for o in structure.objects:
        t = [r["parts"][o.name]["centre_err_mm"] for r in rows if o.name in r["parts"]]
        a = [r["parts"][o.name]["rot_err_deg"] for r in rows if o.name in r["parts"]]
        summary["parts"][o.name] = {"median_mm": float(np.median(t)) if t else None,
                                    "median_deg": float(np.median(a)) if a else None,
                                    "mean_mm": float(np.mean(t)) if t else None,
                                    "mean_deg": float(np.mean(a)) if a else None}
    write_json(Path(out_dir) / "truth_errors.json", {"summary": summary, "frames": rows})
    _plot_truth(Path(out_dir) / "truth_errors.png", rows, [o.name for o in structure.objects])
    return summary


def _plot_truth(path: Path, rows: list[dict], names: list[str]) -> None:
    from matplotlib.figure import Figure  # lazy: heavy dependency (matplotlib)

    fig = Figure(figsize=(9 if len(names) <= 6 else 11, 5), dpi=100)
    ax1, ax2 = fig.subplots(2, 1, sharex=True)
    for name in names:
        f = [r["frame"] for r in rows if name in r["parts"]]
        ax1.plot(f, [r["parts"][name]["centre_err_mm"] for r in rows if name in r["parts"]], ".-", label=name)
        ax2.plot(f, [r["parts"][name]["rot_err_deg"] for r in rows if name in r["parts"]], ".-", label=name)
    lost = [r["frame"] for r in rows if r["state"] != "ok"]
    for ax in (ax1, ax2):
        for k in lost:
            ax.axvspan(k - 0.5, k + 0.5, color="0.85", lw=0)
        ax.grid(alpha=0.3)
    ax1.set_ylabel("centre error, mm")
    ax2.set_ylabel("rotation error, deg")
    ax2.set_xlabel("frame (grey: lost, no pose reported)")
    if len(names) <= 6:
        ax1.legend()
    else:  # a whole structure's parts: beside the plots, not over them
        ax1.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7, ncol=1 + len(names) // 14)
    ax1.set_title("tracked part poses against the reference poses")
    fig.tight_layout()
    fig.savefig(path)
