"""``infer`` with the structure tracker on disk: RGB video + CAD + intrinsics -> per-frame part poses.

Outputs in ``out_dir`` (the layout of :mod:`cadalign.infer.run`, so ``eval`` and the report read both)::

    poses.jsonl     one record per reported part and tracked frame (``source``: ``tracked``); nothing for a
                    frame while the track is lost, nor for a part whose contours find no support (missing)
    track.jsonl     one line per frame: state (ok / lost), T_cam_from_world, edge support, residual, restart,
                    and per part its contour and colour support and what the image shows of the structure's
                    contours it hides (``part_hidden``: samples, share seen, deep samples, deep share seen);
                    on a lost frame the best-supported fit tried and the test that refused it (``closest_fit``)
    overlay.mp4     the frames with the tracked CAD's contours (green: an image edge supports them, red: none)
                    and the state
    track.png       the run at a glance: support per frame, lost frames, restarts, and each part reported or
                    missing per frame (:mod:`~cadalign.infer.track.plot`)
    frames.json     the frame names processed
    timings.json    ms per frame: tracking, restarts, overlay; frames/s
    eval.json, eval.md   with ground truth (--gt): as for the detector pipeline; every section scores the
                    tracked poses

While it runs, each finished frame is appended at once to ``poses.jsonl.partial`` and ``track.jsonl.partial`` (and
its overlay picture to ``overlay.partN.mp4``). A run stopped by Ctrl-C, a crash or a kill keeps every finished frame;
the same command resumes after the last one, the track restarting from that frame's pose, and the files are
renamed to their final names when the video ends.
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from cadalign.errors import InputError
from cadalign.formats.calibration import CameraCalibration, Undistorter
from cadalign.infer.pipeline import PoseRecord
from cadalign.infer.run import evaluate_run
from cadalign.infer.track.config import TrackerConfig, TrackRunConfig
from cadalign.infer.track.edges import as_gray
from cadalign.infer.track.hidden import HiddenContours, HiddenSeen
from cadalign.infer.track.missing import PartMemory, part_records
from cadalign.infer.track.partial import PARTIAL, Finished, take_over
from cadalign.infer.track.parts import MovableParts, mask_box, split_hypotheses
from cadalign.infer.track.plot import plot_track
from cadalign.infer.track.start import pose_from_picks
from cadalign.infer.track.tracker import StructureTracker, TrackStep
from cadalign.infer.video import VideoFrame, count_frames, iter_frames, join_overlays, overlay_piece, video_writer
from cadalign.io import fingerprint, prepare_stage_dir, read_json, read_jsonl, stop_on_signals, write_json
from cadalign.sim.structure import Structure
from cadalign.types import Camera, Progress, Rigid3

log = logging.getLogger(__name__)


def read_init_pose(path: Path, camera: Camera | None = None) -> Rigid3:
    """``T_cam_from_world`` of the first frame from a JSON file: either ``{"T_cam_from_world": 4x4 nested list}``
    (metres; a navigation pose good to ~0.5 m / 10 deg serves) or points picked in the first frame,
    ``{"picks": [{"uv": [column, row], "xyz": [x, y, z]}, ...]}`` (pixels as an image viewer shows them, the
    CAD point in the scene frame in metres; at least 4, see :func:`~cadalign.infer.track.start.pose_from_picks`,
    which needs ``camera``)."""
    try:
        data = read_json(path)
        if isinstance(data, dict) and "picks" in data:
            if camera is None:
                raise ValueError("picked points need the camera's intrinsics")
            picks = data["picks"]
            T, rms = pose_from_picks(np.array([p["uv"] for p in picks], dtype=np.float64),
                                     np.array([p["xyz"] for p in picks], dtype=np.float64), camera)
            log.info("%s: first-frame pose from %d picked points, %.2f px RMS", path, len(picks), rms)
            return T
        M = np.asarray(data["T_cam_from_world"], dtype=np.float64)
        if M.shape != (4, 4):
            raise ValueError(f"shape {M.shape}, expected (4, 4)")
        return Rigid3.from_matrix(M)
    except (KeyError, ValueError, TypeError) as exc:
        raise InputError(f"{path}: not an initial pose ({exc}); write {{\"T_cam_from_world\": [[r00, r01, r02, tx], "
                         f"..., [0, 0, 0, 1]]}} in metres, the structure (scene) frame in the first camera, or "
                         f"{{\"picks\": [{{\"uv\": [col, row], \"xyz\": [x, y, z]}}, ...]}}: at least 4 points of "
                         "the first frame and where they are on the CAD (metres)") from exc


def _draw(image: np.ndarray, step: TrackStep, parts: dict[int, TrackStep] | None = None) -> np.ndarray:
    """The frame with the tracked contours (green: supported by an image edge, red: not; movable parts cyan and
    magenta) and the track state."""
    img = image.copy()
    f = step.fit
    drawn = [(step, (60, 255, 60), (255, 60, 60))]
    drawn += [(s, (60, 230, 255), (255, 60, 255)) for s in (parts or {}).values()]
    for s, on, off in drawn:
        g = s.fit
        if s.state == "ok" and g is not None and g.uv is not None and len(g.uv):
            p = np.round(g.uv).astype(int)
            okp = (p[:, 0] >= 0) & (p[:, 0] < img.shape[1]) & (p[:, 1] >= 0) & (p[:, 1] < img.shape[0])
            sup = g.supported
            img[p[okp & sup, 1], p[okp & sup, 0]] = on
            img[p[okp & ~sup, 1], p[okp & ~sup, 0]] = off
    text = (f"ok ({step.source}) support {f.support:.2f} residual {f.residual_px:.2f} px" if step.state == "ok"
            and f is not None else "LOST: no pose reported")
    cv2.putText(img, text, (8, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255) if step.state == "ok"
                else (255, 80, 80), 1, cv2.LINE_AA)
    return img


def track_video(cfg: TrackRunConfig, source: Path, structure: Structure, camera: Camera, out_dir: Path, *,
                init_pose: Rigid3 | None = None, restart_source: Callable[[np.ndarray, str], list] | None = None,
                gt_scene: Path | None = None, max_frames: int | None = None, overwrite: bool = False,
                progress: Progress | None = None, record: dict | None = None,
                lens: CameraCalibration | None = None, topic: str | None = None,
                nav: dict[str, Rigid3] | None = None, stride: int = 1) -> Path:
    """Track the structure through a video or frame folder; returns ``out_dir / "poses.jsonl"`` (module doc).

    ``init_pose``: ``T_cam_from_world`` of the first frame (rough). ``restart_source(image, name)``: restart
    hypotheses (name, ``T_cam_from_world``) for a frame without a track (e.g. from a detector); at least one of
    the two is needed. ``lens``: the calibration read from the user's file; a lens distortion in it is undone
    on every frame before tracking (``camera`` is then its pinhole part). ``nav``: rough ``T_cam_from_world`` by
    frame name: each bounds its frame's pose and restarts a lost track (``StructureTracker.step``). ``stride``: track
    every ``stride``-th frame (the frames keep their names, so navigation poses still match). An interrupted
    run resumes after its last finished frame, from that frame's pose (:data:`PARTIAL`)."""
    if init_pose is None and restart_source is None and not nav:
        raise InputError("the tracker needs a start: pass --init-pose FILE (a rough first-frame pose), --nav FILE "
                         "(rough poses per frame) or --model RUN (a trained detector)")
    out_dir = Path(out_dir)
    rec = {"track": cfg, "source": str(source), "topic": topic, "max_frames": max_frames, "camera": camera.K.tolist(),
           **({"stride": stride} if stride != 1 else {}),
           **_start_record(lens, init_pose, nav), **(record or {})}
    poses_path = out_dir / "poses.jsonl"
    same = prepare_stage_dir(out_dir, "infer", rec, overwrite=overwrite)
    if same and (out_dir / "timings.json").is_file():
        log.info("infer: %s is complete for this config; reusing it", poses_path)
        return poses_path
    if not same:  # a new run: an interrupted one must not look complete through an older run's timings
        (out_dir / "timings.json").unlink(missing_ok=True)
    done = take_over(out_dir, same)
    if done.rows:
        log.info("infer: resuming %s after frame %s (%d frames finished before)", out_dir, done.rows[-1]["frame_name"],
                 len(done.rows))
    run = _VideoRun(cfg, structure, camera, out_dir, init_pose, restart_source, nav, done)
    left = None if max_frames is None else max(max_frames - len(done.rows), 0)
    after = done.rows[-1]["frame"] if done.rows else -1
    frames = iter_frames(source, stride=stride, max_frames=left, topic=topic, after=after)
    total = count_frames(source, stride=stride, max_frames=left, topic=topic, after=after) if progress else None
    run.track(progress(frames, "track", total) if progress else frames, source,
              Undistorter.of(lens) if lens is not None else None)
    rows = read_jsonl(out_dir / f"track.jsonl{PARTIAL}")
    write_json(out_dir / "frames.json", [r["frame_name"] for r in rows])
    write_json(out_dir / "timings.json", _timings(rows, run.overlay_s))
    join_overlays([*done.overlays, *([run.overlay] if run.overlay else [])], out_dir / "overlay.mp4",
                   cfg.overlay_fps)
    for name in ("track.jsonl", "poses.jsonl"):
        os.replace(out_dir / f"{name}{PARTIAL}", out_dir / name)
    _log_end(out_dir / "track.jsonl", rows, cfg.tracker, len(run.records))
    names = [o.name for o in structure.objects]
    reported: dict[int, set[str]] = {}
    for r in run.records:
        reported.setdefault(r.frame, set()).add(names[r.track_id - 1])
    plot_track(out_dir / "track.png", rows, reported, names, cfg.tracker.min_support)
    if gt_scene is not None:
        evaluate_run(run.records, [r["frame_name"] for r in rows], gt_scene, out_dir)
    return poses_path


