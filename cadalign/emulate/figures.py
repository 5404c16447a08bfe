"""Pictures of emulated sensors: a LiDAR scan coloured by class, a sonar fan, class images (PNG)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cadalign.emulate.lidar import LidarScan
from cadalign.emulate.sonar import SonarImage, fan_image, to_uint8
from cadalign.io import atomic_path

PALETTE = np.array([
    [90, 90, 90], [230, 159, 0], [86, 180, 233], [0, 158, 115], [240, 228, 66], [0, 114, 178],
    [213, 94, 0], [204, 121, 167], [255, 255, 255], [120, 60, 160],
], dtype=np.uint8)
"""Class colours (index = class id modulo the palette; class 0, background, is grey)."""


def class_colours(class_id: np.ndarray) -> np.ndarray:
    """(..., 3) uint8 colours of class ids; negative ids (no return) are black."""
    c = np.asarray(class_id)
    out = PALETTE[np.mod(c, len(PALETTE))]
    out[c < 0] = 0
    return out


def _class_name(names: tuple[str, ...], c: int) -> str:
    return names[c] if 0 <= c < len(names) else f"class {c}"


def _save(fig, path: Path) -> Path:
    import matplotlib.pyplot as plt  # lazy: heavy dependency (matplotlib)

    with atomic_path(Path(path)) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return Path(path)


def lidar_figure(scan: LidarScan, path: Path, class_names: tuple[str, ...] = (), title: str = "") -> Path:
    """Bird's-eye view and, for spinning scans, the ring x azimuth image, both coloured by class."""
    import matplotlib  # lazy: heavy dependency (matplotlib)

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt  # lazy: heavy dependency (matplotlib)

    spinning = bool(len(scan.ring)) and scan.ring.min() >= 0
    n_panels = 3 if spinning else 2
    fig, axes = plt.subplots(1, n_panels, figsize=(7 * n_panels, 6), squeeze=False)
    ax = axes[0, 0]
    cols = class_colours(scan.class_id) / 255.0
    order = np.argsort(scan.xyz_world[:, 2])  # draw high points last (on top)
    ax.scatter(scan.xyz_world[order, 0], scan.xyz_world[order, 1], c=cols[order], s=0.3, linewidths=0)
    ax.set_aspect("equal")
    ax.set_facecolor("black")
    ax.set_xlabel("world x (m)")
    ax.set_ylabel("world y (m)")
    ax.set_title(f"{title} LiDAR returns by class (top view), {len(scan.range_m)} / {scan.n_rays} rays")
    for c in np.unique(scan.class_id):
        ax.scatter([], [], color=PALETTE[c % len(PALETTE)] / 255.0, label=_class_name(class_names, int(c)), s=20)
    if len(scan.class_id):  # a scan with no return has no class to list
        ax.legend(loc="upper right", fontsize=8)
    _oblique(axes[0, 1], scan, cols)
    if spinning:
        n_ring = int(scan.ring.max()) + 1
        n_az = max(1, int(round(2 * np.pi / _az_step(scan.azimuth_rad))))
        img = np.zeros((n_ring, n_az, 3), np.uint8)
        col = np.mod(np.rint(scan.azimuth_rad / (2 * np.pi) * n_az).astype(np.int64), n_az)
        img[n_ring - 1 - scan.ring, col] = class_colours(scan.class_id)
        axes[0, 2].imshow(img, aspect="auto", interpolation="nearest", extent=(0, 360, 0, n_ring))
        axes[0, 2].set_xlabel("azimuth (deg)")
        axes[0, 2].set_ylabel("ring (low to high)")
        axes[0, 2].set_title("range image: class per beam (black = no return)")
    fig.tight_layout()
    return _save(fig, path)


def _oblique(ax, scan: LidarScan, cols: np.ndarray) -> None:  # noqa: ANN001
    """The returns seen from behind and above the sensor, looking at the non-background returns."""
    pts = scan.xyz_world
    if len(pts) == 0:
        return
    fg = scan.class_id > 0
    target = np.median(pts[fg] if fg.sum() >= 10 else pts, axis=0)
    origin = np.asarray(scan.origin_world, dtype=np.float64)
    back = origin - target
    dist = max(float(np.linalg.norm(back)), 1.0)
    eye = origin + 0.5 * back + np.array([0.0, 0.0, 0.4 * dist])
    f = target - eye
    f /= np.linalg.norm(f)
    r = np.cross(f, [0.0, 0.0, 1.0])
    r = r / np.linalg.norm(r) if np.linalg.norm(r) > 1e-9 else np.array([1.0, 0.0, 0.0])
    d = np.cross(f, r)
    cam = (pts - eye) @ np.stack([r, d, f], 1)
    z = np.maximum(cam[:, 2], 1e-9)
    x, y = cam[:, 0] / z, -cam[:, 1] / z
    half_w, half_h = np.tan(np.radians(35.0)), np.tan(np.radians(26.0))  # a 70 x 52 degree camera
    ok = (cam[:, 2] > 0.1) & (np.abs(x) < half_w) & (np.abs(y) < half_h)
    order = np.flatnonzero(ok)[np.argsort(-cam[ok, 2])]  # far first, near drawn over them
    ax.scatter(x[order], y[order], c=cols[order], s=1.0, linewidths=0)
    ax.set_xlim(-half_w, half_w)
    ax.set_ylim(-half_h, half_h)
    ax.set_facecolor("black")
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_title("oblique view from behind and above the sensor")


