"""Scene-level ground-truth files of a simulation: BOP models and the merged per-scene JSONs."""

from __future__ import annotations

from pathlib import Path

from cadalign.cad.model import CadModel
from cadalign.cad.models_info import write_model_ply_mm, write_models_info
from cadalign.cad.symmetry import Symmetry
from cadalign.raycast.bop_writer import PosedObject, merge_scene_files
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


def posed_objects(scene: SimScene) -> list[PosedObject]:
    """The scene's object instances (instance id i + 1 for object i) for the BOP writer."""
    return [PosedObject(o.name, o.obj_id, o.class_id, o.T_world_from_obj) for o in scene.objects]


def write_scene_files(scene: SimScene, scene_dir: Path) -> None:
    """Merge the per-frame records into the BOP scene JSONs plus cadalign extras (see render.bop_writer)."""
    merge_scene_files(scene_dir, posed_objects(scene), scene.spec.classes)
