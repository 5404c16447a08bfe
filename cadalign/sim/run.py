"""``simulate``: render a scene spec into a capture folder plus BOP ground truth.

Output layout (``OUT``)::

    OUT/frames/000000.png        what a real ROV camera would give (all declared effects applied)
    OUT/video.mp4                the same frames as a video
    OUT/gt/models/               obj_000001.ply ... (mm) + models_info.json (BOP)
    OUT/gt/sim/000000/           a BOP scene: rgb/ depth/ mask/ mask_visib/ scene_camera.json
                                 scene_gt.json scene_gt_info.json, plus cadalign extras:
                                 class/ (uint8 class ids), instance/ (uint16, 0 = none, k = GT index k-1),
                                 normals/ (npz, camera frame), cameras.json, objects.json
    OUT/calibration.json         the camera's intrinsics, as an underwater calibration of a real ROV camera
                                 would give them (``--calib`` of sfm / build-dataset)
    OUT/navigation.json          a rough camera pose per frame, as an ROV's navigation gives it (``infer --nav``;
                                 :mod:`cadalign.sim.navigation`)
    OUT/contact_sheet.png        clean render vs each effect alone vs all effects
    OUT/sim_report.json          frames, seconds per frame per step and per effect
    OUT/cadalign_stage.json      the resolved config and version

Frames are rendered independently with a per-frame seed, so an interrupted run
resumes where it stopped and gives the same files as an uninterrupted one.
"""

from __future__ import annotations

import dataclasses
import logging
import shutil
import time
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numpy as np

from cadalign.formats import bop
from cadalign.io import atomic_path, prepare_stage_dir, read_image, read_json, write_image, write_json
from cadalign.raycast.bop_writer import frame_done, write_bop_frame
from cadalign.sim.contact_sheet import write_contact_sheet
from cadalign.sim.effects_chain import build_chain, run_chain
from cadalign.sim.gt_files import posed_objects, write_models, write_scene_files
from cadalign.sim.navigation import write_navigation
from cadalign.sim.render import FrameGT, GroundTruthCaster, RGBRenderer
from cadalign.sim.scene import SimScene, build_scene, camera_from_spec
from cadalign.sim.spec import SceneSpec, load_scene
from cadalign.sim.trajectory import pose_at
from cadalign.types import Camera, Progress, Rigid3

log = logging.getLogger(__name__)
DEPTH_SCALE = 1.0  # BOP depth PNG unit: 1 mm (65.5 m range)
SCENE_SUBDIR = Path("gt") / "sim" / "000000"



def apply_overrides(
    spec: SceneSpec, frames: int | None, resolution: tuple[int, int] | None, seed: int | None
) -> SceneSpec:
    """The spec with command-line overrides applied (validated like the file)."""
    if frames is not None:
        spec = dataclasses.replace(spec, trajectory=dataclasses.replace(spec.trajectory, frames=frames))
    if resolution is not None:
        spec = dataclasses.replace(
            spec, camera=dataclasses.replace(spec.camera, width=resolution[0], height=resolution[1])
        )
    if seed is not None:
        spec = dataclasses.replace(spec, seed=seed)
    return spec


def simulate(
    scene_path: Path,
    out_dir: Path,
    *,
    frames: int | None = None,
    resolution: tuple[int, int] | None = None,
    seed: int | None = None,
    overwrite: bool = False,
    video: bool = True,
    contact_sheet: bool = True,
    progress: Progress | None = None,
) -> Path:
    """Render ``scene_path`` into ``out_dir``; returns ``out_dir``. Finished frames are reused."""
    scene_path, out_dir = Path(scene_path), Path(out_dir)
    spec = apply_overrides(load_scene(scene_path), frames, resolution, seed)
    config = {"scene": spec, "scene_file": str(scene_path.resolve()), "video": video}
    if overwrite and out_dir.exists():
        shutil.rmtree(out_dir)
    reused = prepare_stage_dir(out_dir, "sim", config)
    write_calibration(camera_from_spec(spec), out_dir / "calibration.json")
    report_path = out_dir / "sim_report.json"
    if reused and report_path.is_file():
        log.info("simulation in %s is complete; reusing it", out_dir)
        if not (out_dir / "navigation.json").is_file():  # a simulation made before the file was written
            write_navigation(out_dir, spec.seed)
        return out_dir
    scene = build_scene(spec, scene_path)
    write_models(scene, out_dir / "gt" / "models")
    timings = _render_frames(scene, out_dir, progress)
    write_scene_files(scene, out_dir / SCENE_SUBDIR)
    write_navigation(out_dir, spec.seed)
    if video:
        write_video(
            sorted((out_dir / "frames").glob("*.png")), out_dir / "video.mp4", fps=max(spec.trajectory.fps, 1)
        )
    if contact_sheet:
        write_contact_sheet(scene, out_dir / "contact_sheet.png")
    write_json(report_path, _report(spec, timings))
    return out_dir