def _az_step(az: np.ndarray) -> float:
    u = np.unique(np.round(np.mod(az, 2 * np.pi), 9))
    return float(np.min(np.diff(u))) if len(u) > 1 else 2 * np.pi


def sonar_figure(img: SonarImage, path: Path, dynamic_range_db: float, class_names: tuple[str, ...] = (),
                 title: str = "") -> Path:
    """The sonar fan (log intensity) beside the class of the strongest return per cell."""
    import matplotlib  # lazy: heavy dependency (matplotlib)

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt  # lazy: heavy dependency (matplotlib)

    r_max = float(img.ranges_m[-1])
    half = float(np.max(np.abs(img.bearings_rad)))
    half_w = r_max * np.sin(min(half, np.pi / 2))
    extent = (-half_w, half_w, 0, r_max)
    fig, axes = plt.subplots(1, 2, figsize=(14, 6))
    axes[0].imshow(fan_image(to_uint8(img.intensity, dynamic_range_db), img), cmap="copper", extent=extent)
    axes[0].set_title(f"{title} multibeam sonar intensity ({dynamic_range_db:.0f} dB)")
    axes[1].imshow(fan_image(class_colours(img.class_id), img), extent=extent)
    axes[1].set_title("class of the strongest return per cell")
    for c in np.unique(img.class_id[img.class_id >= 0]):
        axes[1].scatter([], [], color=PALETTE[c % len(PALETTE)] / 255.0, label=_class_name(class_names, int(c)))
    if (img.class_id >= 0).any():
        axes[1].legend(loc="upper right", fontsize=8)
    for ax in axes:
        ax.set_xlabel("across (m, + = starboard/right)")
        ax.set_ylabel("forward range (m)")
    fig.tight_layout()
    return _save(fig, path)


def contact_figure(rgb: np.ndarray, depth_m: np.ndarray, class_id: np.ndarray | None, mesh_view: np.ndarray,
                   scan: LidarScan, path: Path, class_names: tuple[str, ...] = (), title: str = "") -> Path:
    """GenLaM contact picture: photo, depth, classes, a novel view of the layered mesh and the scan from above.

    The scan panel plots camera-frame x (right) against z (forward), the points coloured by class (by their
    colour when there are no classes).
    """
    import matplotlib  # lazy: heavy dependency (matplotlib)

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt  # lazy: heavy dependency (matplotlib)

    fig, ax = plt.subplots(1, 5, figsize=(24, 4.8))
    ax[0].imshow(rgb)
    ax[0].set_title("photo")
    d = np.where(depth_m > 0, depth_m, np.nan)
    im = ax[1].imshow(d, cmap="turbo")
    fig.colorbar(im, ax=ax[1], fraction=0.04, label="depth (m)")
    ax[1].set_title("depth")
    if class_id is not None:
        ax[2].imshow(class_colours(class_id))
        shown = np.unique(class_id)[:8]
        ax[2].set_title("classes: " + ", ".join(_class_name(class_names, int(c)) for c in shown), fontsize=7)
    else:
        ax[2].set_title("classes: none (no segmentation model)")
    ax[3].imshow(mesh_view)
    ax[3].set_title("layered mesh, novel view")
    colour = class_colours(scan.class_id) if class_id is not None else scan.rgb
    ax[4].scatter(scan.xyz_world[:, 0], scan.xyz_world[:, 2], s=0.3, c=colour / 255.0)
    panes = scan.pane_id > 0
    if panes.any():
        ax[4].scatter(scan.xyz_world[panes, 0], scan.xyz_world[panes, 2], s=0.3, c="red", label="pane")
        ax[4].legend(loc="upper right", fontsize=7)
    ax[4].set_aspect("equal")
    ax[4].set_xlabel("x right (m)")
    ax[4].set_ylabel("z forward (m)")
    ax[4].set_title(f"LiDAR scan: {len(scan.range_m)} returns")
    for a in ax[:4]:
        a.axis("off")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    return _save(fig, path)
