"""What the benchmark sweeps run on: the size presets and the simulated clips they share.

Every clip is the embedded default scene (every water effect on) flown at 1 frame/s instead of 0.5, so
consecutive frames are ~2.9 degrees apart like a real survey (SfM needs the overlap), rendered at the
size's resolution into ``DIR/data/`` once and reused by every stage and by later runs.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cadalign.errors import ConfigError
from cadalign.io import write_text
from cadalign.sim.run import simulate
from cadalign.sim.spec import default_scene_path, load_scene

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SizeSpec:
    """How heavy a benchmark run is."""

    clip_resolution: tuple[int, int]
    """Width, height of the clip that render/fuse/refine/models run on, pixels."""
    clip_frames: int
    """Frames of that clip."""
    sfm_resolution: tuple[int, int]
    """Width, height of the SfM clip (SfM needs enough pixels for SIFT), pixels."""
    sfm_frames: int
    """Frames of the SfM clip."""
    train_steps: int
    """Optimiser steps of each small network trained by the seg/depth sweeps."""
    repeats: int
    """Default timed repeats per setting."""
    level: int
    """0 tiny, 1 small, 2 full: stages pick their knob lists by it."""


SIZES: dict[str, SizeSpec] = {
    "tiny": SizeSpec((160, 120), 6, (320, 240), 8, 3, 1, 0),
    "small": SizeSpec((320, 240), 12, (320, 240), 12, 60, 3, 1),
    "full": SizeSpec((640, 480), 24, (640, 480), 24, 150, 3, 2),
}
"""tiny: what the tests run (seconds per stage); small: minutes in all; full: what a person runs (<~1 h, 2 cores)."""


def size_spec(size: str) -> SizeSpec:
    """The :class:`SizeSpec` named ``size``; ConfigError naming the allowed ones otherwise."""
    if size not in SIZES:
        raise ConfigError(f"unknown bench size {size!r}; allowed: {', '.join(SIZES)}")
    return SIZES[size]


def bench_scene(data_dir: Path, name: str = "scene.yaml") -> Path:
    """Write the benchmark scene (the default scene, 1 frame/s) to ``data_dir/name``; returns its path.

    The file only ``extends`` the default scene (by absolute path, so it loads from any folder; the default
    scene's meshes stay relative to it). Variants are written by :func:`write_scene_variant`.
    """

    src = default_scene_path()
    if load_scene(src).trajectory.fps != 1.0:
        raise ConfigError(f"{src}: expected [trajectory] fps = 1.0; the benchmarks' frame spacing derives from it")
    return write_scene_variant(Path(data_dir) / name, src, {})


def write_scene_variant(path: Path, base: Path, changes: dict[str, Any]) -> Path:
    """Write a scene that ``extends`` ``base`` with ``changes`` (tables merge key by key, lists replace the
    base's, see :func:`cadalign.sim.spec.load_scene`), as JSON text in a ``.yaml`` file (YAML reads JSON; no
    TOML writer needed). The file is rewritten only when its text changes, so finished work keyed on it stays.

    Raises:
        ValueError: ``path`` is not a ``.yaml`` file.
    """
    path = Path(path)
    if path.suffix != ".yaml":
        raise ValueError(f"{path}: scene variants are written as .yaml")
    text = json.dumps({"extends": str(Path(base).resolve()), **changes}, indent=1) + "\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    if not path.is_file() or path.read_text() != text:
        write_text(path, text)
    return path


def simulate_clip(scene: Path, out: Path, resolution: tuple[int, int], frames: int, seed: int = 0) -> Path:
    """Simulate ``frames`` frames of ``scene`` at ``resolution`` into ``out`` (reused when finished)."""

    log.info("bench data: simulating %d frames at %dx%d into %s", frames, *resolution, out)
    return simulate(scene, out, frames=frames, resolution=resolution, seed=seed, video=False, contact_sheet=False)


@dataclass(frozen=True)
class BenchData:
    """The data folder of a benchmark run and its size; builds clips on first use."""

    root: Path
    """``DIR/data``."""
    size: SizeSpec
    """The run's size."""
    seed: int = 0
    """Simulation seed."""

    def scene(self) -> Path:
        return bench_scene(self.root)

    def _finished(self, out: Path) -> bool:
        # the folder name holds resolution, frames and seed, and the scene is fixed: skip re-validating it
        return (out / "sim_report.json").is_file() and (out / "cadalign_stage.json").is_file()

    def clip(self) -> Path:
        """The simulation folder of the render/fuse/refine/model clip."""
        w, h = self.size.clip_resolution
        out = self.root / f"clip_{w}x{h}_{self.size.clip_frames}_s{self.seed}"
        if self._finished(out):
            return out
        return simulate_clip(self.scene(), self.root / f"clip_{w}x{h}_{self.size.clip_frames}_s{self.seed}",
                             self.size.clip_resolution, self.size.clip_frames, self.seed)

    def sfm_clip(self) -> Path:
        """The simulation folder of the SfM clip."""
        w, h = self.size.sfm_resolution
        out = self.root / f"clip_{w}x{h}_{self.size.sfm_frames}_s{self.seed}"
        if self._finished(out):
            return out
        return simulate_clip(self.scene(), self.root / f"clip_{w}x{h}_{self.size.sfm_frames}_s{self.seed}",
                             self.size.sfm_resolution, self.size.sfm_frames, self.seed)

    def work(self, *parts: str) -> Path:
        """A scratch folder ``DIR/data/work/...`` (created)."""
        p = self.root.joinpath("work", *parts)
        p.mkdir(parents=True, exist_ok=True)
        return p
