"""Sparse viewpoint models (ICG / SRT3D style) against the tracker's carried contours: a measurement, not library code.

Usage: python viewpoint_templates.py PRESET carry|tmpl|time N_SPHERE SIM SCENE.toml INIT.json N_FRAMES
(CFG=over.toml to override the preset). RGB only; the truth of SIM scores the camera only.

Templates: eyes on a sphere round the CAD's box centre, at the start pose's distance from it (the --init-pose file,
not the truth), looking at the centre, rendered at 1920x1440 with the tracker's focal length so the whole structure
is in view; Fibonacci directions over the sphere (N_SPHERE), those within -15..+35 deg of the start's elevation
kept. Each keeps the full-resolution level's contour samples: world point, a world 'normal tip' (1 px along the
2-D normal at the sample's depth) and the sample's part. In 'tmpl' mode the full-resolution level of every fit takes
the template nearest in eye direction (its normals projected afresh) instead of a render or the carried contours
(EdgeTracker._carried is replaced); 'carry' runs the preset as it is; 'time' runs the two in turn in one process,
three times each. Results: docs/tuning/tracker.md, "Sparse viewpoint models against carried contours (s64)".
"""
import os
import sys
import time
import types
from pathlib import Path

import numpy as np

from cadalign.align.edge_refine import contour_samples
from cadalign.config import resolve
from cadalign.formats.calibration import read_calibration
from cadalign.geometry.camera import backproject
from cadalign.geometry.rotations import geodesic_angle
from cadalign.infer.track import edges as E
from cadalign.infer.track import tracker as TR
from cadalign.infer.track.config import PRESETS, TrackRunConfig
from cadalign.infer.track.run import read_init_pose
from cadalign.infer.video import iter_frames
from cadalign.raycast.core import RaycastRenderer
from cadalign.sim.navigation import true_poses
from cadalign.sim.structure import load_structure
from cadalign.sim.trajectory import look_at
from cadalign.types import Camera, Rigid3

preset, mode, n_sphere = sys.argv[1], sys.argv[2], int(sys.argv[3])
S, SCENE, INIT, NF = Path(sys.argv[4]), Path(sys.argv[5]), Path(sys.argv[6]), int(sys.argv[7])
cfg = resolve(TrackRunConfig, PRESETS, preset, Path(os.environ["CFG"]) if os.environ.get("CFG") else None)
K = read_calibration(S / "calibration.json").K
cam = Camera(K, 640, 480)
meshes = load_structure(SCENE).render_meshes()
lo = np.min([m.vertices_m.min(0) for m in meshes], 0)
hi = np.max([m.vertices_m.max(0) for m in meshes], 0)
centre = (lo + hi) / 2
truth = true_poses(S)
names = sorted(truth)
init = read_init_pose(INIT)
eye0 = init.inverse().t - centre
radius = float(np.linalg.norm(eye0))
el0 = float(np.degrees(np.arcsin(eye0[2] / radius)))


class Inst:
    """A template's per-sample parts, handed through the frame's instance map."""

    def __init__(self, inst: np.ndarray) -> None:
        self.inst = inst


def build_templates() -> tuple[np.ndarray, list]:
    i = np.arange(n_sphere) + 0.5
    zz = 1 - 2 * i / n_sphere
    ph = np.pi * (1 + 5**0.5) * i
    dirs = np.stack([np.sqrt(1 - zz**2) * np.cos(ph), np.sqrt(1 - zz**2) * np.sin(ph), zz], 1)
    el = np.degrees(np.arcsin(dirs[:, 2]))
    dirs = dirs[(el > el0 - 15) & (el < el0 + 35)]
    Kt = K.copy()
    Kt[0, 2], Kt[1, 2] = 960, 720
    rt = RaycastRenderer(meshes, Camera(Kt, 1920, 1440))
    lcfg = E.EdgeTracker(meshes, cam, cfg.tracker.edges)._level_cfg(cfg.tracker.edges.levels[-1].search_px)
    t0, out = time.perf_counter(), []
    for d in dirs:
        T = look_at(centre + radius * d, centre)
        f = rt.render(T, with_full_masks=False, with_normals=False)
        Xc, uv, n = contour_samples(f.depth_m, f.rays_cam, f.range_m, lcfg, f.instance)
        tip = T.apply(backproject(Kt, uv + n, Xc[:, 2])[0]) - T.apply(backproject(Kt, uv, Xc[:, 2])[0])
        out.append((T.apply(Xc).astype(np.float32), tip.astype(np.float32), E.sample_instances(uv, n, f.instance)))
    mem = sum(a.nbytes + b.nbytes + c.nbytes for a, b, c in out)
    print(f"{len(dirs)} templates of {n_sphere} on the sphere, built in {time.perf_counter() - t0:.0f} s, "
          f"{mem / 1e6:.0f} MB, radius {radius:.2f} m")
    return dirs, out


