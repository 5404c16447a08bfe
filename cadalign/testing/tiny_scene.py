"""The tiny test scene: its TOML text, writers for effect-list and capture variants, and one call that simulates it.

Seeded (``seed = 7``), 160x120 px, an orbit round a block, a procedural valve and a real UUV hot stab (the latter
read from ``data:uuv_subsea_cad``, so ``$CADALIGN_DATA_DIR`` or ``../shared/data`` must hold it). The test folders'
conftests make their session fixtures with :func:`simulate_tiny`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cadalign.build.report import true_cad_from_sfm
from cadalign.io import read_json, write_json
from cadalign.sim.run import simulate

TINY_SCENE = """
name = "tiny"
seed = 7
classes = ["background", "structure", "valve", "hot_stab"]
effects = {effects}
ambient = 0.5

[camera]
width = 160
height = 120
hfov_deg = 65.0

[trajectory]
kind = "orbit"
center = [0.0, 0.0, 0.5]
radius_m = 3.2
height_m = 1.6
speed_mps = 0.5
fps = 1.0
frames = {frames}
jitter_m = 0.0
shutter_s = 0.02

[water]
jerlov = "II"

[seabed]
size_m = 12.0
relief_m = 0.05
texture = "sediment"

[[objects]]
name = "block"
source = "procedural:box"
class_name = "structure"
texture = "painted_steel"
size_m = [1.2, 0.8, 0.6]
position = [0.0, 0.0, 0.3]

[[objects]]
name = "valve"
source = "procedural:valve_a"
class_name = "valve"
texture = "rust"
position = [-1.0, 0.9, 0.0]

[[objects]]
name = "uuv_hot_stab"
source = "data:uuv_subsea_cad/hot_stab/meshes/HotStab.dae"
unit = "m"
class_name = "hot_stab"
texture = "yellow_paint"
position = [0.9, -0.8, 0.1]
rpy_deg = [0.0, 0.0, 30.0]
"""

ALL_EFFECTS = [
    "artificial_light", "attenuation", "forward_scatter", "backscatter", "marine_snow",
    "motion_blur", "vignetting", "low_light",
]


def write_tiny_scene(path: Path, *, effects: list[str], frames: int = 4) -> Path:
    """Write the tiny scene TOML with the given effect list; returns its path."""
    path.write_text(TINY_SCENE.format(effects=repr(list(effects)).replace("'", '"'), frames=frames))
    return path


def simulate_tiny(root: Path, *, frames: int, effects: list[str] | tuple[str, ...] = (),
                  resolution: tuple[int, int] | None = None, video: bool = False) -> Path:
    """Write ``root/tiny.toml`` (:func:`write_tiny_scene`) and simulate it into ``root/sim``; returns ``root/sim``
    (``frames/``, ``gt/sim/000000`` the BOP scene, ``gt/models``). No contact sheet."""
    scene = write_tiny_scene(Path(root) / "tiny.toml", effects=list(effects), frames=frames)
    return simulate(scene, Path(root) / "sim", resolution=resolution, video=video, contact_sheet=False)


def write_build_capture(path: Path, *, effects: list[str], frames: int) -> Path:
    """The tiny scene made a dataset builder's capture: 320x240, a closer orbit round a bigger block (so the
    structure, not the seabed, holds most SfM points) with the valve and the hot stab on it."""
    spec = write_tiny_scene(path, effects=effects, frames=frames)
    text = spec.read_text().replace("width = 160", "width = 320").replace("height = 120", "height = 240")
    for a, b in (("speed_mps = 0.5", "speed_mps = 0.3"), ("radius_m = 3.2", "radius_m = 3.0"),
                 ("size_m = [1.2, 0.8, 0.6]", "size_m = [2.0, 1.4, 1.2]"), ("position = [0.0, 0.0, 0.3]",
                 "position = [0.0, 0.0, 0.0]"), ("center = [0.0, 0.0, 0.5]", "center = [0.0, 0.0, 0.8]"),
                 ("position = [-1.0, 0.9, 0.0]", "position = [-0.6, 0.0, 1.2]"),
                 ("position = [0.9, -0.8, 0.1]", "position = [0.6, -0.3, 1.2]")):
        text = text.replace(a, b)
    spec.write_text(text)
    return spec


def write_picks_from_truth(sfm_dir: Path, sim: Path, path: Path, noise_m: float = 0.02) -> Path:
    """A picks file (``--init``) of four CAD corners of the tiny block scenes and where the SfM model in
    ``sfm_dir`` puts them, from the simulation's true cameras, with ``noise_m`` of seeded noise on the
    CAD side (as a user's clicks would have)."""
    true = true_cad_from_sfm(read_json(sfm_dir / "cameras.json")["frames"],
                             read_json(sim / "gt" / "sim" / "000000" / "cameras.json")["frames"])
    cad_pts = np.array([[1.0, 0.7, 1.2], [-1.0, -0.7, 1.2], [1.0, -0.7, 0.0], [-1.0, 0.7, 0.0]])
    clicked = cad_pts + np.random.default_rng(0).normal(0, noise_m, cad_pts.shape) if noise_m else cad_pts
    sfm_pts = true.inverse().apply(clicked)
    pairs = [{"sfm": s.tolist(), "cad_m": c.tolist()} for s, c in zip(sfm_pts, cad_pts, strict=True)]
    write_json(path, {"pairs": pairs})
    return path