class _VideoRun:
    """One run of the tracker over frames, writing each finished frame at once (``track_video``)."""

    def __init__(self, cfg: TrackRunConfig, structure: Structure, camera: Camera, out_dir: Path,
                 init_pose: Rigid3 | None, restart_source: Callable[[np.ndarray, str], list] | None,
                 nav: dict[str, Rigid3] | None, done: Finished) -> None:
        self.cfg, self.structure, self.camera, self.out_dir = cfg, structure, camera, out_dir
        self.restart_source, self.nav = restart_source, nav
        self.first = not done.rows
        self.work = working_camera(camera, cfg.max_width)
        camera = self.work  # what the tracker sees
        self.tracker = StructureTracker(structure.render_meshes(), camera, cfg.tracker)  # the rigid assembly
        self.resumed = done.resume(self.tracker)
        self.start = [("init_pose", init_pose)] if init_pose is not None and not self.resumed else []
        self.parts = MovableParts(structure, camera, cfg.movable)
        self.memory, self.behind = PartMemory(), HiddenContours(structure, camera)  # the missing-part checks
        for row in [r for r in done.rows if r["state"] == "ok"][-1:]:
            self.memory.take_over(row, structure)  # the parts' verdicts at the last tracked frame
        self.records: list[PoseRecord] = list(done.records)
        self.overlay = overlay_piece(out_dir, len(done.overlays)) if cfg.overlay else None
        self.overlay_s: list[float] = []

    def track(self, frames: Iterable[VideoFrame], source: Path, undistort: Undistorter | None) -> None:
        """Track ``frames``, appending each to the partial files; SIGINT / SIGTERM stop the run once the frame at
        hand is written (a KeyboardInterrupt raised elsewhere, off the main thread, loses only that frame)."""
        writer = None
        try:
            with stop_on_signals() as flag, open(self.out_dir / f"poses.jsonl{PARTIAL}", "a", encoding="utf-8") as fh, \
                    open(self.out_dir / f"track.jsonl{PARTIAL}", "a", encoding="utf-8") as th:
                for vf in frames:
                    if vf.image.shape[:2] != (self.camera.height, self.camera.width):
                        raise InputError(f"{source}: frame {vf.name} is {vf.image.shape[1]}x{vf.image.shape[0]} but "
                                         f"the calibration is {self.camera.width}x{self.camera.height}; pass the "
                                         "calibration of this video")
                    image = undistort(vf.image) if undistort is not None else vf.image
                    recs, row, drawn = self._frame(vf, image, source)
                    recs = [in_frame_pixels(r, self.work, self.camera) for r in recs]
                    fh.write("".join(json.dumps(r.to_json()) + "\n" for r in recs))
                    fh.flush()  # the poses before the frame's track line: a line there means its poses are written
                    th.write(json.dumps(row) + "\n")
                    th.flush()
                    self.records.extend(recs)
                    if drawn is not None:
                        t0 = time.perf_counter()
                        writer = writer or video_writer(self.overlay, self.cfg.overlay_fps)
                        writer.append_data(drawn)
                        self.overlay_s.append(time.perf_counter() - t0)
                    if flag["stop"]:  # SIGINT / SIGTERM: stop between frames, the overlay closed whole
                        raise KeyboardInterrupt(f"stopped after frame {vf.name}, its work kept in {self.out_dir}; "
                                                "re-run the same command to resume")
        finally:
            if writer is not None:
                writer.close()  # a whole video even when interrupted
            elif self.overlay is not None:
                self.overlay = None

    def _frame(self, vf: VideoFrame, image: np.ndarray, source: Path,
               ) -> tuple[list[PoseRecord], dict, np.ndarray | None]:
        """One frame (``image``: undistorted, the frame's size): its part records, its ``track.jsonl`` line and its
        overlay picture (None: no overlay)."""
        cfg, tracker = self.cfg, self.tracker
        restarts: list[tuple[str, Rigid3]] = list(self.start) if tracker.last_pose is None else []  # until it starts
        part_hyps: dict[str, list] = {}
        detector_ms = None
        if self.restart_source is not None and (tracker.lost or self.parts.lost):
            t0 = time.perf_counter()  # the detector sees the frame at its own size (its camera's)
            rigid, part_hyps = split_hypotheses(list(self.restart_source(image, vf.name)), self.structure)
            restarts += rigid if tracker.lost else []
            detector_ms = round(1e3 * (time.perf_counter() - t0), 2)
        if self.work.width != self.camera.width:
            image = cv2.resize(image, (self.work.width, self.work.height), interpolation=cv2.INTER_AREA)
        rgb = image[..., :3] if image.ndim == 3 else None
        gray = as_gray(image, cfg.tracker.edges.colour)
        step = tracker.step(gray, restarts, rgb, _nav_pose(self.nav, vf.name, self.first, source))
        self.first = False
        part_steps = self.parts.step(gray, rgb, step.T_cam_from_world, part_hyps)
        hidden = self.behind.seen(gray, step, cfg.tracker.edges.support_px, cfg.tracker.edges.min_contrast)
        recs, missing = part_records(step, vf.index, vf.name, self.structure, cfg, self.memory, hidden)
        recs += self.parts.records(part_steps, vf.index, vf.name, cfg.min_visible_px)
        row = {**_step_json(step, vf.name, missing, self.structure, hidden), "frame": vf.index,  # the video's
               **({"movable": self.parts.summary(part_steps)} if part_steps else {}),
               **({} if detector_ms is None else {"detector_ms": detector_ms}),
               **({"resumed": True} if self.resumed else {})}
        self.resumed = False  # only the first frame after a resume says so
        return recs, row, _draw(image, step, part_steps) if cfg.overlay else None


