"""``build_dataset``: ROV video (or frames) + CAD -> a metric, dense, per-frame BOP dataset.

Steps, each in its own folder of ``OUT`` and each reused when finished (an interrupted build resumes
at the frame it was rendering, without redoing SfM or the alignment)::

    OUT/sfm/        cadalign.sfm: frames, COLMAP model, cameras.json, SfM depth (SfM units), report
    OUT/align/      cadalign.align: align.json (cad_from_sfm, a Sim3 to metres) + align.png
    OUT/dataset/    the BOP dataset
        models/                 obj_XXXXXX.ply (mm) + models_info.json (diameters, symmetries)
        all/000000/             one BOP scene, every registered frame (rgb, depth, mask, mask_visib,
                                scene_camera/scene_gt/scene_gt_info.json, class/, instance/, normals/,
                                cameras.json, objects.json) plus depth_sfm/ (the SfM depth in BOP
                                encoding, metres after the alignment) and frame_names.json
        splits.json             train/val/test image ids by time blocks (no near-duplicate leakage)
        coco_{split}.json       COCO instance annotations per split
    OUT/build_report.json, OUT/build_report.html   alignment quality, timings; with ``gt`` the errors
                                against the simulator's truth and the CAD-depth vs SfM-depth table

The CAD is either a scene spec (TOML/YAML: the structure's parts with their world poses and classes, e.g.
``datasets/scenes/default.toml``) or one mesh file (one part, class ``structure``).
"""

from __future__ import annotations

import dataclasses
import logging
import shutil
import time
from collections.abc import Mapping
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from cadalign.align import PRESETS as ALIGN_PRESETS
from cadalign.align import read_sim3
from cadalign.align import run as align_run
from cadalign.align.camera_refine import CameraRefineConfig, RefinedCamera, rays_of, refine_cameras
from cadalign.align.edge_refine import edge_align_frames
from cadalign.align.gates import check_gates, measure, raise_if_failed
from cadalign.align.roi import read_roi, roi_mask
from cadalign.align.run import load_cloud
from cadalign.align.seabed import SeabedConfig, seabed_from_model
from cadalign.align.surface import sample_surface
from cadalign.align.verify.core import VerifyConfig
from cadalign.align.verify.run import VerificationError, verify_alignment
from cadalign.build.frames import CameraModel, FrameJob, FrameShared, render_chunk
from cadalign.build.report import evaluate_against_sim, write_build_html
from cadalign.cad.models_info import write_model_ply_mm, write_models_info
from cadalign.config import from_dict
from cadalign.errors import ConfigError, InputError
from cadalign.formats.bop import BopScene
from cadalign.formats.calibration import frame_pose
from cadalign.formats.coco import coco_annotations, write_coco
from cadalign.formats.splits import time_block_splits
from cadalign.geometry import sim3_from_matrix
from cadalign.io import fingerprint, prepare_stage_dir, read_json, write_json
from cadalign.raycast.bop_writer import frame_done, merge_scene_files, visible_masks
from cadalign.raycast.core import RaycastRenderer, RenderMesh
from cadalign.sfm import PRESETS as SFM_PRESETS
from cadalign.sfm import SfMConfig
from cadalign.sfm import run as sfm_run
from cadalign.sfm.colmap_log import colmap_log
from cadalign.sfm.image_prep import prep_of_frame_config, write_record
from cadalign.sfm.known_camera import with_calibration
from cadalign.sim.structure import Structure, load_structure
from cadalign.types import Camera, Progress, Rigid3, Sim3

if TYPE_CHECKING:
    from cadalign.build.executor import RayExecutor

log = logging.getLogger(__name__)
SCENE = Path("all") / "000000"
DEPTH_SCALE = 1.0
DEFAULT_REFINE = CameraRefineConfig()
DEFAULT_SEABED = SeabedConfig()
DEFAULT_VERIFY = VerifyConfig()


def metric_pose(entry: dict, cad_from_sfm: Sim3) -> tuple[Camera, Rigid3]:
    """A cameras.json entry (SfM units) -> (camera, metric ``T_world_from_cam`` in the CAD frame)."""
    T = cad_from_sfm.carry_pose(frame_pose(entry).inverse())
    return Camera(np.reshape(entry["K"], (3, 3)), int(entry["width"]), int(entry["height"])), T


