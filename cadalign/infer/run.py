"""``infer`` stage on disk: video/frames -> ``poses.jsonl``, ``overlay.mp4``, ``timings.json`` (+ ``eval.json``).

Outputs in ``out_dir``::

    poses.jsonl     one JSON object per reported instance and frame (see PoseRecord.to_json); empty when the
                    video shows no parts. With track completion (``complete.enabled``) it is written after a
                    second pass over the frames and holds the completed records (``source``: ``track``) too
    overlay.mp4     the frames with each part's CAD wireframe drawn at its reported pose (after completion, drawn
                    again in a last pass)
    frames.json     the names of the frames processed (readable ones), in order
    calibration.json  with ``--calib``: the camera read (file, format, K, size, distortion) and whether the frames
                    were undistorted (once, to the same K) before detection
    frame_stamps.json  {name: header stamp, ns} of those frames, only for a ROS bag input (capture times)
    timings.json    seconds per frame per stage (detector / pose / refinement / temporal / overlay; the completion
                    pass's share), frames/s
    eval.json, eval.md   with ground truth: detection P/R/F1, Table 4.5, BOP recalls, errors by distance,
                    for the detector's, the refined and the fused poses (the fused ones after completion)
    cadalign_stage.json  the resolved config (a different config in the same folder is refused)

A run stopped early (Ctrl-C, SIGTERM, a crash) resumes when the same command is run again
(:mod:`cadalign.infer.checkpoint`: ``poses.jsonl.partial``, ``overlay.partN.mp4``, ``infer_state.pkl`` meanwhile).
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from cadalign.cad.model import CadModel
from cadalign.errors import InputError
from cadalign.formats.bop import BopScene
from cadalign.formats.calibration import CameraCalibration, Undistorter, posed_frames, read_calibration
from cadalign.formats.class_map import load_class_map
from cadalign.formats.coco import rle_to_mask
from cadalign.fuse.predictors import depth_predictor
from cadalign.infer.checkpoint import POSES_PARTIAL, STATE, RunState, take_over
from cadalign.infer.complete import TrackCompleter
from cadalign.infer.config import InferConfig
from cadalign.infer.detect import Detector, frame_ids, models_dir_of
from cadalign.infer.model_geom import draw_wireframe
from cadalign.infer.pipeline import PosePipeline, PoseRecord
from cadalign.infer.video import (
    VideoFrame,
    count_frames,
    iter_frames,
    join_overlays,
    overlay_piece,
    overlay_pieces,
    video_writer,
)
from cadalign.io import atomic_path, prepare_stage_dir, read_json, stop_on_signals, write_json, write_text
from cadalign.metrics.pose_eval import (
    CroppedMask,
    PoseEvalConfig,
    PosePrediction,
    evaluate_scene,
    load_bop_models,
    table_markdown,
)
from cadalign.metrics.pose_symmetry import warn_undeclared
from cadalign.sfm import image_prep
from cadalign.types import Camera, Progress, Rigid3

log = logging.getLogger(__name__)
COLORS = ((255, 80, 80), (80, 255, 80), (80, 160, 255), (255, 220, 60), (255, 80, 255), (60, 255, 255))


@dataclass(frozen=True)
class Calibration:
    """Intrinsics per frame name (with a default for unlisted frames), when metric camera poses, and the lens
    (size, distortion) of a ``--calib`` file."""

    K_default: np.ndarray | None
    K_of: dict[str, np.ndarray]
    T_world_from_cam_of: dict[str, Rigid3]
    lens: CameraCalibration | None = None
    """The ``--calib`` file's camera: frames are checked against its size and undistorted by its distortion."""

    def K(self, name: str) -> np.ndarray:
        K = self.K_of.get(name, self.K_default)
        if K is None:
            raise InputError(f"no intrinsics for frame {name}: pass --calib cameras.json listing it")
        return K

    def frames(self, source: Path, max_frames: int | None, topic: str | None = None,
               stride: int = 1, after: int = -1) -> Iterator[VideoFrame]:
        """The frames of ``source`` as the pipeline sees them (every ``stride``-th): undistorted once by the lens
        distortion (to the same K), the first checked against the calibration's image size."""
        undistort = Undistorter.of(self.lens) if self.lens is not None else None
        for i, vf in enumerate(iter_frames(source, max_frames=max_frames, topic=topic, stride=stride, after=after)):
            if i == 0 and self.lens is not None:
                h, w = vf.image.shape[:2]
                self.lens.check_size(w, h, f"frame {vf.name} of {source}")
            yield replace(vf, image=undistort(vf.image)) if undistort is not None and undistort.active else vf