def working_camera(camera: Camera, max_width: int) -> Camera:
    """The camera the tracker works with: ``camera``, or the same scaled to ``max_width`` when it is wider."""
    if max_width <= 0 or camera.width <= max_width:
        return camera
    return camera.scaled(max_width, max(int(round(camera.height * max_width / camera.width)), 1))


def in_frame_pixels(rec: PoseRecord, work: Camera, camera: Camera) -> PoseRecord:
    """A record made at the working size with its mask and box in the frame's pixels."""
    if work.width == camera.width or rec.mask is None:
        return rec
    mask = cv2.resize(np.asarray(rec.mask, dtype=np.uint8), (camera.width, camera.height),
                      interpolation=cv2.INTER_NEAREST) > 0
    return replace(rec, mask=mask, box_xyxy=mask_box(mask)) if mask.any() else rec


def _log_end(track_path: Path, rows: list[dict], cfg: TrackerConfig, n_records: int) -> list[int]:
    """Log what was tracked (``rows``: the run's ``track_path``), and warn when frames were lost only because their
    fit was too far from the navigation pose (the navigation may be in another frame, or rougher than the bounds);
    returns those frames."""
    ok = sum(r["state"] == "ok" for r in rows)
    log.info("track: %d frames, %d tracked, %d lost, %d poses -> %s", len(rows), ok, len(rows) - ok, n_records,
             track_path.parent / "poses.jsonl")
    refused = [r for r in rows if r["state"] == "lost" and r.get("nav_offset_deg_m")]
    if refused:
        deg, m = np.median([r["nav_offset_deg_m"] for r in refused], axis=0)
        log.warning("%d of %d frames were lost only because their fit was off the navigation pose (median %.1f deg /"
                    " %.2f m; allowed %.0f deg / %.1f m): if the navigation is rougher than that, or its poses are not"
                    " T_cam_from_world in the scene file's frame, fix them or raise tracker.nav_max_deg / nav_max_m in"
                    " a --config (frames in %s: nav_offset_deg_m)", len(refused), len(rows), deg, m,
                    cfg.nav_max_deg, cfg.nav_max_m, track_path)
    closest = [r["closest_fit"] for r in rows if r["state"] == "lost" and r.get("closest_fit")]
    if 2 * (len(rows) - ok) > len(rows) and closest:
        sup = float(np.median([c["support"] for c in closest]))
        why = Counter(c["refused"].split(":")[0] for c in closest).most_common(1)[0][0]
        log.warning("%d of %d frames were lost. Their best fits had edge support %.2f (median; a start needs %.2f) and "
                    "were mostly refused for their %s: the image shows few of the CAD's contours where the start "
                    "put them (turbid, dark or blurred water, a start pose far off, or another calibration). Each "
                    "frame's closest_fit in %s says why; --nav (a rough pose per frame) restarts every frame.",
                    len(rows) - ok, len(rows), sup, cfg.min_start_support, why, track_path)
    return [r["frame"] for r in refused]


