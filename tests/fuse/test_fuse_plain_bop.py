"""Issue 46: ``cadalign fuse`` (and the torch datasets) on a plain BOP scene folder: only ``rgb/``, ``depth/``,
``scene_camera.json`` and ``scene_gt.json`` (no objects.json, cameras.json, class/, instance/, normals/, masks)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh
from typer.testing import CliRunner

from cadalign.cli.main import app
from cadalign.errors import InputError
from cadalign.formats.class_map import load_class_map
from cadalign.fuse.run import REPORT
from cadalign.io import read_json
from cadalign.train.datasets import DepthDataset, SegmentationDataset

PLAIN = ("rgb", "depth", "scene_camera.json", "scene_gt.json")
ARGS = ["--voxel", "0.04", "--ids", "0:3", "--no-eval"]


def _plain_copy(fuse_sim: Path, dst: Path, extra: tuple[str, ...] = ()) -> Path:
    src = fuse_sim / "gt" / "sim" / "000000"
    dst.mkdir(parents=True)
    for name in PLAIN + extra:
        (shutil.copytree if (src / name).is_dir() else shutil.copy)(src / name, dst / name)
    return dst


@pytest.fixture(scope="module")
def plain(fuse_sim: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _plain_copy(fuse_sim, tmp_path_factory.mktemp("plain") / "000001")


def _fuse(args: list[str]) -> dict:
    res = CliRunner().invoke(app, ["fuse", *args])
    assert res.exit_code == 0, res.output
    return read_json(Path(args[args.index("--out") + 1]) / REPORT)


def test_fuse_runs_on_a_plain_bop_scene_geometry_only(plain: Path, fuse_sim: Path, tmp_path: Path) -> None:
    assert sorted(p.name for p in plain.iterdir()) == sorted(PLAIN)
    report = _fuse([str(plain), "--out", str(tmp_path / "plain"), *ARGS])
    ids = sorted({g["obj_id"] for gts in read_json(plain / "scene_gt.json").values() for g in gts})
    assert report["labels"] == "none" and report["classes"] == ["background", *(f"obj_{i:06d}" for i in ids)]
    assert report["timing"]["frames"] == 3 and report["map"]["mesh_vertices"] > 1000
    # the geometry is the one fused from the full simulator scene (same depth and poses)
    full = _fuse([str(fuse_sim), "--out", str(tmp_path / "full"), *ARGS])
    a = trimesh.load(tmp_path / "plain" / "mesh.ply", process=False)
    b = trimesh.load(tmp_path / "full" / "mesh.ply", process=False)
    assert full["labels"] == "gt" and len(a.vertices) == len(b.vertices)
    va, vb = (np.asarray(m.vertices)[np.lexsort(np.asarray(m.vertices).T)] for m in (a, b))  # order may differ
    np.testing.assert_allclose(va, vb, atol=1e-6)


def test_classes_file_and_masks_give_a_labelled_map(fuse_sim: Path, tmp_path: Path) -> None:
    scene = _plain_copy(fuse_sim, tmp_path / "000001", extra=("mask_visib",))
    objects = read_json(fuse_sim / "gt" / "sim" / "000000" / "objects.json")["objects"]
    classes = tmp_path / "classes.json"
    classes.write_text(json.dumps({str(o["obj_id"]): o["class_name"] for o in objects}))
    report = _fuse([str(scene), "--out", str(tmp_path / "map"), "--classes", str(classes), *ARGS])
    assert report["labels"] == "gt"
    assert set(report["classes"][1:]) == {o["class_name"] for o in objects} - {"background"}
    hist = report["map"]["label_histogram"]
    assert sum(h > 0 for h in hist[1:]) >= 2  # the masks painted the named classes into the map


def test_classes_file_must_cover_the_scene(plain: Path, tmp_path: Path) -> None:
    (tmp_path / "c.json").write_text(json.dumps({"1": "valve"}))
    with pytest.raises(InputError, match=r"c.json names no class for object ids \[2"):
        load_class_map(plain, tmp_path / "c.json")


def test_torch_depth_dataset_reads_a_plain_scene(plain: Path) -> None:
    ds = DepthDataset(plain)
    item = ds[0]
    assert item["image"].shape[0] == 3 and float(item["depth"].max()) > 0
    assert ds.classes.names[0] == "background" and len(ds.classes.names) > 1


def test_segmentation_on_a_plain_scene_says_it_has_no_labels(plain: Path) -> None:
    with pytest.raises(InputError, match=r"000001 has no ground-truth labels .* add the BOP visible masks"):
        SegmentationDataset(plain)[0]