def load_calibration(path: Path, *, use_poses: bool = True) -> Calibration:
    """A ``--calib`` file in any format of :mod:`cadalign.formats.calibration`. A ``cameras.json`` (``cadalign
    sim`` / ``sfm`` / dataset format) also gives per-frame K and, when metric, camera poses."""
    lens = read_calibration(path)
    if lens.format != "cameras.json":
        return Calibration(lens.K, {}, {}, lens)
    data = read_json(path)
    frames = data.get("frames") or {}
    metric = data.get("units", "m") in ("m", "metres", "meters")
    if use_poses and not metric and frames:
        log.warning("%s is in %s units, not metres: its camera poses are not used (infer tracks the structure "
                    "itself; with --no-tracker the detections are fused by the filter)", path, data.get("units"))
    K_of = {n: np.reshape(np.asarray(f["K"], float), (3, 3)) for n, f in frames.items()}
    T_of = {}
    if use_poses and metric:
        T_of = {n: T.inverse() for n, T in posed_frames(data).items()}
    return Calibration(lens.K, K_of, T_of, lens)


def calibration_from_scene(scene_dir: Path, *, use_poses: bool = True) -> Calibration:
    """Intrinsics (and camera poses) of a BOP scene's ``scene_camera.json``, keyed by frame name."""

    scene = BopScene(scene_dir)
    K_of, T_of = {}, {}
    for name, im_id in frame_ids(scene_dir).items():
        fr = scene.frame(im_id)
        K_of[name] = fr.camera.K
        if use_poses and fr.T_cam_from_world is not None:
            T_of[name] = fr.T_cam_from_world.inverse()
    return Calibration(next(iter(K_of.values())) if K_of else None, K_of, T_of)


def is_depth_run(path: Path) -> bool:
    """Whether ``path`` names a trained network (a ``cadalign train depth`` run folder or its ``.pt``) rather
    than a scene with depth maps."""
    path = Path(path)
    return path.suffix == ".pt" or (path / "checkpoints").is_dir()


class _DepthSource:
    """Depth for ICP per frame: the depth maps of a BOP scene or simulation (``path`` a scene), or the metric depth
    a ``cadalign train depth`` network predicts from the frame (``path`` a run, :func:`is_depth_run`; fusion's
    :func:`~cadalign.fuse.predictors.depth_predictor`).

    A network gets the raw frame prepared as its own training images were when the frames are raw
    (``raw_frames``: ``enhance = "auto"``), else the frame as the detector gets it."""

    def __init__(self, path: Path | None, *, raw_frames: bool = True, device: str = "cpu") -> None:
        self.scene, self.ids, self.predict, self.raw_frames = None, {}, None, raw_frames
        if path is not None and is_depth_run(path):
            self.predict = depth_predictor(Path(path), device=device,
                                           source_prep=dict(image_prep.RAW) if raw_frames else None)
        elif path is not None:
            self.scene, self.ids = BopScene(path), frame_ids(path)

    @property
    def predicted(self) -> bool:
        """Whether the depth comes from a network (a stage of its own) rather than from depth maps."""
        return self.predict is not None

    def get(self, name: str, raw: np.ndarray, prepared: np.ndarray, K: np.ndarray) -> np.ndarray | None:
        """(H, W) depth in metres of frame ``name`` (``raw`` as read, ``prepared`` as the detector sees it)."""
        if self.predict is not None:
            rgb = raw if self.raw_frames else prepared
            return np.asarray(self.predict(rgb, Camera(K, rgb.shape[1], rgb.shape[0])), dtype=np.float64)
        if self.scene is None or name not in self.ids:
            return None
        return self.scene.depth_m(self.ids[name])


def _draw(image: np.ndarray, records: list[PoseRecord], pipeline: PosePipeline, K: np.ndarray) -> np.ndarray:
    img = image.copy()
    for r in records:
        if r.obj_id is None:
            continue
        color = COLORS[r.label % len(COLORS)]
        draw_wireframe(img, pipeline.geometry(r.obj_id), r.T_cam_from_obj, K, color)
        x0, y0 = int(r.box_xyxy[0]), int(r.box_xyxy[1])
        tag = " track" if r.source == "track" else ""
        cv2.putText(img, f"{r.class_name} #{r.track_id} {r.score:.2f}{tag}", (x0, max(y0 - 3, 10)),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.35, color, 1, cv2.LINE_AA)
    return img


