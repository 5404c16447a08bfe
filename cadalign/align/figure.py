"""A picture of an alignment: top and side views of the aligned SfM points over the CAD, coloured by residual."""

from __future__ import annotations

import io

import numpy as np

from cadalign.align.result import AlignResult
from cadalign.align.surface import CadSurface

MAX_DRAWN = 30_000
"""At most this many points of each set are drawn (a seeded subset)."""


def _subset(n: int, k: int, seed: int) -> np.ndarray:
    return np.arange(n) if n <= k else np.sort(np.random.default_rng(seed).choice(n, k, replace=False))


def render_png(points_sfm: np.ndarray, surface: CadSurface, result: AlignResult, *, inlier_dist_m: float,
               title: str = "", seed: int = 0) -> bytes:
    """PNG bytes: top (x-y) and side (x-z, y-z) views of the aligned points around the CAD.

    The views are cropped to the CAD's bounding box plus 15 percent. CAD samples are light grey; SfM
    points are coloured by their distance to the CAD surface (dark blue on it, red at ``3 * inlier_dist_m``)
    and points further away (clutter, seabed) are small dark-grey dots.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # lazy: heavy dependency (matplotlib)
    from matplotlib.figure import Figure  # lazy: heavy dependency (matplotlib)

    y = result.cad_from_sfm.apply(points_sfm[_subset(len(points_sfm), MAX_DRAWN, seed)])
    d = surface.distances(y)
    cad = surface.points_m[_subset(len(surface.points_m), MAX_DRAWN, seed)]
    lo, hi = cad.min(axis=0), cad.max(axis=0)
    pad = 0.15 * (hi - lo).max()
    near = np.all((y >= lo - pad) & (y <= hi + pad), axis=1)
    vmax = 3.0 * inlier_dist_m
    fig = Figure(figsize=(17, 5), dpi=110, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 4, width_ratios=[1, 1, 1, 0.8])
    sc = None
    views = [(0, 1, "top (x-y)"), (0, 2, "side (x-z)"), (1, 2, "side (y-z)")]
    for ax, (i, j, name) in zip(axes[:3], views, strict=True):
        order = np.argsort(-d[near])  # draw the worst first so the good points stay visible on top
        yy, dd = y[near][order], d[near][order]
        ax.scatter(cad[:, i], cad[:, j], s=0.3, c="0.8", linewidths=0)
        far = dd > vmax
        ax.scatter(yy[far, i], yy[far, j], s=0.5, c="0.45", linewidths=0)
        sc = ax.scatter(yy[~far, i], yy[~far, j], s=1.5, c=dd[~far] * 100, cmap="turbo", vmin=0, vmax=vmax * 100,
                        linewidths=0)
        ax.set_xlim(lo[i] - pad, hi[i] + pad)
        ax.set_ylim(lo[j] - pad, hi[j] + pad)
        ax.set_aspect("equal")
        ax.set_title(name)
        ax.set_xlabel("xyz"[i] + " (m)")
        ax.set_ylabel("xyz"[j] + " (m)")
    if sc is not None:
        fig.colorbar(sc, ax=list(axes[:3]), shrink=0.8, label=f"distance to CAD (cm); grey: > {vmax * 100:.0f} cm")
    hist = axes[3]
    hist.hist(np.minimum(d[near], 2 * vmax) * 100, bins=60, color="0.3")
    hist.axvline(inlier_dist_m * 100, color="tab:red", label=f"inlier distance {inlier_dist_m * 100:.1f} cm")
    hist.set_xlabel(f"distance to CAD (cm), clipped at {2 * vmax * 100:.0f}")
    hist.set_ylabel("points around the CAD")
    hist.legend()
    m = result.metrics
    fig.suptitle(
        f"{title}  scale {result.scale:.5g} m/unit, fitness {m.fitness:.3f}, "
        f"inlier RMSE {m.inlier_rmse_m * 100:.2f} cm, {m.n_inliers} inliers of {m.n_points} points", fontsize=11,
    )
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()
