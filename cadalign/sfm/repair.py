"""Repairing a model that every mapping attempt broke: re-map a window round each break and merge.

A break (:mod:`cadalign.sfm.consistency`) is a seam where the incremental mapper joined two rigid pieces
with a wrong relative pose. On the default orbit it happens in the one weak stretch (frames 36-45: 140-230
verified matches between neighbours, 45-80 two frames apart) in about one run in eight, and when the
database's matches lead there, every seed does it (measured: 42/43 turned 15.7 deg with the baseline
reversed, with 3 of 3 seeds). Each piece is sound, only the joint is wrong.

Mapped on its own, a short window round the seam starts from a pair inside it and registers the seam
frames from their neighbours only (measured: frames 35-50 sound with every seed). :func:`repair_breaks`
maps such a window for each break (breaks closer than a window are taken together), then chains
``piece, window, piece, window, ...`` with :func:`cadalign.sfm.segments.merge_models` (each joined to the
previous by the Sim(3) of their shared frames; points triangulated anew over the whole database) and checks
the merged model again. Every frame a piece holds keeps that piece's pose (a window's end frames are its
least certain: taking them from the window left one frame 0.3 deg off after the refinement); a window gives
only the relative placement of the pieces and the frames no piece holds.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from typing import Any

from cadalign.errors import DegenerateGeometryError
from cadalign.sfm.colmap_log import stderr_captured
from cadalign.sfm.consistency import Consistency, pieces

log = logging.getLogger(__name__)

MIN_SHARED = 3
"""Frames a window must share (registered) with each piece it joins: a Sim(3) needs three."""


def break_windows(names: Sequence[str], cons: Consistency, frames: int) -> list[tuple[int, int]]:
    """Index ranges ``[lo, hi)`` of ``names`` (capture order) to re-map: ``frames`` frames centred on each
    break's seam, clipped to the sequence; windows that overlap are joined into one."""
    index = {n: k for k, n in enumerate(names)}
    half = frames // 2
    spans: list[list[int]] = []
    for b in sorted(cons.breaks, key=lambda b: index[b.frame_b]):
        lo, hi = max(0, index[b.frame_b] - half), min(len(names), index[b.frame_b] + frames - half)
        if spans and lo < spans[-1][1]:
            spans[-1][1] = max(spans[-1][1], hi)
        else:
            spans.append([lo, hi])
    return [(lo, hi) for lo, hi in spans]


def restricted(rec: Any, keep: set[str]) -> Any:
    """A copy of ``rec`` (``pycolmap.Reconstruction``) with every frame outside ``keep`` deregistered."""
    import pycolmap  # lazy: heavy dependency (pycolmap)

    out = pycolmap.Reconstruction(rec)
    for im in list(out.images.values()):
        if im.has_pose and im.name not in keep:
            out.deregister_frame(im.frame_id)
    return out


def adopt_camera(win: Any, rec: Any, num_threads: int) -> None:
    """Give ``win`` (a window's model) the cameras of ``rec`` (the broken model) and re-adjust its poses and
    points with them held fixed: a window self-calibrates on a few frames only, and its relative poses must
    match the pieces' camera to join them (on the tiny test dive a 6-frame window's own focal length turned
    consecutive frames up to 1.6 deg against the whole model's)."""
    import pycolmap  # lazy: heavy dependency (pycolmap)

    for cid in list(win.cameras):
        if cid in rec.cameras:
            c = rec.cameras[cid]
            win.cameras[cid] = pycolmap.Camera(model=c.model, width=c.width, height=c.height,
                                               params=list(c.params), camera_id=cid)
    win.update_point_3d_errors()
    opts = pycolmap.BundleAdjustmentOptions()
    opts.print_summary = False
    opts.refine_focal_length = opts.refine_principal_point = opts.refine_extra_params = False
    opts.ceres.solver_options.num_threads = num_threads
    opts.ceres.use_gpu = False
    with stderr_captured():  # pycolmap's bundle_adjustment logs at INFO whatever glog's flags say
        pycolmap.bundle_adjustment(win, opts)


def repair_breaks(rec: Any, names: Sequence[str], cons: Consistency, frames: int,
                  map_window: Callable[[list[str], int], tuple[Any, Consistency]],
                  merge: Callable[[list[Any], list[set[str] | None]], tuple[Any, list[dict[str, Any]]]],
                  check: Callable[[Any], Consistency]) -> tuple[Any | None, dict[str, Any]]:
    """Re-map a window round each break of ``rec`` and merge (module doc).

    Args:
        rec: the broken model (``pycolmap.Reconstruction``; not changed).
        names: all frames in capture order.
        cons: ``rec``'s consistency (its breaks).
        frames: window length.
        map_window: maps a list of frame names (``k``: the window's number) and gives the model and its
            consistency.
        merge: :func:`cadalign.sfm.segments.merge_models` bound to the database (models, ``adds``).
        check: the consistency of a model.

    Returns:
        The repaired model, or None when a window broke too, shares too few frames with a piece, or the
        merged model still has breaks; and a report (windows, seams, the merged model's consistency, why not).
    """
    registered = {im.name for im in rec.images.values() if im.has_pose}
    parts = pieces(names, registered, cons.breaks)
    piece_of = {n: i for i, p in enumerate(parts) for n in p}
    spans = break_windows(names, cons, frames)
    report: dict[str, Any] = {"windows": [], "repaired": False}
    chain: list[Any] = []
    adds: list[set[str] | None] = []  # a window gives the poses of frames no piece holds; it joins the rest
    for k, (lo, hi) in enumerate(spans):
        sub = list(names[lo:hi])
        try:
            win, wcons = map_window(sub, k)
        except DegenerateGeometryError as exc:  # a window with no model is a failed repair, not a failed run
            report["windows"].append({"frames": [sub[0], sub[-1]], "registered": 0, "breaks": 0})
            report["why_not"] = f"the window {sub[0]}..{sub[-1]} found no model on its own ({exc})"
            return None, report
        win_reg = {im.name for im in win.images.values() if im.has_pose}
        report["windows"].append({"frames": [sub[0], sub[-1]], "registered": len(win_reg),
                                  "breaks": len(wcons.breaks)})
        if not wcons.ok:
            report["why_not"] = f"the window {sub[0]}..{sub[-1]} mapped on its own breaks too"
            return None, report
        held = [piece_of[n] for n in sub if n in piece_of]  # the window holds a seam: two pieces at least
        left, right = parts[held[0]], parts[held[-1]]
        for side, piece in (("before", left), ("after", right)):
            if len(win_reg & set(piece)) < MIN_SHARED:
                report["why_not"] = (f"the window {sub[0]}..{sub[-1]} shares fewer than {MIN_SHARED} registered "
                                     f"frames with the piece {side} its seam ({piece[0]}..{piece[-1]})")
                return None, report
        if not chain:
            chain.append(restricted(rec, set(left)))
            adds.append(None)
        chain += [win, restricted(rec, set(right))]
        adds += [set(sub) - set(piece_of), None]
    merged, seams = merge(chain, adds)
    after = check(merged)
    report.update({"seams": seams, "consistency": after.to_dict(), "registered": merged.num_reg_images()})
    if not after.ok:
        report["why_not"] = "the merged model still breaks at " + ", ".join(
            f"{b.frame_a}/{b.frame_b}" for b in after.breaks)
        return None, report
    report["repaired"] = True
    return merged, report