def _infer_frame(pipeline: PosePipeline, vf: Any, K: np.ndarray, prep: dict[str, Any], depth: _DepthSource,
                 calib: Calibration) -> tuple[list[PoseRecord], dict[str, float]]:
    """One frame through the pipeline: its poses and its timings (with ``depth_net`` when depth is predicted, and
    ``pipeline_cpu``, the process time, which a busy machine inflates less than the wall times)."""
    cpu0 = time.process_time()
    prepared = image_prep.apply(vf.image, prep)
    t0, c0 = time.perf_counter(), time.process_time()
    d_m = depth.get(vf.name, vf.image, prepared, K)
    t_depth, c_depth = time.perf_counter() - t0, time.process_time() - c0
    records, t = pipeline.process(vf.index, vf.name, prepared, K, d_m, calib.T_world_from_cam_of.get(vf.name))
    if depth.predicted:  # a depth network is a stage; reading a scene's depth map is not
        t["depth_net"] = t_depth
    # wall times above inflate on a busy machine
    t["pipeline_cpu"] = time.process_time() - cpu0 - (0.0 if depth.predicted else c_depth)
    return records, t


def _write_run_files(out_dir: Path, names: list[str], calib: Calibration, stamps: dict[str, int],
                     timings: dict[str, Any]) -> None:
    """frames.json, calibration.json (an undistorted lens), frame_stamps.json (a bag's) and timings.json."""
    write_json(out_dir / "frames.json", names)
    if calib.lens is not None:
        write_json(out_dir / "calibration.json", {**calib.lens.record(), "undistorted": calib.lens.distorted})
    if stamps:
        write_json(out_dir / "frame_stamps.json", stamps)
    write_json(out_dir / "timings.json", timings)


def run(cfg: InferConfig, source: Path, detector: Detector, models: dict[int, CadModel], class_names: tuple[str, ...],
        out_dir: Path, *, calib: Calibration, detector_info: dict, depth_scene: Path | None = None,
        gt_scene: Path | None = None, max_frames: int | None = None, overwrite: bool = False,
        progress: Progress | None = None, device: str = "cpu", topic: str | None = None, stride: int = 1,
        checkpoint_every: int = 25) -> Path:
    """Run the pose pipeline over a video or frame folder (every ``stride``-th frame); returns ``out_dir /
    "poses.jsonl"`` (see module doc). A run stopped early resumes (:mod:`cadalign.infer.checkpoint`): its state is
    saved every ``checkpoint_every`` frames and when SIGINT / SIGTERM stops it.

    ``depth_scene``: depth for ICP, a scene with depth maps or a ``cadalign train depth`` run (its predicted
    depth, on ``device``; :class:`_DepthSource`)."""
    out_dir = Path(out_dir)
    prep = resolve_prep(cfg.enhance, detector_info)
    detector_info = {**detector_info, "images": prep}
    record = {"infer": cfg, "source": str(source) if topic is None else f"{source} {topic}",
              "detector": detector_info, "max_frames": max_frames, **({"stride": stride} if stride != 1 else {}),
              "depth": None if depth_scene is None else str(depth_scene),
              "gt": None if gt_scene is None else str(gt_scene)}
    poses_path = out_dir / "poses.jsonl"
    same = prepare_stage_dir(out_dir, "infer", record, overwrite=overwrite)
    if same and (out_dir / "timings.json").is_file():
        log.info("infer: %s is complete for this config; reusing it", poses_path)
        return poses_path
    (out_dir / "timings.json").unlink(missing_ok=True)  # this run's mark of completion, not an older run's
    state = take_over(out_dir, same)
    pipeline = PosePipeline(detector, models, class_names, cfg)
    state.restore(pipeline)
    depth = _DepthSource(depth_scene, raw_frames=cfg.enhance == "auto", device=device)
    keep_masks = gt_scene is not None or cfg.complete.enabled
    if state.names:  # the finished frames' records, as the evaluation and the completion keep them
        state.records = [r if keep_masks else replace(r, mask=None) for r in read_poses(out_dir / POSES_PARTIAL)]
    left = None if max_frames is None else max(max_frames - len(state.names), 0)
    frames = calib.frames(source, left, topic, stride, after=state.last_index)
    total = count_frames(source, stride=stride, max_frames=left, topic=topic, after=state.last_index) \
        if progress else None
    _detect(cfg, pipeline, state, progress(frames, "infer", total) if progress else frames, calib, prep, depth,
            out_dir, keep_masks, checkpoint_every)
    final, times, names = state.records, state.times, state.names
    redrawn = False
    if cfg.complete.enabled:
        t0 = time.perf_counter()
        final, summary = _complete(cfg, pipeline, state.records, source, calib, depth, prep, max_frames, progress,
                                   topic, stride)
        times["complete"] = [time.perf_counter() - t0]
        if summary is not None:
            with atomic_path(poses_path) as tmp, open(tmp, "w", encoding="utf-8") as fh:
                for r in final:
                    mask = r.mask.full(state.shapes[r.frame_name]) if isinstance(r.mask, CroppedMask) else r.mask
                    fh.write(json.dumps(replace(r, mask=mask).to_json()) + "\n")
            (out_dir / POSES_PARTIAL).unlink()
            if cfg.overlay and overlay_pieces(out_dir):
                with atomic_path(out_dir / "overlay.mp4") as tmp:
                    _redraw_overlay(tmp, cfg, final, pipeline, source, calib, max_frames, topic, stride)
                redrawn = True
    if (out_dir / POSES_PARTIAL).is_file():
        os.replace(out_dir / POSES_PARTIAL, poses_path)
    if redrawn:
        for piece in overlay_pieces(out_dir):
            piece.unlink()
    else:
        join_overlays(overlay_pieces(out_dir), out_dir / "overlay.mp4", cfg.overlay_fps)
    _write_run_files(out_dir, names, calib, state.stamps,
                     _timing_summary(times, len(names), len(final), detector_info))
    (out_dir / STATE).unlink(missing_ok=True)
    log.info("infer: %d frames, %d poses -> %s", len(names), len(final), poses_path)
    if gt_scene is not None:
        evaluate_run(state.records, names, gt_scene, out_dir, fused=final)
    return poses_path


