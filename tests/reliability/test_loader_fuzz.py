"""Loader fuzzing: byte-level corruption and truncation of real files raises only the project's errors.

The scene loader (a real scene TOML), the CAD loader (a real UUV Simulator COLLADA file and PLY/OBJ/STL
exports of it) and the BOP reader (scene_gt.json, scene_camera.json and a depth PNG of a tiny
simulated scene) must either load the damaged file or raise a :class:`~cadalign.errors.CadalignError`,
never a KeyError, TypeError, IndexError, UnicodeDecodeError ..., and emit no RuntimeWarning. Runs are
derandomized (the same examples every time) and small; raise ``CADALIGN_FUZZ_EXAMPLES`` for a longer hunt
and set ``CADALIGN_FUZZ_RANDOM=1`` for fresh random examples.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cadalign.cad import load_cad
from cadalign.errors import CadalignError
from cadalign.formats.bop import BopScene
from cadalign.sim.spec import load_scene

pytestmark = pytest.mark.filterwarnings("error::RuntimeWarning")  # a damaged file must not emit NaN/overflow noise
N = int(os.environ.get("CADALIGN_FUZZ_EXAMPLES", "40"))
FUZZ = settings(max_examples=N, deadline=None, derandomize="CADALIGN_FUZZ_RANDOM" not in os.environ, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
REPO = Path(__file__).resolve().parents[2]
SMALL_DAE = "rov_bop_panel/meshes/SmallValve.dae"
#: Values a damaged JSON/TOML entry is swapped for: wrong types, non-finite, huge and empty values.
ODD_VALUES: list[Any] = [None, True, -1, 0, 1e308, float("nan"), "x", [], {}, [1, 2], [[1.0] * 9], 2**70]


@st.composite
def corrupted(draw: st.DrawFn, data: bytes) -> bytes:
    """``data`` truncated, with bytes overwritten, inserted or deleted (one of them)."""
    n = len(data)
    kind = draw(st.sampled_from(["truncate", "overwrite", "insert", "delete"]))
    if kind == "truncate":
        return data[: draw(st.integers(0, n - 1))]
    if kind == "overwrite":
        out = bytearray(data)
        for i, v in draw(st.lists(st.tuples(st.integers(0, n - 1), st.integers(0, 255)), min_size=1, max_size=8)):
            out[i] = v
        return bytes(out)
    i = draw(st.integers(0, n - 1))
    if kind == "insert":
        return data[:i] + draw(st.binary(min_size=1, max_size=32)) + data[i:]
    return data[:i] + data[draw(st.integers(i + 1, min(n, i + 256))) :]


def _paths(obj: Any, prefix: tuple = ()) -> list[tuple]:
    """Every key/index path into a JSON value."""
    out = [prefix]
    if isinstance(obj, dict):
        for k, v in obj.items():
            out += _paths(v, (*prefix, k))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            out += _paths(v, (*prefix, i))
    return out


@st.composite
def mutated_json(draw: st.DrawFn, data: Any) -> bytes:
    """``data`` with one value (or key) replaced by an odd value, or deleted, serialised as JSON."""
    data = json.loads(json.dumps(data))
    path = draw(st.sampled_from(_paths(data)[1:]))
    parent = data
    for key in path[:-1]:
        parent = parent[key]
    if draw(st.booleans()):
        parent[path[-1]] = draw(st.sampled_from(ODD_VALUES))
    else:
        del parent[path[-1]]
    return json.dumps(data).encode()


def _survives(load: Callable[[], Any]) -> None:
    """``load`` returns or raises a CadalignError; anything else fails the test (pytest shows it)."""
    try:
        load()
    except CadalignError:
        pass


# ------------------------------------------------------------------------------------------------------- scene


SCENE_BYTES = (REPO / "datasets" / "scenes" / "default.toml").read_bytes()


@FUZZ
@given(data=corrupted(SCENE_BYTES))
def test_scene_loader_survives_corruption(data: bytes) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "default.toml"
        path.write_bytes(data)
        _survives(lambda: load_scene(path))


@FUZZ
@given(data=mutated_json(tomllib.loads(SCENE_BYTES.decode())))
def test_scene_loader_survives_odd_values(data: bytes) -> None:
    """The same scene as JSON (the loader reads TOML, YAML and JSON) with one value swapped or removed."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "default.json"
        path.write_bytes(data)
        _survives(lambda: load_scene(path))


SFM_YAML = b"""# an SfM stage config as a user writes it
frames:
  sampling: fps
  fps: 2.0
  blur_ratio: 0.35
  mask_rects: [[0, 0, 40, 12]]
features:
  max_num_features: 4096
matching:
  pairing: sequential
  overlap: 8
"""