def render_frames(structure: Structure, cameras: dict[str, dict], cad_from_sfm: Sim3, sfm_dir: Path,
                  scene_dir: Path, progress: Progress | None = None,
                  refine: CameraRefineConfig | None = DEFAULT_REFINE, executor: RayExecutor | None = None,
                  seabed: SeabedConfig | None = DEFAULT_SEABED) -> tuple[dict[int, str], dict[int, bool]]:
    """Ray-cast and write every registered frame (resumably).

    Rays come from the SfM camera model (its distortion included), poses from the SfM refined against the
    CAD (:mod:`cadalign.align.camera_refine`) unless ``refine`` is None. The seabed found by SfM round the
    structure (:mod:`cadalign.align.seabed`, unless ``seabed`` is None) occludes it. With an ``executor`` (Ray) the
    frames are rendered by its workers, else here by the same loop (:func:`cadalign.build.frames.render_chunk`).
    Returns im_id -> source frame name and im_id -> whether the frame's pose was verified against the CAD.
    """
    import pycolmap  # lazy: heavy dependency (pycolmap)

    names = sorted(cameras)
    rec = pycolmap.Reconstruction(str(sfm_dir / "sparse" / "0"))
    meshes, rec, refined, edge_poses, edge_info = _against_cad(structure, rec, cad_from_sfm, sfm_dir,
                                                               scene_dir.parent.parent, refine, seabed, progress)
    by_name = {im.name: im for im in rec.images.values()}
    ids = list(range(len(names)))
    quality: dict[int, dict] = {}
    shared = FrameShared(tuple(meshes), structure.objects, {}, scene_dir, DEPTH_SCALE)
    pending: list[FrameJob] = []
    for k in ids:
        _, T_world_from_cam = metric_pose(cameras[names[k]], cad_from_sfm)
        cam = by_name[names[k]].camera
        camera = Camera(np.asarray(cam.calibration_matrix(), dtype=np.float64), int(cam.width), int(cam.height))
        r = refined.get(names[k])
        if r is not None:
            T_world_from_cam = edge_poses.get(names[k], r.T_world_from_cam)
            quality[k] = {"verified": r.verified, "pairs": r.n_pairs, "inliers": r.n_inliers, "rms_px": r.rms_px,
                          "shift_m": r.shift_m, "turn_deg": r.turn_deg, "edges": edge_info.get(names[k])}
        else:
            quality[k] = {"verified": refine is None}
        if frame_done(scene_dir, k):
            continue
        sfm_depth = sfm_dir / "depth" / f"{Path(names[k]).stem}.npy"
        job = FrameJob(k, cam.camera_id, camera, T_world_from_cam, sfm_dir / "images" / names[k],
                       sfm_depth if sfm_depth.is_file() else None, cad_from_sfm.s)
        pending.append(job)
        shared.cameras[cam.camera_id] = CameraModel.of(cam)
    if executor is not None:  # rendered by the executor's workers
        executor.render(pending, shared, progress)
    else:  # here, by the same loop a worker runs
        render_chunk(pending, shared, progress)
    merge_scene_files(scene_dir, structure.objects, structure.class_names)
    frame_names = {k: n for k, n in zip(ids, names, strict=True)}
    write_json(scene_dir / "frame_names.json", {str(k): n for k, n in frame_names.items()})
    write_json(scene_dir / "frame_quality.json", {str(k): q for k, q in quality.items()})
    return frame_names, {k: bool(q["verified"]) for k, q in quality.items()}


