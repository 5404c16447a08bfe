"""``cadalign emulate (lidar|sonar|view|mesh) SOURCE --out DIR``: emulated sensors by ray casting."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import typer

from cadalign.cli.common import console, user_errors
from cadalign.config import resolve
from cadalign.emulate.layered_mesh import PRESETS, LayeredMeshConfig
from cadalign.emulate.run import CONFIGS, default_pose, parse_pose, run, sensor_pose_from_camera
from cadalign.emulate.sources import image_scene_dir, require_image_source
from cadalign.errors import InputError
from cadalign.sim.trajectory import look_at as look_at_fn
from cadalign.types import Rigid3

app = typer.Typer(help="Emulate LiDAR, multibeam sonar or novel views by ray casting, or build a layered mesh "
                       "from one image.", no_args_is_help=True)

SOURCE_HELP = ("Scene spec (TOML/YAML), mesh PLY (e.g. a fused map; colour/class/part/pane properties used), a CAD "
               "file (OBJ, STL, GLB/GLTF, DAE, OFF, STEP/IGES), or an image: SCENE/rgb/NNNNNN.png of a BOP scene or "
               "an .npz with rgb, depth_m, K.")
UNIT_HELP = ("Length unit of a mesh/CAD SOURCE: m, cm, mm or in. Default: metres for a PLY, else the unit the file "
             "declares or the size rule of 'cadalign.cad.load_cad'.")
POSE_HELP = ("Sensor pose in the world: 'x,y,z' or 'x,y,z,roll,pitch,yaw' (m, deg, extrinsic xyz) or a JSON with "
             "a 4x4 T_world_from_sensor. Axes: LiDAR/sonar x forward, y left, z up; views x right, y down, "
             "z forward (aim with --look-at). Default: a scene's first trajectory pose / the image's camera.")


MODEL_DEPTH_HELP = "Image sources: a 'cadalign train depth' run (or .pt) whose depth replaces the ground truth."
MODEL_SEG_HELP = "Image sources: a 'cadalign train seg' run (or .pt) whose classes replace the ground truth."


def _predictors(model_depth: Path | None, model_seg: Path | None, device: str, source: Path) -> dict:
    """``run`` keyword arguments using trained networks for an image source's depth / classes.

    The frame is prepared as each network's training images were (:mod:`cadalign.sfm.image_prep`: a built
    dataset's frames are already CLAHE-enhanced, a simulator's are raw; an ``.npz`` says nothing and is fed as
    it is).

    Raises:
        InputError: a network is given with a scene or mesh source (it has exact depth and classes).
    """
    if model_depth is None and model_seg is None:
        return {}
    # lazy: pulls cv2; keeps `cadalign --help` light
    from cadalign.fuse.predictors import depth_predictor, seg_predictor
    from cadalign.sfm.image_prep import read_prep  # lazy: pulls cv2; keeps `cadalign --help` light

    source = Path(source)  # checked before the networks are built
    require_image_source(source, " and ".join(o for o, m in (("--model-depth", model_depth),
                                                             ("--model-seg", model_seg)) if m))
    scene_dir = image_scene_dir(source)
    source_prep = read_prep(scene_dir) if scene_dir is not None else None
    seg_fn = seg_predictor(model_seg, None, device, source_prep) if model_seg is not None else None
    depth_fn = None
    if model_depth is not None:
        depth_fn = depth_predictor(model_depth, seg=seg_fn, device=device, source_prep=source_prep)
    models = {k: str(v) for k, v in (("depth", model_depth), ("seg", model_seg)) if v is not None}
    return {"depth_fn": depth_fn, "seg_fn": seg_fn, "models": models}


def _emulate(sensor: str, source: Path, out: Path, preset: str | None, config: Path | None, pose: str | None,
             look_at: str | None, engine: str | None, overwrite: bool, models: dict | None = None,
             unit: str | None = None) -> Path:
    cls, presets, default = CONFIGS[sensor]
    overrides = {"engine": engine} if engine is not None else {}
    cfg = resolve(cls, presets, preset or default, config, overrides)
    T = parse_pose(pose) if pose is not None else None
    if look_at is not None:
        target = parse_pose(look_at).t
        eye = (T or default_pose(source, sensor)).t
        if np.linalg.norm(target - eye) < 1e-9:
            raise InputError(f"--look-at {look_at!r} coincides with the sensor position")
        T_cam = look_at_fn(eye, target)
        T = T_cam if sensor in ("view", "mesh") else sensor_pose_from_camera(T_cam)
    assert T is None or isinstance(T, Rigid3)
    return run(sensor, cfg, source, out, pose=T, overwrite=overwrite, unit=unit,  # type: ignore[arg-type]
               **(models or {}))


def _options(sensor: str, default_preset: str, what: str):
    def command(
        source: Path = typer.Argument(..., help=SOURCE_HELP),
        out: Path = typer.Option(..., "--out", help=f"Output folder ({what})."),
        pose: str | None = typer.Option(None, "--pose", help=POSE_HELP),
        look_at: str | None = typer.Option(None, "--look-at", help="Aim the sensor at this world point 'x,y,z'."),
        preset: str = typer.Option(default_preset, "--preset", help="Sensor preset (see the config module)."),
        config: Path | None = typer.Option(None, "--config", help="TOML/YAML with overrides of the preset."),
        engine: str | None = typer.Option(None, "--engine", help="Ray caster: bvh (Open3D) or torch (exact)."),
        model_depth: Path | None = typer.Option(None, "--model-depth", help=MODEL_DEPTH_HELP),
        model_seg: Path | None = typer.Option(None, "--model-seg", help=MODEL_SEG_HELP),
        device: str = typer.Option("cpu", "--device", help="Torch device of the networks."),
        unit: str | None = typer.Option(None, "--unit", help=UNIT_HELP),
        overwrite: bool = typer.Option(False, "--overwrite", help="Replace results made with another config."),
    ) -> None:
        with user_errors():
            models = _predictors(model_depth, model_seg, device, source)
            path = _emulate(sensor, source, out, preset, config, pose, look_at, engine, overwrite, models, unit)
        console.print(f"[green]{sensor} written to {path}[/]")

    return command


def _register() -> None:
    docs = {
        "lidar": ("scan.npz, scan.ply, lidar_class.png", "Spinning LiDAR / sphere scan: points with range, colour, "
                  "class and part id. Presets: " + ", ".join(CONFIGS["lidar"][1])),
        "sonar": ("sonar.npz, sonar.png, sonar_polar.png", "Multibeam imaging sonar: range x bearing intensity "
                  "with incidence-angle reflectance, attenuation and speckle. Presets: "
                  + ", ".join(CONFIGS["sonar"][1])),
        "view": ("rgb.png, depth.png, class.png, view.npz", "Novel RGB / depth / class view from any pose. "
                 "Presets: " + ", ".join(CONFIGS["view"][1])),
    }
    for sensor, (what, doc) in docs.items():
        cmd = _options(sensor, CONFIGS[sensor][2], what)
        cmd.__doc__ = doc
        app.command(sensor)(cmd)


_register()


PHOTO_HELP = ("An RGB frame of a BOP scene (SCENE/rgb/NNNNNN.png; depth, class and instance maps read beside it), "
              "an .npz with rgb, depth_m, K, or any photograph (.jpg/.png; with --depth-model) or a point-map .npz "
              "(rgb + points, or rgb + depth_m + rays).")


def _is_photo(source: Path, photo_options: list) -> bool:
    """Whether ``emulate mesh`` takes the photo path (:mod:`cadalign.emulate.photo`): a photo option is given, or
    the source is an image outside a BOP scene folder, or an ``.npz`` point map."""

    from cadalign.emulate.photo import PHOTO_SUFFIXES  # lazy: pulls cv2; keeps `cadalign --help` light

    if any(o is not None for o in photo_options):
        return True
    suffix = source.suffix.lower()
    if suffix == ".npz" and source.is_file():
        with np.load(source) as z:
            return "points" in z.files or "rays" in z.files
    return suffix in PHOTO_SUFFIXES and not (source.parent.name == "rgb"
                                             and (source.parent.parent / "scene_camera.json").is_file())


@app.command("mesh")
def mesh(
    source: Path = typer.Argument(..., help=PHOTO_HELP),
    out: Path = typer.Option(..., "--out", help="Output folder (layered_mesh.ply, preview_rgb.png, ...)."),
    preset: str = typer.Option("default", "--preset", help="default | coarse | strict."),
    config: Path | None = typer.Option(None, "--config", help="TOML/YAML with overrides of the preset."),
    model_depth: Path | None = typer.Option(None, "--model-depth", help=MODEL_DEPTH_HELP),
    model_seg: Path | None = typer.Option(None, "--model-seg", help=MODEL_SEG_HELP),
    depth_model: Path | None = typer.Option(None, "--depth-model", help="Photos: a local transformers depth "
                                            "checkpoint folder (Depth Anything V1/V2 metric or relative, DPT)."),
    seg_model: Path | None = typer.Option(None, "--seg-model", help="Photos: a local SegFormer checkpoint folder "
                                          "(e.g. ADE20k; its glass / window classes become planar panes)."),
    hfov: float | None = typer.Option(None, "--hfov", help="Photos: horizontal field of view, degrees."),
    calib: Path | None = typer.Option(None, "--calib", help="Photos: a cameras.json whose K is used."),
    scale_from: str | None = typer.Option(None, "--scale-from", help="Photos: metric scale of relative depth: "
                                          "distance:M (median depth), pixel:U,V:M or depth:PATH (sparse metric "
                                          "depth)."),
    pane_mask: Path | None = typer.Option(None, "--pane-mask", help="Photos: a mask image of glass / panes."),
    sr_model: Path | None = typer.Option(None, "--sr-model", help="Photos: a Real-ESRGAN (RRDBNet) .pth that "
                                         "upscales the photo before depth (unmeasured; off by default)."),
    device: str = typer.Option("cpu", "--device", help="Torch device of the networks."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace results made with another config."),
) -> None:
    """Layered mesh from one image: grid triangles cut at depth jumps, class/part/pane layers, planar panes.

    From a photograph (GenLaM): depth from --depth-model, field of view from --calib / --hfov / EXIF / an
    eq. (1) fit to a point map, classes from --seg-model or --model-seg; writes also scan.npz, contact.png and
    lidar_pose.json (for 'emulate lidar OUT/layered_mesh.ply --pose OUT/lidar_pose.json'; the mesh is in the
    photo's camera frame, so 'emulate view OUT/layered_mesh.ply --pose 0,0,0' sees it as the photo did).
    """
    with user_errors():
        if _is_photo(source, [depth_model, seg_model, hfov, calib, scale_from, pane_mask, sr_model]):
            path = _photo(source, out, preset, config, model_depth, model_seg, depth_model, seg_model, hfov, calib,
                          scale_from, pane_mask, sr_model, device, overwrite)
        else:
            models = _predictors(model_depth, model_seg, device, source)
            path = _emulate("mesh", source, out, preset, config, None, None, None, overwrite, models)
    console.print(f"[green]layered mesh written to {path}[/]")


def _photo(source: Path, out: Path, preset: str, config: Path | None, model_depth: Path | None,
           model_seg: Path | None, depth_model: Path | None, seg_model: Path | None, hfov: float | None,
           calib: Path | None, scale_from: str | None, pane_mask: Path | None, sr_model: Path | None, device: str,
           overwrite: bool) -> Path:
    from cadalign.emulate import photo  # lazy: pulls cv2; keeps `cadalign --help` light
    from cadalign.emulate.pretrained import PretrainedConfig  # lazy: pulls cv2; keeps `cadalign --help` light

    if model_depth is not None:
        raise InputError("--model-depth (a network trained on the simulator) needs a BOP frame or an .npz with K; "
                         "for a photograph pass --depth-model DIR (a local transformers checkpoint)")
    if seg_model is not None and model_seg is not None:
        raise InputError("give --seg-model (a SegFormer checkpoint) or --model-seg (a 'train seg' run), not both")
    cfg = photo.PhotoConfig(mesh=resolve(LayeredMeshConfig, PRESETS, preset, config),
                            pretrained=PretrainedConfig(device=device))
    return photo.run(cfg, source, out, depth_model=depth_model, seg_model=seg_model, seg_run=model_seg,
                     sr_model=sr_model, hfov_deg=hfov, calib=calib, scale_from=scale_from, pane_mask=pane_mask,
                     overwrite=overwrite)