@FUZZ
@given(data=corrupted(SFM_YAML))
def test_stage_config_loader_survives_corruption(data: bytes) -> None:
    from cadalign.config import resolve
    from cadalign.sfm.config import PRESETS, SfMConfig

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "sfm.yaml"
        path.write_bytes(data)
        _survives(lambda: resolve(SfMConfig, PRESETS, "fast", path))


def test_scene_intact_loads() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "default.toml"
        path.write_bytes(SCENE_BYTES)
        assert load_scene(path).name


# --------------------------------------------------------------------------------------------------------- CAD


@pytest.fixture(scope="module")
def cad_files(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, bytes]:
    """The bytes of a small real COLLADA file and of PLY (binary), OBJ and STL exports of its mesh."""
    root = tmp_path_factory.mktemp("cad_fuzz")
    dae = root / "SmallValve.dae"
    shutil.copyfile(shared_data / "uuv_subsea_cad" / SMALL_DAE, dae)
    model = load_cad(dae, unit="m")
    mesh = trimesh.Trimesh(model.vertices_m, model.faces, process=False)
    out = {"dae": dae.read_bytes()}
    for ext in ("ply", "obj", "stl"):
        mesh.export(root / f"valve.{ext}")
        out[ext] = (root / f"valve.{ext}").read_bytes()
    return out


@pytest.mark.parametrize("ext", ["dae", "ply", "obj", "stl"])
def test_cad_loader_survives_corruption(cad_files: dict[str, bytes], ext: str) -> None:
    @FUZZ
    @given(data=corrupted(cad_files[ext]))
    def check(data: bytes) -> None:
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / f"valve.{ext}"
            path.write_bytes(data)
            _survives(lambda: load_cad(path))

    check()


def test_cad_files_load_intact(cad_files: dict[str, bytes], tmp_path: Path) -> None:
    sizes = {}
    for ext, data in cad_files.items():
        (tmp_path / f"v.{ext}").write_bytes(data)
        sizes[ext] = load_cad(tmp_path / f"v.{ext}", unit="m").extent
    for ext in ("ply", "obj", "stl"):
        np.testing.assert_allclose(sizes[ext], sizes["dae"], rtol=1e-6)


# --------------------------------------------------------------------------------------------------------- BOP


def _read_all(scene_dir: Path) -> None:
    scene = BopScene(scene_dir)
    for im_id in scene.ids:
        frame = scene.frame(im_id)
        depth = scene.depth_m(im_id)
        assert depth.shape == (frame.camera.height, frame.camera.width)
        for g in range(len(frame.instances)):
            scene.mask(im_id, g)


def _fuzz_bop_file(tiny_bop: Path, name: str, data: bytes) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        scene_dir = Path(tmp) / "000000"
        shutil.copytree(tiny_bop, scene_dir, ignore=shutil.ignore_patterns("class", "instance", "normals", "rgb"))
        (scene_dir / name).write_bytes(data)
        _survives(lambda: _read_all(scene_dir))


@pytest.mark.parametrize("name", ["scene_gt.json", "scene_camera.json", "scene_gt_info.json", "depth/000001.png"])
def test_bop_reader_survives_byte_corruption(tiny_bop: Path, name: str) -> None:
    @FUZZ
    @given(data=corrupted((tiny_bop / name).read_bytes()))
    def check(data: bytes) -> None:
        _fuzz_bop_file(tiny_bop, name, data)

    check()


@pytest.mark.parametrize("name", ["scene_gt.json", "scene_camera.json", "scene_gt_info.json"])
def test_bop_reader_survives_odd_json_values(tiny_bop: Path, name: str) -> None:
    @FUZZ
    @given(data=mutated_json(json.loads((tiny_bop / name).read_text())))
    def check(data: bytes) -> None:
        _fuzz_bop_file(tiny_bop, name, data)

    check()


def test_bop_intact_scene_reads(tiny_bop: Path) -> None:
    _read_all(tiny_bop)


def test_stage_config_intact_loads(tmp_path: Path) -> None:
    from cadalign.config import resolve
    from cadalign.sfm.config import PRESETS, SfMConfig

    (tmp_path / "sfm.yaml").write_bytes(SFM_YAML)
    cfg = resolve(SfMConfig, PRESETS, "fast", tmp_path / "sfm.yaml")
    assert cfg.matching.overlap == 8 and cfg.frames.mask_rects == ((0, 0, 40, 12),)