def _against_cad(structure: Structure, rec: Any, cad_from_sfm: Sim3, sfm_dir: Path, ds: Path,
                 refine: CameraRefineConfig | None, seabed: SeabedConfig | None, progress: Progress | None,
                 ) -> tuple[list[RenderMesh], Any, dict[str, RefinedCamera], dict[str, Rigid3], dict[str, dict]]:
    """The meshes to render (the CAD, plus the seabed as an occluder when SfM shows one), the model with
    the refined intrinsics, the CAD-anchored cameras and their edge-aligned poses."""

    meshes = structure.render_meshes()
    verts = np.concatenate([m.vertices_m for m in meshes])
    offsets = np.cumsum([0] + [len(m.vertices_m) for m in meshes[:-1]])
    faces = np.concatenate([m.faces + o for m, o in zip(meshes, offsets, strict=True)])
    floor = seabed_from_model(rec, cad_from_sfm, verts, faces, seabed) if seabed is not None else None
    write_json(ds / "seabed.json", {"found": floor is not None, **(floor.summary if floor else {})})
    if floor is not None:
        meshes.append(RenderMesh(floor.vertices, floor.faces, 0, 0))
    refined: dict[str, RefinedCamera] = {}
    if refine is not None:
        result = refine_cameras(rec, cad_from_sfm, verts, faces, refine)
        refined, rec = result.frames, result.model
        write_json(ds / "camera_refine.json", result.summary)
    edge_poses, edge_info = _edge_align(meshes, rec, refined, sfm_dir, ds, refine, progress)
    return meshes, rec, refined, edge_poses, edge_info