def _detect(cfg: InferConfig, pipeline: PosePipeline, state: RunState, frames: Iterable[VideoFrame],
            calib: Calibration, prep: dict[str, Any], depth: _DepthSource, out_dir: Path, keep_masks: bool,
            checkpoint_every: int) -> None:
    """The pipeline over ``frames``, each frame's poses appended to ``poses.jsonl.partial`` and its picture to the
    overlay's current piece; ``state`` is saved every ``checkpoint_every`` frames and when a signal stops the run
    between frames (which then raises KeyboardInterrupt)."""
    writer = None
    with stop_on_signals() as flag, open(out_dir / POSES_PARTIAL, "a", encoding="utf-8") as fh:
        try:
            for vf in frames:
                K = calib.K(vf.name)
                records, t = _infer_frame(pipeline, vf, K, prep, depth, calib)
                fh.write("".join(json.dumps(r.to_json()) + "\n" for r in records))
                fh.flush()
                if cfg.overlay:
                    t0 = time.perf_counter()
                    writer = writer or video_writer(overlay_piece(out_dir, state.pieces), cfg.overlay_fps)
                    writer.append_data(_draw(vf.image, records, pipeline, K))
                    t["overlay"] = time.perf_counter() - t0
                for k, v in t.items():
                    state.times.setdefault(k, []).append(v)
                # kept for the evaluation and completion: masks only with either, and cropped to their box
                state.records.extend(replace(r, mask=CroppedMask.of(r.mask) if keep_masks and r.mask is not None
                                             else None) for r in records)
                state.names.append(vf.name)
                if vf.stamp_ns is not None:
                    state.stamps[vf.name] = vf.stamp_ns
                state.shapes[vf.name] = vf.image.shape[:2]
                state.last_index, state.poses_lines = vf.index, state.poses_lines + len(records)
                if flag["stop"] or len(state.names) % checkpoint_every == 0:
                    if writer is not None:  # the piece ends with the checkpoint: a resumed run adds the next one
                        writer.close()
                        writer, state.pieces = None, state.pieces + 1
                    state.save(out_dir, pipeline)
                if flag["stop"]:
                    raise KeyboardInterrupt(f"stopped after frame {vf.name}, its work kept in {out_dir}; re-run the "
                                            "same command to resume")
        finally:
            if writer is not None:
                writer.close()


def _redraw_overlay(path: Path, cfg: InferConfig, records: list[PoseRecord], pipeline: PosePipeline, source: Path,
                    calib: Calibration, max_frames: int | None, topic: str | None, stride: int = 1) -> None:
    """The overlay video again, from the records after completion (a completed part's label says ``track``)."""
    by_frame: dict[str, list[PoseRecord]] = {}
    for r in records:
        by_frame.setdefault(r.frame_name, []).append(r)
    writer = video_writer(path, cfg.overlay_fps)
    try:
        for vf in calib.frames(source, max_frames, topic, stride):
            writer.append_data(_draw(vf.image, by_frame.get(vf.name, []), pipeline, calib.K(vf.name)))
    finally:
        writer.close()


