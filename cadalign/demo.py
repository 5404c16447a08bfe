"""The end-to-end demo on the embedded default scene (what ``make demo`` runs).

Each stage writes into its own sub-folder of ``out`` and reuses finished work,
so re-running the demo after an interruption continues where it stopped.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

from cadalign import demo_stages as st
from cadalign.demo_stages import DemoConfig, DemoContext
from cadalign.eval.report import write_report
from cadalign.io import read_json, write_json
from cadalign.sim.spec import default_scene_path

log = logging.getLogger(__name__)

LEARNING_STAGES = {
    "train-seg": st.train_seg_stage, "train-depth": st.train_depth_stage, "train-pose": st.train_pose_stage,
    "infer": st.infer_stage, "fuse": st.fuse_stage, "emulate": st.emulate_stage,
}
"""Stages after the dataset build, in order (infer needs train-pose; fuse with predictions needs seg/depth)."""


def run_demo(out: Path, *, scene: Path | None = None, frames: int | None = None,
             resolution: tuple[int, int] | None = None, progress: Any = None,
             cfg: DemoConfig | None = None) -> dict:
    """Run every stage on ``scene`` (default: the embedded scene); returns the summary dict.

    simulate -> build the dataset from the video (SfM, alignment, CAD ground truth) -> train the
    segmentation, depth and detector+pose networks -> infer poses on held-out frames -> fuse semantic
    maps (exact and predicted inputs) -> emulate a LiDAR scan and a sonar image -> report.html. When the
    build fails its gate, the learning stages use the simulator's exact ground truth instead, and the
    summary says so (and ``ok`` is False).
    """
    from cadalign.sim.run import simulate

    out = Path(out)
    scene = Path(scene) if scene is not None else default_scene_path()
    stages: dict[str, dict] = {}
    t0 = time.perf_counter()
    sim_dir = simulate(scene, out / "sim", frames=frames, resolution=resolution, progress=progress)
    stages["sim"] = {"status": "done", "dir": "sim", "seconds": round(time.perf_counter() - t0, 2),
                     "report": read_json(sim_dir / "sim_report.json")}
    stages["build-dataset"] = _build_stage(sim_dir, scene, out / "build", progress)
    built = stages["build-dataset"]["status"] == "done"
    ctx = DemoContext(out, sim_dir, scene, out / "build" / "dataset" if built else sim_dir / "gt" / "sim" / "000000",
                      "built" if built else "simulator ground truth", cfg or DemoConfig())
    for name, fn in LEARNING_STAGES.items():
        log.info("demo stage %s", name)
        stages[name] = st.timed(name, fn, ctx)
        _write(out, scene, stages)
    return _write(out, scene, stages)


def _write(out: Path, scene: Path, stages: dict[str, dict]) -> dict:
    summary = {"scene": str(scene), "stages": stages,
               "ok": all(v["status"] == "done" for v in stages.values()),
               "seconds_total": round(sum(v.get("seconds", 0.0) for v in stages.values()), 1)}
    write_json(out / "summary.json", summary)
    write_report(out, summary)
    return summary


def _build_stage(sim_dir: Path, scene: Path, out: Path, progress: Any) -> dict:
    """SfM -> alignment -> dataset on the simulated video, checked against the simulator's truth.

    A failed alignment gate is a result, not a crash: the report shows why no dataset was written.
    """
    from cadalign.build_dataset import build_dataset
    from cadalign.errors import AlignmentError, CadalignError

    t0 = time.perf_counter()
    try:
        # the simulated ROV camera's calibration, as a real survey would pass its underwater calibration
        build_dataset(sim_dir / "frames", scene, out, preset="balanced", gt=sim_dir, progress=progress,
                      calib=sim_dir / "calibration.json")
    except AlignmentError as exc:
        return {"status": "failed (alignment gate)", "dir": "build", "error": str(exc),
                "seconds": round(time.perf_counter() - t0, 2)}
    except CadalignError as exc:  # e.g. SfM found no model: reported, and the learning stages fall back
        return {"status": f"failed ({type(exc).__name__})", "dir": "build", "error": str(exc),
                "seconds": round(time.perf_counter() - t0, 2)}
    report = read_json(out / "build_report.json")
    return {"status": "done", "dir": "build", "seconds": round(time.perf_counter() - t0, 2),
            "vs_truth": report.get("vs_truth"), "frames": report["frames"], "splits": report["splits"]}
