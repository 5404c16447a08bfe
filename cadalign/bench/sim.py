"""``cadalign bench sim``: what each simulated effect costs per frame, against the bare render.

The baseline is measured in the same run: the bare render (pyrender RGB + Open3D ground truth) of each
frame. For every frame we time, interleaved so load changes hit all variants alike:

* ``bare``: RGB render + ground-truth ray casting, no effect machinery at all;
* ``effect_free``: the production per-frame path (:func:`cadalign.sim.run.render_frame`) with the
  scene's effects removed — it must cost the same as ``bare`` (the "undeclared effects cost nothing"
  promise, reported as a ratio);
* ``all_effects``: the production path with every effect the scene declares;
* each declared effect alone, on the same rendered buffers;
* ``write``: encoding and writing the frame's files (BOP PNGs, masks, normals).

Outputs ``bench_sim.json`` and ``bench_sim.png`` (per-frame cost per step) in ``out_dir``.
"""

from __future__ import annotations

import dataclasses
import logging
import tempfile
import time
from pathlib import Path

import numpy as np

from cadalign.io import write_json
from cadalign.sim.effects_chain import build_chain, run_chain
from cadalign.sim.render import GroundTruthCaster, RGBRenderer
from cadalign.sim.run import _write_frame, apply_overrides, render_frame
from cadalign.sim.scene import build_scene
from cadalign.sim.spec import load_scene
from cadalign.sim.trajectory import pose_at

log = logging.getLogger(__name__)
ROUNDS = 3
"""Repeats of the bare and effect-free timings per frame; their per-frame minimum is the estimate of the
intrinsic cost (timing noise on a shared 2-core machine is one-sided: it only adds time)."""


def bench_sim(scene_path: Path, out_dir: Path, *, frames: int = 8, resolution: tuple[int, int] | None = None,
              progress=None) -> dict:  # noqa: ANN001
    """Time the simulator on ``frames`` frames of ``scene_path``; writes and returns the result dict."""

    scene_path, out_dir = Path(scene_path), Path(out_dir)
    spec = apply_overrides(load_scene(scene_path), None, resolution, None)
    n_total = spec.trajectory.frames
    ids = [int(k) for k in np.linspace(0, n_total - 1, min(frames, n_total)).round()]
    scene = build_scene(spec, scene_path)
    clean_scene = dataclasses.replace(scene, spec=dataclasses.replace(spec, effects=(), effect_params={}))
    chain = build_chain(spec)
    renderer, caster = RGBRenderer(scene), GroundTruthCaster(scene)
    t: dict[str, list[float]] = {"bare": [], "effect_free": [], "all_effects": [], "write": []}
    t.update({f"effect:{name}": [] for name, _ in chain})
    try:
        render_frame(scene, chain, ids[0], renderer, caster)  # warm-up (GL context, caches)
        with tempfile.TemporaryDirectory() as tmp:
            for k in progress(ids, "bench sim", len(ids)) if progress else ids:
                T = pose_at(spec.trajectory, k / spec.trajectory.fps, spec.seed)
                # bare and effect-free alternate order over rounds, so caches and load favour neither
                for rnd in range(ROUNDS):
                    for variant in (("bare", "effect_free") if (k + rnd) % 2 == 0 else ("effect_free", "bare")):
                        t0 = time.perf_counter()
                        if variant == "bare":
                            renderer.render(T)
                            caster.cast(T)
                        else:
                            render_frame(clean_scene, [], k, renderer, caster)
                        t[variant].append(time.perf_counter() - t0)
                t0 = time.perf_counter()
                _, rgb, gt, _ = render_frame(scene, chain, k, renderer, caster)
                t["all_effects"].append(time.perf_counter() - t0)
                clean = renderer.render(T)
                for name, params in chain:
                    _, eff = run_chain([(name, params)], clean, gt, spec, k, T, scene.camera)
                    t[f"effect:{name}"].append(eff[name])
                t0 = time.perf_counter()
                _write_frame(Path(tmp), scene, k, T, rgb, gt)
                t["write"].append(time.perf_counter() - t0)
    finally:
        renderer.close()
    result = _summarise(spec, ids, t)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json(out_dir / "bench_sim.json", result)
    plot_bench_sim(result, out_dir / "bench_sim.png")
    return result


def _summarise(spec, ids: list[int], t: dict[str, list[float]]) -> dict:  # noqa: ANN001
    med = {k: float(np.median(v)) for k, v in t.items()}
    bare = med["bare"]
    per_frame_min = {k: np.asarray(t[k]).reshape(len(ids), ROUNDS).min(axis=1) for k in ("bare", "effect_free")}
    return {
        "scene": spec.name,
        "resolution": [spec.camera.width, spec.camera.height],
        "frames": ids,
        "effects": [k.split(":", 1)[1] for k in t if k.startswith("effect:")],
        "seconds_per_frame_median": med,
        "ratio_to_bare": {k: v / bare for k, v in med.items() if k != "bare"},
        "effect_free_overhead_pct": 100.0 * (per_frame_min["effect_free"].sum() / per_frame_min["bare"].sum() - 1.0),
        "effect_free_overhead_note": "sum over frames of the minimum of the rounds, effect-free vs bare",
        "all_effects_s_per_frame": med["all_effects"],
        "all_effects_with_write_s_per_frame": med["all_effects"] + med["write"],
        "samples": {k: [float(x) for x in v] for k, v in t.items()},
    }


def plot_bench_sim(result: dict, path: Path) -> Path:
    """Horizontal bars: median seconds per frame of each variant and each effect alone."""
    import matplotlib  # lazy: heavy dependency (matplotlib)

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # lazy: heavy dependency (matplotlib)

    med = result["seconds_per_frame_median"]
    names = list(med)
    vals = [med[n] * 1000 for n in names]
    fig, ax = plt.subplots(figsize=(7, 0.35 * len(names) + 1.2))
    colors = ["tab:gray" if n in ("bare", "effect_free") else "tab:blue" if n.startswith("effect:")
              else "tab:orange" for n in names]
    ax.barh(names, vals, color=colors)
    for y, v in enumerate(vals):
        ax.text(v, y, f" {v:.1f}", va="center", fontsize=8)
    ax.invert_yaxis()
    w, h = result["resolution"]
    ax.set_xlabel("milliseconds per frame (median)")
    ax.set_title(f"simulator cost, scene '{result['scene']}' at {w}x{h} "
                 f"(effect-free overhead {result['effect_free_overhead_pct']:+.1f}%)", fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