def instances(uv: np.ndarray, n: np.ndarray, instance: object) -> np.ndarray:
    if isinstance(instance, Inst):  # a template's parts, thinned as the fit thinned its samples
        step = max(int(round(len(instance.inst) / max(len(uv), 1))), 1)
        return instance.inst[::step][:len(uv)]
    return sample_instances(uv, n, instance)


def nearest_template(self: E.EdgeTracker, T: Rigid3) -> types.SimpleNamespace:
    """The template nearest in eye direction, its samples seen from ``T`` (in place of the carried contours)."""
    eye = (T.t - centre) / np.linalg.norm(T.t - centre)
    X, tip, inst = templates[int(np.argmax(dirs @ eye))]
    X = X.astype(np.float64)
    Xc = T.inverse().apply(X)
    front = Xc[:, 2] > 0.1
    X, Xc, tip, inst = X[front], Xc[front], tip[front].astype(np.float64), inst[front]
    uv = E.array_pixels(K, Xc)
    n = E.array_pixels(K, T.inverse().apply(X + tip)) - uv
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-9)
    inb = (uv[:, 0] >= 0) & (uv[:, 0] < 640) & (uv[:, 1] >= 0) & (uv[:, 1] < 480)
    return types.SimpleNamespace(X_w=X[inb], uv=uv[inb], normal=n[inb], support=-1.0,
                                 frame=types.SimpleNamespace(instance=Inst(inst[inb])))


def patch(on: bool) -> None:
    E.sample_instances = instances if on else sample_instances
    E.EdgeTracker._carried = nearest_template if on else carried


def track(frames: list[np.ndarray]) -> tuple[float, np.ndarray]:
    """Seconds a frame after the first, and the camera's (mm, deg) errors on the tracked frames."""
    tr = TR.StructureTracker(meshes, cam, cfg.tracker)
    col = tr.cfg.edges.colour
    tr.step(E.as_gray(frames[0], col), [("init_pose", init)], frames[0][..., :3])
    t0, errs = time.perf_counter(), []
    for k, img in enumerate(frames[1:], 1):
        s = tr.step(E.as_gray(img, col), [], img[..., :3])
        if s.T_cam_from_world is not None:
            a, b = s.T_cam_from_world.inverse(), truth[names[k]].inverse()
            errs.append((1e3 * np.linalg.norm(a.t - b.t), np.degrees(geodesic_angle(a.R, b.R))))
    return (time.perf_counter() - t0) / (len(frames) - 1), np.array(errs).reshape(-1, 2)


sample_instances, carried = E.sample_instances, E.EdgeTracker._carried
if mode in ("tmpl", "time"):
    dirs, templates = build_templates()
frames = [vf.image for vf in iter_frames(S / "frames", max_frames=NF)]
nf = len(frames) - 1
for m in ("carry", "tmpl") * 3 if mode == "time" else (mode,):
    patch(m == "tmpl")
    sec, e = track(frames)
    print(f"{preset} {m}: {1e3 * sec:.1f} ms/frame, tracked {len(e)}/{nf}, camera mean {e[:, 0].mean():.1f} mm, "
          f"median {np.median(e[:, 0]):.1f}, max {e[:, 0].max():.1f} mm, {e[:, 1].mean():.3f} deg mean", flush=True)