def _start_record(lens: CameraCalibration | None, init_pose: Rigid3 | None, nav: dict[str, Rigid3] | None) -> dict:
    """What a run's record keeps of its calibration and its start (another start: another run)."""
    return {"calibration": None if lens is None else lens.record(),
            "init_pose": None if init_pose is None else init_pose.matrix().tolist(),
            "nav": None if not nav else _poses_digest(nav)}


def _nav_pose(nav: dict[str, Rigid3] | None, name: str, first: bool, source: Path) -> Rigid3 | None:
    """A frame's navigation pose (None without); a first frame without one means the names do not match."""
    pose = nav.get(name) if nav else None
    if nav and first and pose is None:
        raise InputError(f"the navigation poses have no frame named {name!r} (the first frame of {source}); key "
                         f"them by the frame names (e.g. {sorted(nav)[:2]})")
    return pose


def _poses_digest(poses: dict[str, Rigid3]) -> str:
    """A short fingerprint of per-frame poses (the run's record: other poses, another run)."""
    return f"{len(poses)} frames, {fingerprint({k: np.round(T.matrix(), 9).tolist() for k, T in poses.items()})}"


def _step_json(step: TrackStep, name: str, missing: list[str], structure: Structure,
               hidden: dict[int, HiddenSeen] | None = None) -> dict:
    f = step.fit
    parts = {} if f is None else {structure.objects[k - 1].name: [n, round(share, 4), round(conc, 4)]
                                  for k, (n, share, conc) in sorted(f.instance_support.items()) if k > 0}
    return {"frame": step.index, "frame_name": name, "state": step.state, "source": step.source or None,
            "T_cam_from_world": None if step.T_cam_from_world is None else step.T_cam_from_world.matrix().tolist(),
            "support": None if f is None else round(float(f.support), 4),
            "residual_px": None if f is None else _rounded(f.residual_px),
            "contour_samples": None if f is None else int(f.samples), "missing_parts": missing,
            "part_support": parts,
            "region_support": None if f is None else _rounded(f.region_support),
            "part_region": {} if f is None else {structure.objects[k - 1].name: round(v, 4)
                                                  for k, v in sorted(f.instance_region.items()) if k > 0},
            "part_hidden": {structure.objects[k - 1].name: [h.samples, _rounded(h.seen), h.deep_samples, _rounded(
                h.deep_seen)] for k, h in sorted((hidden or {}).items())},  # no deep sample: null, not NaN
            **({} if step.closest is None else {"closest_fit": {
                "support": round(step.closest.support, 4), "residual_px": _rounded(step.closest.residual_px),
                "region_support": _rounded(step.closest.region_support), "refused": step.closest.why}}),
            "restarts_tried": int(step.restarts_tried), "ms": round(1e3 * step.seconds, 2),
            **({} if step.nav_offset is None else {"nav_offset_deg_m": [round(v, 3) for v in step.nav_offset]})}


