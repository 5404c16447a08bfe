"""``track.png``: a tracker run at a glance, from its ``track.jsonl`` and ``poses.jsonl`` (no truth needed).

Top: each frame's edge and colour-region support against the track's floor, lost frames shaded, restarts marked.
Bottom: each part in each frame: reported, reported missing, or neither (out of view, too small to check, or the
frame lost).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

REPORTED, MISSING, NEITHER = 2, 1, 0


def part_states(rows: list[dict], reported: dict[int, set[str]], names: list[str]) -> np.ndarray:
    """(parts, frames) of :data:`REPORTED` / :data:`MISSING` / :data:`NEITHER`: ``rows`` the ``track.jsonl`` lines,
    ``reported`` the part names with a record in ``poses.jsonl`` by frame index, ``names`` the parts in order."""
    out = np.full((len(names), len(rows)), NEITHER, dtype=np.int8)
    row_of = {n: i for i, n in enumerate(names)}
    for j, r in enumerate(rows):
        for n in r.get("missing_parts") or []:
            if n in row_of:
                out[row_of[n], j] = MISSING
        for n in reported.get(r["frame"], set()):
            if n in row_of:
                out[row_of[n], j] = REPORTED
    return out


def plot_track(path: Path, rows: list[dict], reported: dict[int, set[str]], names: list[str],
               min_support: float) -> None:
    """Write ``track.png`` (module doc); ``min_support``: the tracker's floor on edge support, drawn for reference."""
    from matplotlib.colors import ListedColormap  # lazy: heavy dependency (matplotlib)
    from matplotlib.figure import Figure  # lazy: heavy dependency (matplotlib)

    frames = np.array([r["frame"] for r in rows])
    fig = Figure(figsize=(11, 3.2 + 0.16 * len(names)), dpi=100)
    ax1, ax2 = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [2.2, 0.6 + 0.16 * len(names)]})
    for key, label, colour in (("support", "edge support", "tab:blue"), ("region_support", "colour-region support",
                                                                         "tab:orange")):
        v = np.array([np.nan if r.get(key) is None else r[key] for r in rows], dtype=float)
        if np.isfinite(v).any():
            ax1.plot(frames, v, ".-", ms=3, lw=1, color=colour, label=label)
    ax1.axhline(min_support, color="0.4", ls="--", lw=1, label=f"edge support floor ({min_support:.2f})")
    restarts = [r["frame"] for r in rows if r["state"] == "ok" and r.get("source") not in ("track", None)]
    ax1.plot(restarts, [1.02] * len(restarts), "v", color="tab:red", ms=5, label="(re)start", clip_on=False)
    for r in rows:
        if r["state"] != "ok":
            for ax in (ax1, ax2):
                ax.axvspan(r["frame"] - 0.5, r["frame"] + 0.5, color="0.85", lw=0)
    ax1.set_ylim(0, 1.05)
    ax1.set_ylabel("share of contour samples")
    ax1.set_title(f"{sum(r['state'] == 'ok' for r in rows)} of {len(rows)} frames tracked (grey: lost, no pose)")
    ax1.legend(loc="lower left", fontsize=7, ncol=4)
    ax1.grid(alpha=0.3)
    states = part_states(rows, reported, names)
    step = float(np.median(np.diff(frames))) if len(frames) > 1 else 1.0
    ax2.imshow(states, aspect="auto", interpolation="nearest", vmin=0, vmax=2,
               cmap=ListedColormap(["white", "tab:red", "tab:green"]),
               extent=(frames[0] - step / 2, frames[-1] + step / 2, len(names) - 0.5, -0.5) if len(frames) else None)
    ax2.set_yticks(range(len(names)), names, fontsize=6 if len(names) > 12 else 8)
    ax2.set_xlabel("frame (parts: green reported, red reported missing, white neither)")
    fig.tight_layout()
    fig.savefig(path)