def _edge_align(meshes: list[RenderMesh], rec: Any, refined: dict[str, RefinedCamera], sfm_dir: Path, ds: Path,
                refine: CameraRefineConfig | None, progress: Progress | None,
                ) -> tuple[dict[str, Rigid3], dict[str, dict]]:
    """The verified frames' poses aligned to the CAD's contours in their images (``ds/edge_align.json``
    keeps them, so a resumed build does not redo it); empty when off."""
    if refine is None or not refine.edges.enabled or not refined:
        return {}, {}
    path = ds / "edge_align.json"
    if path.is_file():  # a resumed build: the saved poses (a fresh one reads them back too, so both agree bitwise)
        saved = read_json(path)
        return ({n: Rigid3.from_matrix(np.array(M)) for n, M in saved["T_world_from_cam"].items()},
                saved["frames"])

    by_name = {im.name: im for im in rec.images.values()}
    renderers: dict[int, RaycastRenderer] = {}

    def renderer_of(name: str) -> RaycastRenderer:
        cam = by_name[name].camera
        if cam.camera_id not in renderers:
            K = np.asarray(cam.calibration_matrix(), dtype=np.float64)
            renderers[cam.camera_id] = RaycastRenderer(meshes, Camera(K, int(cam.width), int(cam.height)),
                                                       rays_cam=rays_of(cam))
        return renderers[cam.camera_id]

    def gray_of(name: str) -> np.ndarray:
        img = cv2.imread(str(sfm_dir / "images" / name), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise InputError(f"cannot read frame {sfm_dir / 'images' / name} for the edge alignment; re-run the "
                             "build with --overwrite to extract the frames again")
        return img.astype(np.float32)

    poses = {n: r.T_world_from_cam for n, r in refined.items() if r.verified}
    # the similarity turns and scales about the CAD's centre (not the seabed square's, an occluder only)
    centre = np.concatenate([m.vertices_m for m in meshes if m.instance > 0]).mean(axis=0)
    out, info, summary = edge_align_frames(poses, renderer_of, gray_of, centre, refine.edges, progress)
    write_json(path, {"summary": summary, "frames": info,
                      "T_world_from_cam": {n: T.matrix().tolist() for n, T in out.items()}})
    return _edge_align(meshes, rec, refined, sfm_dir, ds, refine, progress)


def _roi_points(model: Path, roi: Path, sfm_dir: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """The SfM points of ``model`` inside the region of interest ``roi``, and how many images see each."""

    pts, views = load_cloud(model)
    keep = roi_mask(pts, read_roi(roi), read_json(sfm_dir / "cameras.json")["frames"])
    log.info("region of interest %s: %d of %d SfM points", roi, int(keep.sum()), len(pts))
    if keep.sum() < 50:
        raise InputError(f"{roi}: the region of interest holds {int(keep.sum())} of {len(pts)} SfM points; the "
                         "alignment needs many more: enlarge the box or the clicked outlines")
    return pts[keep], None if views is None else views[keep]


def hypotheses_of(align_json: Path) -> tuple[list[Sim3], list[float]]:
    """The alignment's refined hypotheses and their cloud scores (an older align.json: its result only)."""

    rec = read_json(align_json)
    hyps = rec.get("hypotheses") or [{"matrix": rec["cad_from_sfm"]["matrix"], "score": float("nan")}]
    return ([sim3_from_matrix(np.asarray(h["matrix"], dtype=np.float64)) for h in hyps],
            [float(h["score"]) for h in hyps])


def _gate(cfg: Any, points: Path | np.ndarray, views: np.ndarray | None, parts: list, cad_from_sfm: Sim3) -> None:
    """The alignment's quality gates on another hypothesis (``cfg``: an AlignConfig); raises
    ``AlignmentGateError`` when one fails."""

    pts, views = load_cloud(points, views)
    surface = sample_surface(parts, cfg.cad_samples, cfg.seed)
    metrics = measure(pts, surface, cad_from_sfm, cfg.gates, views)
    checks = check_gates(metrics, cad_from_sfm, cad_from_sfm, surface, cfg.gates)
    raise_if_failed(checks, metrics, cad_from_sfm, "the hypothesis the images chose")


def _verify(cfg: VerifyConfig, structure: Structure, align_json: Path, sfm_dir: Path, out: Path,
            hypothesis: int | None, report: dict[str, Any]) -> Any:  # -> Verification
    """The image verification of the alignment's hypotheses; unless ok, writes the refusal into
    ``build_report.json/html`` (beside ``out``) and raises ``VerificationError``."""
    import pycolmap  # lazy: heavy dependency (pycolmap)

    hyps, scores = hypotheses_of(align_json)
    gates = read_json(align_json)["config"]["gates"]
    verts = np.concatenate([m.vertices_m for m in structure.render_meshes()])
    inlier_m = min(gates["inlier_dist_m"], gates["inlier_dist_rel"] * float(np.linalg.norm(np.ptp(verts, axis=0))))
    rec = pycolmap.Reconstruction(str(sfm_dir / "sparse" / "0"))
    try:
        return verify_alignment(cfg, rec, sfm_dir / "images", structure.render_meshes(), hyps, scores, inlier_m,
                                out, hypothesis)
    except VerificationError as exc:
        align_rec = read_json(align_json)
        report = {"refused": str(exc), "verification": exc.verification.summary(), "frames": 0, "splits": {},
                  "alignment": {k: v for k, v in align_rec.items() if k in ("cad_from_sfm", "metrics", "gates")},
                  **report}
        write_json(out.parent / "build_report.json", report)
        write_build_html(out.parent, report)
        raise


def write_dataset_extras(ds: Path, structure: Structure, verified: dict[int, bool] | None = None, block: int = 10,
                         gap: int = 1) -> dict[str, list[int]]:
    """models/ + models_info.json, splits.json and per-split COCO annotations (verified frames only)."""

    for oid, model in structure.models.items():
        write_model_ply_mm(model, ds / "models" / f"obj_{oid:06d}.ply")
    write_models_info(structure.models, ds / "models" / "models_info.json")
    scene = BopScene(ds / SCENE)
    ids = [k for k in scene.ids if verified is None or verified.get(k, False)]
    splits = time_block_splits(ids, block=block, gap=gap)
    write_json(ds / "splits.json", {"scene": str(SCENE), "block": block, "gap": gap, **splits})
    class_of_obj = {o.obj_id: o.class_id for o in structure.objects}
    for name, ids in splits.items():
        write_coco(ds / f"coco_{name}.json", coco_annotations(scene, ids, class_of_obj, structure.class_names,
                                                              partial(visible_masks, ds / SCENE)))
    return splits


def build_dataset(source: Path, cad: Path, out: Path, *, preset: str = "balanced", picks: Path | None = None,
                  gt: Path | None = None, cad_unit: str | None = None, calib: Path | None = None,
                  overwrite: bool = False, progress: Progress | None = None, executor: RayExecutor | None = None,
                  sfm_set: Mapping[str, Any] | None = None, topic: str | None = None,
                  hypothesis: int | None = None, verify: VerifyConfig | None = DEFAULT_VERIFY,
                  roi: Path | None = None, sfm_preset: str | None = None) -> Path:
    """Run frames -> SfM -> align -> render -> write; returns ``out``. See the module doc for the layout.

    ``calib``: the camera's known intrinsics and lens distortion, any format of
    :mod:`cadalign.formats.calibration` (``{"K": [...]}`` as 'cadalign sim' writes, a cameras.json, COLMAP
    cameras.txt, OpenCV YAML/XML, ROS CameraInfo YAML); its image size must be the frames'. SfM undistorts the
    frames once, maps self-calibrated, then sets and holds this calibration while it
    refines the model (``camera.known_intrinsics_from``), and the CAD-anchored camera refinement keeps it
    too. Without it the focal length is self-calibrated: on the default orbit it comes out ~0.8 % long,
    which moves every object ~4 cm in its camera frame; calibrate the ROV camera underwater and pass it.
    ``executor``: render the
    frames with Ray (:mod:`cadalign.build`); None renders them here. The dataset files are the same.
    ``sfm_preset``: the SfM preset when it differs from ``preset`` (which then names the alignment's only).
    ``sfm_set``: SfM settings over the preset's (nested keys of :class:`cadalign.sfm.SfMConfig`, e.g.
    ``{"mapper": {"repair_frames": 20}}``), checked strictly.
    ``topic``: the image topic when ``source`` is a ROS bag (None: the bag's only image topic).
    ``verify``: judge the alignment's hypotheses by the images (:mod:`cadalign.align.verify.core`) and refuse unless
    the outcome is ``ok``; None trusts the cloud gates alone. ``roi``: a region of interest file
    (:mod:`cadalign.align.roi`: a box in the SfM frame or clicks round the CAD in a few frames); the alignment
    then uses only the SfM points there (a CAD that is a small part of the scene). ``hypothesis``: the hypothesis
    a person chose from ``OUT/verify/hypotheses.png`` (the margin to the runner-up is then not required; the
    evidence still is).

    Raises:
        AlignmentError: the alignment failed its quality gate, or (``VerificationError``) the images do not
            confirm it (no dataset is written; ``OUT/verify/`` holds the evidence and the picture).
        InputError, ConfigError: unusable inputs, or ``out`` holds results of another config.
    """
    sfm_preset = sfm_preset or preset
    if preset not in ALIGN_PRESETS or sfm_preset not in SFM_PRESETS:
        raise ConfigError(f"unknown preset {preset if preset not in ALIGN_PRESETS else sfm_preset!r}; allowed "
                          f"values: {', '.join(SFM_PRESETS)}")
    out = Path(out)
    structure = load_structure(cad, cad_unit)
    seconds: dict[str, float] = {}
    sfm_cfg, sfm_dir = _sfm(sfm_preset, source, out, calib=calib, sfm_set=sfm_set, overwrite=overwrite,
                            progress=progress, topic=topic, seconds=seconds)
    align_json, cad_from_sfm, verification = _align_and_verify(
        preset, structure, sfm_dir, out, picks=picks, roi=roi, verify=verify, hypothesis=hypothesis,
        overwrite=overwrite, seconds=seconds)
    ds = out / "dataset"
    if overwrite and ds.exists():
        shutil.rmtree(ds)
    refine_cfg = DEFAULT_REFINE if calib is None else dataclasses.replace(DEFAULT_REFINE, intrinsics=False)
    # the pose used: the verification may choose another hypothesis and moves it to the image contours
    config = {"align": fingerprint(read_json(align_json)["cad_from_sfm"] if verification is None
                                   else cad_from_sfm.matrix().tolist()),
              "cad": str(Path(cad).resolve()),
              "depth_scale": DEPTH_SCALE, "camera_refine": refine_cfg, "seabed": DEFAULT_SEABED}
    prepare_stage_dir(ds, "build-dataset", config, overwrite=overwrite)
    t0 = time.perf_counter()
    cameras = read_json(sfm_dir / "cameras.json")["frames"]
    with colmap_log() as colmap_said:  # the CAD-anchored camera refinement is a COLMAP bundle adjustment
        frame_names, verified = render_frames(structure, cameras, cad_from_sfm, sfm_dir, ds / SCENE, progress,
                                              refine=refine_cfg, executor=executor)
    splits = write_dataset_extras(ds, structure, verified)
    write_record(ds, prep_of_frame_config(sfm_cfg.frames), source="sfm/images (the SfM stage's prepared frames)")
    seconds["render_and_write"] = time.perf_counter() - t0
    report = {
        "frames": len(frame_names), "frames_verified": int(sum(verified.values())),
        "frames_not_verified": [frame_names[k] for k, ok in verified.items() if not ok],
        "splits": {k: len(v) for k, v in splits.items()},
        "alignment": {k: v for k, v in read_json(align_json).items() if k in ("cad_from_sfm", "metrics", "gates")},
        "seconds": seconds, "sfm_report": read_json(sfm_dir / "sfm_report.json"),
        "colmap_log": colmap_said.to_json(),
    }
    _add_findings(report, ds, verification)
    if gt is not None:
        report["vs_truth"] = evaluate_against_sim(ds / SCENE, Path(gt), frame_names, cad_from_sfm, cameras,
                                                  structure, sfm_dir)
    write_json(out / "build_report.json", report)
    write_build_html(out, report)
    return out


def _sfm(preset: str, source: Path, out: Path, *, calib: Path | None, sfm_set: Mapping[str, Any] | None,
         overwrite: bool, progress: Progress | None, topic: str | None, seconds: dict[str, float]) -> tuple[Any, Path]:
    """SfM of ``source`` into ``OUT/sfm`` with the preset, the known calibration and the ``--sfm-set`` overrides:
    (the SfM config used, ``OUT/sfm``). Adds its seconds."""
    t0 = time.perf_counter()
    sfm_cfg = SFM_PRESETS[preset]
    if calib is not None:  # any --calib format; frames are undistorted by its lens distortion at extraction
        sfm_cfg = with_calibration(sfm_cfg, Path(calib), Path(source))
    if sfm_set:
        sfm_cfg = from_dict(SfMConfig, sfm_set, source="the SfM settings (--sfm-set)", base=sfm_cfg)
    sfm_dir = sfm_run(sfm_cfg, Path(source), out / "sfm", overwrite=overwrite, progress=progress, topic=topic)
    seconds["sfm"] = time.perf_counter() - t0
    return sfm_cfg, sfm_dir


def _align_and_verify(preset: str, structure: Structure, sfm_dir: Path, out: Path, *, picks: Path | None,
                      roi: Path | None, verify: VerifyConfig | None, hypothesis: int | None, overwrite: bool,
                      seconds: dict[str, float]) -> tuple[Path, Sim3, Any]:
    """The CAD aligned to the SfM cloud (``OUT/align``) and, unless ``verify`` is off, judged by the images
    (``OUT/verify``): (align.json, the ``cad_from_sfm`` used, the verification or None). Adds the steps' seconds."""
    t0 = time.perf_counter()
    parts = [(structure.models[o.obj_id], o.T_world_from_obj) for o in structure.objects]
    points: Path | np.ndarray = sfm_dir / "sparse" / "0"
    views = None
    if roi is not None:
        points, views = _roi_points(points, Path(roi), sfm_dir)
    align_json = align_run(ALIGN_PRESETS[preset], points, parts, out / "align", picks=picks, overwrite=overwrite,
                           views=views)
    seconds["align"] = time.perf_counter() - t0
    cad_from_sfm = read_sim3(align_json)
    verification = None
    if verify is not None and verify.enabled:
        t0 = time.perf_counter()
        verification = _verify(verify, structure, align_json, sfm_dir, out / "verify", hypothesis,
                               {"seconds": seconds, "sfm_report": read_json(sfm_dir / "sfm_report.json")})
        if verification.chosen != 0:  # the cloud gates judged hypothesis 0: judge the chosen one too
            _gate(ALIGN_PRESETS[preset], points, views, parts, verification.cad_from_sfm)
        cad_from_sfm = verification.cad_from_sfm
        seconds["verify"] = time.perf_counter() - t0
    return align_json, cad_from_sfm, verification


def _add_findings(report: dict[str, Any], ds: Path, verification: Any) -> None:
    """The verification's summary, the seabed and the edge alignment found, into the build report."""
    if verification is not None:
        report["verification"] = verification.summary()
    if (ds / "seabed.json").is_file():
        report["seabed"] = read_json(ds / "seabed.json")
    if (ds / "edge_align.json").is_file():
        report["edge_alignment"] = read_json(ds / "edge_align.json")["summary"]
