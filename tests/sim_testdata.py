"""The tiny test scene (TOML text) and a writer for effect-list variants."""

from __future__ import annotations

from pathlib import Path

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