def _rounded(v: float) -> float | None:
    return round(float(v), 4) if np.isfinite(v) else None


def _timings(rows: list[dict], overlay_s: list[float]) -> dict:
    """``timings.json`` from the frames' ``track.jsonl`` lines (an interrupted run's too) and the overlay's times
    of the last run."""
    def ms(v: list[float]) -> dict:
        return {"frames": len(v), "mean_ms": float(np.mean(v)) if v else None,
                "median_ms": float(np.median(v)) if v else None}

    track = [r["ms"] for r in rows if r["source"] == "track"]
    restart = [r["ms"] for r in rows if r["source"] != "track"]
    detector = [r["detector_ms"] for r in rows if r.get("detector_ms") is not None]
    total_ms = sum(track) + sum(restart) + sum(detector)
    return {"frames": len(rows), "tracked": sum(r["state"] == "ok" for r in rows),
            "lost": sum(r["state"] == "lost" for r in rows),
            "per_stage": {"track": ms(track), "restart": ms(restart), "detector": ms(detector),
                          "overlay": ms([1e3 * s for s in overlay_s])},
            "frames_per_s": 1e3 * len(rows) / total_ms if total_ms > 0 else None,
            "note": "track: frames continued from the last pose; restart: frames started from a hypothesis "
                    "(init pose, detector) or tried while lost; wall clock; overlay apart"}