def _complete(cfg: InferConfig, pipeline: PosePipeline, records: list[PoseRecord], source: Path, calib: Calibration,
              depth: _DepthSource, prep: dict, max_frames: int | None, progress: Progress | None,
              topic: str | None, stride: int = 1) -> tuple[list[PoseRecord], dict | None]:
    """The completion pass (:mod:`cadalign.infer.complete`) over the frames again: the records it reports and its
    summary; the records unchanged and None without depth."""
    cameras = pipeline.fuser.cameras  # frame -> (world, T_world_from_cam): given, or registered on the parts
    if depth.scene is None and not depth.predicted:
        log.warning("infer: track completion needs depth (--depth) to tell which parts are in sight; the records "
                    "stay as detected")
        return records, None
    completer = TrackCompleter(cfg.complete, pipeline.world_tracks(), records, pipeline.geometry)
    if completer.tracks:
        frames = calib.frames(source, max_frames, topic, stride)
        total = count_frames(source, stride=stride, max_frames=max_frames, topic=topic) if progress else None
        for vf in progress(frames, "complete", total) if progress else frames:
            if vf.index not in cameras:
                continue
            world, T_wc = cameras[vf.index]
            K = calib.K(vf.name)
            prepared = image_prep.apply(vf.image, prep) if depth.predicted else vf.image
            completer.frame(vf.index, vf.name, K, T_wc, depth.get(vf.name, vf.image, prepared, K), world)
    final, summary = completer.result()
    log.info("infer: track completion: %d tracks, %d not trusted, added %s, dropped %d detections of short tracks",
             summary["tracks"], summary["untrusted"], summary["added"] or "nothing", summary["dropped"])
    return final, summary


def resolve_prep(enhance: str, detector_info: dict) -> dict:
    """The preparation each raw frame gets before detection (``InferConfig.enhance``).

    ``"auto"``: as the network's training images were prepared, from its run's ``train_config.json``
    (``images``, recorded by ``cadalign train``), else from the dataset the run names; an oracle detector, or a
    run that says nothing (a warning), gets the raw frames. Any other value is used as it is.
    """
    if enhance != "auto":
        return image_prep.prep_named(enhance)
    if detector_info.get("kind") != "network":
        return dict(image_prep.RAW)
    prep = image_prep.read_run_prep(Path(detector_info["run"]))
    if prep is None:
        log.warning("infer: %s does not record how its training images were prepared; frames are fed raw. If the "
                    "network was trained on a built dataset (CLAHE-enhanced by SfM), set enhance = 'clahe'",
                    detector_info["run"])
        return dict(image_prep.RAW)
    return prep


def _timing_summary(times: dict[str, list[float]], n_frames: int, n_poses: int, detector_info: dict) -> dict:
    per_stage = {k: {"mean_ms": 1e3 * float(np.mean(v)), "median_ms": 1e3 * float(np.median(v)),
                     "total_s": float(np.sum(v))} for k, v in times.items()}
    core = [k for k in ("depth_net", "detector", "identify", "refinement", "temporal") if k in times]  # wall clock
    per_frame = np.sum([times[k] for k in core], axis=0) if core and n_frames else np.zeros(0)

    def ms(key: str) -> float:
        return 1e3 * float(np.mean(times[key])) if times.get(key) else 0.0

    # the three stages: the network without its pose head, pose (head + CAD model identification),
    # refinement against the CAD
    head = ms("detector.pose")
    summary = {"detector": ms("detector") - head, "pose": head + ms("identify"), "refinement": ms("refinement")}
    if "depth_net" in times:
        summary["depth_net"] = ms("depth_net")
    # the completion pass runs once after the video: its share per frame
    complete = float(np.sum(times.get("complete", []))) / n_frames if n_frames else 0.0
    if "complete" in times:
        summary["complete"] = 1e3 * complete
    mean = float(per_frame.mean()) + complete if len(per_frame) else 0.0
    return {"detector": detector_info, "frames": n_frames, "poses": n_poses, "stages": per_stage,
            "stages_ms": summary,
            "pipeline_ms_per_frame": 1e3 * mean if len(per_frame) else None,
            "pipeline_fps": 1.0 / mean if len(per_frame) and mean > 0 else None,
            "note": "stages_ms: detector (network without its pose head), pose (pose head + CAD model "
                    "identification), refinement (and depth_net, a depth network's prediction; complete, the "
                    "track completion pass's time over the frames); pipeline = depth_net + detector + identify + "
                    "refinement + temporal (+ complete), wall clock; pipeline_cpu = process CPU time of the "
                    "per-frame stages; overlay apart"}


