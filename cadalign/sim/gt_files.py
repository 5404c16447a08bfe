"""Scene-level ground-truth files of a simulation: BOP models and the merged per-scene JSONs."""

from __future__ import annotations

from pathlib import Path

from cadalign.cad.model import CadModel
from cadalign.cad.models_info import write_model_ply_mm, write_models_info
from cadalign.cad.symmetry import Symmetry
from cadalign.data import bop
from cadalign.io import read_json, write_json
from cadalign.sim.scene import SimScene


def cad_models(scene: SimScene) -> dict[int, CadModel]:
    """BOP model id -> CadModel (metres) for every distinct mesh of the scene."""
    first = {}
    for obj in scene.objects:
        first.setdefault(obj.obj_id, obj)
    return {
        oid: CadModel(
            name=f"obj_{oid:06d}_{o.spec.source.split(':')[-1].split('/')[-1]}",
            vertices_m=scene.models[oid].vertices,
            faces=scene.models[oid].faces,
            unit=o.spec.unit or "m",
            class_name=scene.spec.classes[o.class_id],
            symmetry=Symmetry.from_name(scene.model_symmetry[oid]),
        )
        for oid, o in sorted(first.items())
    }


def write_models(scene: SimScene, models_dir: Path) -> Path:
    """``models_dir/obj_XXXXXX.ply`` (mm) and ``models_info.json`` (BOP, with symmetries)."""
    models = cad_models(scene)
    for oid, model in models.items():
        write_model_ply_mm(model, Path(models_dir) / f"obj_{oid:06d}.ply")
    write_models_info(models, Path(models_dir) / "models_info.json")
    return Path(models_dir)


def write_scene_files(scene: SimScene, scene_dir: Path, depth_scale: float) -> None:
    """Merge the per-frame records into scene_camera/scene_gt/scene_gt_info.json plus cadalign extras.

    Extras: ``cameras.json`` (per frame ``T_cam_from_world`` in metres and K, the same format the
    SfM stage writes) and ``objects.json`` (each instance's name, model id, class and world pose).
    """
    scene_dir = Path(scene_dir)
    records = {int(p.stem): read_json(p) for p in sorted((scene_dir / "frames_json").glob("*.json"))}
    write_json(scene_dir / "scene_camera.json", {str(k): r["camera"] for k, r in records.items()})
    write_json(scene_dir / "scene_gt.json", {str(k): r["gt"] for k, r in records.items()})
    write_json(scene_dir / "scene_gt_info.json", {str(k): r["gt_info"] for k, r in records.items()})
    cams = {}
    for k, r in records.items():
        c = r["camera"]
        cams[bop.frame_name(k)] = {
            "K": c["cam_K"],
            "width": c["width"],
            "height": c["height"],
            "R_cam_from_world": c["cam_R_w2c"],
            "t_cam_from_world_m": [t / bop.M_TO_MM for t in c["cam_t_w2c"]],
        }
    write_json(scene_dir / "cameras.json", {"frames": cams})
    objects = [
        {
            "index": i,
            "name": o.name,
            "obj_id": o.obj_id,
            "class_id": o.class_id,
            "class_name": scene.spec.classes[o.class_id],
            "R_world_from_obj": o.T_world_from_obj.R.ravel().tolist(),
            "t_world_from_obj_m": o.T_world_from_obj.t.tolist(),
        }
        for i, o in enumerate(scene.objects)
    ]
    write_json(
        scene_dir / "objects.json",
        {
            "classes": list(scene.spec.classes),
            "objects": objects,
            "gt_index_to_object": {str(k): r["object_index"] for k, r in records.items()},
        },
    )
