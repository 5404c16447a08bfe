"""Configuration of the fusion stage: one frozen dataclass and the named presets.

Load with :func:`cadalign.config.resolve` (preset, then file keys, then overrides)::

    cfg = resolve(FuseConfig, PRESETS, "default", overrides={"voxel_m": 0.05})
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

from cadalign.config import bounded


@dataclass(frozen=True)
class FuseConfig:
    """Semantic map fusion (TSDF or surfels) of posed depth + class probabilities."""

    method: Literal["tsdf", "surfel"] = "tsdf"
    """Map representation: Open3D voxel-block TSDF, or an ElasticFusion-like surfel map."""
    voxel_m: float = bounded(0.02, gt=0)
    """TSDF voxel size, and the spacing of new surfels, metres."""
    trunc_voxels: float = bounded(4.0, ge=3.0)
    """TSDF truncation distance in voxels (>= 3; also keep it >= 3 sigma of the depth error)."""
    depth_min_m: float = bounded(0.1, ge=0)
    """Depth below this is ignored, metres."""
    depth_max_m: float = bounded(20.0, gt=0)
    """Depth beyond this is ignored, metres (underwater visibility rarely exceeds it)."""
    weight_cap: float = bounded(64.0, ge=1)
    """TSDF weights (frames averaged) and surfel confidences are capped here, so the map keeps adapting."""
    block_resolution: int = bounded(8, ge=2, le=16)
    """Voxels per side of one TSDF block. 4 makes Open3D's integration ~40% cheaper at 2 cm (fewer voxels away
    from the surface are visited) but Open3D picks blocks from every 4th pixel only, so small blocks miss
    some surface: 95.9% instead of 96.3% of the default scene's CAD within 2 cm."""
    block_count: int = bounded(70000, ge=16)
    """Initial hash map capacity in blocks (8^3 blocks of ~18 kB each, allocated up front). Open3D doubles it when full,
    stalling a frame for seconds, so it is sized for the default scene's ~50k blocks after its orbit
    (docs/tuning/fuse_config.md#fuseconfigblock_count)."""
    color_every: int = bounded(1, ge=1)
    """TSDF only: integrate colour on every n-th frame (depth and labels on every frame). Colour is about a
    third of Open3D's TSDF time at 640x480; with n > 1 a voxel's colour is still a weighted average of the
    colours seen, earlier frames weighing more. 1 = every frame (exact)."""
    mesh_weight_threshold: float = bounded(1.0, gt=0)
    """Voxels observed less than this are left out of the mesh and point cloud."""
    label_min_prob: float = bounded(1e-3, gt=0, lt=1)
    """Input class probabilities are clamped to [label_min_prob, 1] before the Bayes update."""
    label_log_floor: float = bounded(-20.0, lt=0)
    """Fused class log-probabilities are floored here (finite, and the map can still change its mind)."""
    label_confidence: float = bounded(0.95, gt=0, le=1)
    """Probability given to the labelled class when labels come as class indices (ground truth)."""
    label_band_voxels: float = bounded(2.0, gt=0)
    """Voxels within +-band/2 of the observed surface (along the ray) get the label update; at most
    ``trunc_voxels`` (the update is only ever applied where |sdf| < trunc/2)."""
    label_lookup: Literal["frustum", "reference"] = "frustum"
    """How the label update finds the voxel of each sample: ``frustum`` looks its block up in a dense table of
    the blocks this frame touched (fast); ``reference`` asks Open3D's hash map once per sample (the first
    implementation, the baseline of ``bench_fuse``). Both update the same voxels with the same values."""
    label_threads: int = bounded(2, ge=1)
    """Threads for the frustum label update (NumPy releases the GIL, so they use separate cores); the result
    is the same for any number. 1 = none (on a machine already busy, threads only add hand-over cost)."""
    label_cell_voxels: int = bounded(1, ge=1, le=8)
    """Edge of a label cell in TSDF voxels (1, 2, 4 or 8; must divide ``block_resolution``): one class
    distribution per cell, held by its lowest-index voxel. 1 = a distribution per voxel (exact, the first
    implementation, the default: 2 lost more label accuracy than ``label_pixel_stride`` 2 for less speed)."""
    label_pixel_stride: int = bounded(2, ge=1)
    """Largest pixel stride (both directions) of the label update, its speed knob: a frame fuses one pixel in s^2, the
    offset cycling frame by frame (smaller where samples would land > 2 voxels apart; 1 = every pixel). 2 keeps fusion
    with labels >= 0.8x Open3D's grid alone at 640x480, 2 cm (docs/tuning/fuse_labels.md)."""
    pred_depth_foreground_only: bool = True
    """With predicted depth and a segmentation model: fuse only pixels segmented as non-background (depth
    networks also predict depths for open water, which would become phantom surfaces)."""
    surfel_max_normal_deg: float = bounded(30.0, gt=0, le=90)
    """A measurement merges into a surfel only if their normals differ by less than this."""
    surfel_max_dist_voxels: float = bounded(2.0, gt=0)
    """... and if it is closer than this along the ray, in voxels."""
    surfel_min_confidence: float = bounded(2.0, gt=0)
    """Surfels less confident than this are left out of the outputs (seen once, never confirmed)."""


    def __post_init__(self) -> None:
        if self.label_band_voxels > self.trunc_voxels:
            raise ValueError(f"label_band_voxels ({self.label_band_voxels}) must be <= trunc_voxels "
                             f"({self.trunc_voxels}): labels are only updated where |sdf| < trunc/2")
        f = self.label_cell_voxels
        if f & (f - 1) or self.block_resolution % f:
            raise ValueError(f"label_cell_voxels ({f}) must be a power of two dividing block_resolution "
                             f"({self.block_resolution})")
        if self.depth_min_m >= self.depth_max_m:
            raise ValueError(f"depth_min_m ({self.depth_min_m}) must be < depth_max_m ({self.depth_max_m})")


PRESETS: dict[str, FuseConfig] = {
    "default": FuseConfig(),
    "fast": FuseConfig(voxel_m=0.04, label_pixel_stride=2),
    "fine": FuseConfig(voxel_m=0.01, trunc_voxels=5.0),
    # for ~2 cm pixels at 2 cm voxels (640x480 at ~8 m): default scene 95.9% of the CAD within 2 cm (default
    # preset 96.3%), label accuracy 0.996 (0.998), about 2x faster than the first implementation. With coarser
    # pixels it loses surface and labels (320x240: label accuracy 0.88 instead of 0.97): use the default there.
    "realtime": FuseConfig(block_resolution=4, block_count=250000, color_every=4, label_pixel_stride=2),
    "surfel": FuseConfig(method="surfel"),
}


def with_overrides(cfg: FuseConfig, **kwargs: object) -> FuseConfig:
    """``cfg`` with the given (non-None) fields replaced."""
    return replace(cfg, **{k: v for k, v in kwargs.items() if v is not None})