def evaluate_run(records: list[PoseRecord], names: list[str], gt_scene: Path, out_dir: Path | None,
                 eval_cfg: PoseEvalConfig | None = None, fused: list[PoseRecord] | None = None) -> dict:
    """Evaluate the detector's, the refined and the fused poses against a BOP scene (eval.json/eval.md).

    ``fused``: the records the fused section scores (after track completion), ``records`` by default; the other
    sections score ``records`` (the detections). ``eval_cfg`` defaults to
    :class:`~cadalign.metrics.pose_eval.PoseEvalConfig` () (BOP's rules)."""

    cmap = load_class_map(gt_scene)
    ids = frame_ids(gt_scene)
    label_of = {n: i for i, n in enumerate(cmap.names)}  # by class name: the detector's list may differ
    models = load_bop_models(models_dir_of(gt_scene))
    cfg = eval_cfg or PoseEvalConfig()
    targets = {k: m for k, m in models.items()  # only pose targets: the structure's symmetries count for nothing
               if cmap.names[cmap.class_of_obj.get(k, 0)] not in cfg.ignore_classes}
    undeclared = warn_undeclared({k: (m.points_m, m.diameter_m, m.symmetry) for k, m in targets.items()})
    im_ids = [ids[n] for n in names if n in ids]
    if not im_ids:
        raise InputError(f"none of the {len(names)} frames is in the ground truth {gt_scene} (names like "
                         f"{names[:2]}); pass the simulation the video came from")
    reports, md = {}, []
    for which, attr in (("detector", "T_detector"), ("refined", "T_refined"), ("fused", "T_cam_from_obj")):
        recs = fused if which == "fused" and fused is not None else records
        preds = [PosePrediction(ids[r.frame_name], label_of.get(r.class_name, -1), r.score, r.box_xyxy,
                                getattr(r, attr), r.obj_id, r.mask) for r in recs if r.frame_name in ids]
        rep = evaluate_scene(preds, gt_scene, models, cmap.names, cmap.class_of_obj, cfg, im_ids)
        if which != "fused":
            rep.pop("matches")
            rep.pop("misses")
        rep["config"]["undeclared_symmetries"] = {str(k): v for k, v in undeclared.items()}
        reports[which] = rep
        md.append(f"## {which} poses\n\n" + table_markdown(rep))
    if undeclared:
        md.append("Models invariant to turns they do not declare (errors of those turns are counted): "
                  + "; ".join(f"obj {k}: {', '.join(v)}" for k, v in undeclared.items()) + "\n")
    if out_dir is not None:
        write_json(out_dir / "eval.json", reports)
        write_text(out_dir / "eval.md", "\n".join(md))
    return reports


def read_poses(path: Path) -> list[PoseRecord]:
    """The records of a ``poses.jsonl`` (masks decoded when stored)."""

    out = []
    for i, line in enumerate(Path(path).read_text(encoding="utf-8").splitlines()):
        if not line.strip():
            continue
        try:
            d = json.loads(line)
            out.append(PoseRecord(
                int(d["frame"]), str(d["frame_name"]), d.get("obj_id"), int(d.get("track_id", -1)), int(d["label"]),
                str(d["class"]), float(d["score"]), np.asarray(d["box_xyxy"], float),
                Rigid3.from_matrix(np.asarray(d["T_cam_from_obj"])),
                Rigid3.from_matrix(np.asarray(d.get("T_cam_from_obj_detector", d["T_cam_from_obj"]))),
                Rigid3.from_matrix(np.asarray(d.get("T_cam_from_obj_refined", d["T_cam_from_obj"]))),
                dict(d.get("refine_iters") or {}),
                CroppedMask.of(rle_to_mask(d["mask_rle"])) if d.get("mask_rle") else None,
                str(d.get("source", "detector")),
                None if d.get("box_xyxy_detector") is None else np.asarray(d["box_xyxy_detector"], float)))
        except (KeyError, ValueError, TypeError) as exc:
            raise InputError(f"{path}, line {i + 1}: not a cadalign pose record ({exc})") from exc
    return out