def write_calibration(camera: Camera, path: Path) -> None:
    """The simulated camera's intrinsics as a calibration file (no distortion: the simulator has none)."""
    write_json(path, {"K": [float(v) for v in np.asarray(camera.K).ravel()], "width": camera.width,
                      "height": camera.height, "distortion": None, "unit": "px",
                      "convention": "pixel (0, 0) covers [0, 1)^2 (centres at +0.5), as COLMAP"})


def render_frame(
    scene: SimScene, chain: list, k: int, renderer: RGBRenderer, caster: GroundTruthCaster
) -> tuple[Rigid3, np.ndarray, FrameGT, dict[str, float]]:
    """Frame ``k``: its camera pose, the image with the declared effects, exact ground truth and timings.

    This is the whole per-frame simulation path (what ``cadalign bench sim`` measures); with an empty
    ``chain`` the image is the clean render itself.
    """
    spec = scene.spec
    T = pose_at(spec.trajectory, k / spec.trajectory.fps, spec.seed)
    t0 = time.perf_counter()
    clean = renderer.render(T)
    t1 = time.perf_counter()
    gt = caster.cast(T)
    t2 = time.perf_counter()
    rgb, eff_t = run_chain(chain, clean, gt, spec, k, T, scene.camera)
    timings = {"render_rgb": t1 - t0, "ground_truth": t2 - t1}
    timings.update({f"effect:{name}": sec for name, sec in eff_t.items()})
    return T, rgb, gt, timings


def _render_frames(scene: SimScene, out_dir: Path, progress: Progress | None) -> dict[str, list[float]]:
    """Render every unfinished frame; file writing overlaps the next frame's rendering (one writer thread)."""

    spec = scene.spec
    n = spec.trajectory.frames
    chain = build_chain(spec)
    timings: dict[str, list[float]] = {"render_rgb": [], "ground_truth": [], "write": []}
    rgb_renderer = RGBRenderer(scene)
    caster = GroundTruthCaster(scene)
    pending: list[Future] = []

    def write(k: int, T: Rigid3, rgb: np.ndarray, gt: FrameGT) -> float:
        t0 = time.perf_counter()
        _write_frame(out_dir, scene, k, T, rgb, gt)
        return time.perf_counter() - t0

    try:
        with ThreadPoolExecutor(max_workers=1, thread_name_prefix="sim-write") as pool:
            ids = range(n)
            for k in progress(ids, "simulate", n) if progress else ids:
                if _frame_done(out_dir, k):
                    continue
                T, rgb, gt, frame_t = render_frame(scene, chain, k, rgb_renderer, caster)
                for name, sec in frame_t.items():
                    timings.setdefault(name, []).append(sec)
                while len(pending) >= 2:  # bound memory: at most two frames waiting to be written
                    timings["write"].append(pending.pop(0).result())
                pending.append(pool.submit(write, k, T, rgb, gt))
            for fut in pending:
                timings["write"].append(fut.result())
    finally:
        rgb_renderer.close()
    return timings


def _frame_done(out_dir: Path, k: int) -> bool:
    return frame_done(out_dir / SCENE_SUBDIR, k)


def _write_frame(
    out_dir: Path, scene: SimScene, k: int, T_world_from_cam: Rigid3, rgb: np.ndarray, gt: FrameGT
) -> None:
    img8 = (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
    frame_png = out_dir / "frames" / bop.frame_name(k)
    write_image(frame_png, img8, atomic=False)  # the frame record written last marks completion
    write_bop_frame(out_dir / SCENE_SUBDIR, k, scene.camera, T_world_from_cam.inverse(), gt,
                    posed_objects(scene), DEPTH_SCALE, rgb_source=frame_png)


def write_video(frames: list[Path], path: Path, fps: float) -> Path:
    """Encode PNG frames to an H.264 MP4 (imageio-ffmpeg's bundled ffmpeg), atomically."""
    import imageio.v2 as imageio  # lazy: heavy dependency (imageio)

    with atomic_path(path) as tmp:
        with imageio.get_writer(
            tmp,
            format="FFMPEG",
            fps=fps,
            codec="libx264",
            quality=8,
            macro_block_size=16,
            ffmpeg_log_level="error",
        ) as writer:
            for f in frames:
                writer.append_data(read_image(f))
    return path


def _report(spec: SceneSpec, timings: dict[str, list[float]]) -> dict:
    per_frame = {k: float(np.median(v)) for k, v in timings.items() if v}
    effects = {k.split(":", 1)[1]: v for k, v in per_frame.items() if k.startswith("effect:")}
    return {
        "scene": spec.name,
        "frames": spec.trajectory.frames,
        "resolution": [spec.camera.width, spec.camera.height],
        "effects": list(spec.effects),
        "seconds_per_frame_median": per_frame,
        "seconds_per_frame_per_effect": effects,
        "seconds_per_frame_effects_total": float(sum(effects.values())),
        "frames_rendered_this_run": len(timings.get("render_rgb", [])),
    }


def load_frame_records(scene_dir: Path) -> list[dict]:
    """The per-frame JSON records of a simulated scene, in frame order."""
    return [read_json(p) for p in sorted((Path(scene_dir) / "frames_json").glob("*.json"))]
