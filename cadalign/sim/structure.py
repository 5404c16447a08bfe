"""The CAD structure of a scene: its posed parts, their models and the class names (``load_structure``).

A scene spec (TOML/YAML: parts, world poses, classes, as ``cadalign sim`` reads it) or one CAD mesh file (one part,
class ``structure``) -> :class:`Structure`. The dataset builder, inference, the tracker, the CLI and the benchmarks
read the CAD through it. It lives beside the scene spec it parses (``cadalign.sim.spec``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from cadalign.cad import load_cad
from cadalign.cad.model import CadModel
from cadalign.raycast.bop_writer import PosedObject
from cadalign.raycast.core import RenderMesh
from cadalign.sim.gt_files import cad_models, posed_objects
from cadalign.sim.scene import build_scene
from cadalign.sim.spec import load_scene
from cadalign.types import Rigid3

SPEC_SUFFIXES = (".toml", ".yaml", ".yml")


@dataclass(frozen=True)
class Structure:
    """The CAD structure: posed instances, their models (model frame, metres) and the class names."""

    objects: tuple[PosedObject, ...]
    models: dict[int, CadModel]
    class_names: tuple[str, ...]
    movable: frozenset[str] = frozenset()
    """Names of the parts the scene declares movable (``movable = true``): not part of the rigid assembly."""

    def render_meshes(self, *, movable: bool | None = False) -> list[RenderMesh]:
        """The parts placed in the world as ray-cast instances (instance id ``i + 1`` for object ``i``).
        ``movable``: False, the rigid assembly only (without the movable parts); True, the movable parts only;
        None, all parts."""
        return [RenderMesh(o.T_world_from_obj.apply(self.models[o.obj_id].vertices_m), self.models[o.obj_id].faces,
                           i + 1, o.class_id) for i, o in enumerate(self.objects)
                if movable is None or (o.name in self.movable) == movable]


def load_structure(cad: Path, unit: str | None = None) -> Structure:
    """The structure from a scene spec (parts, poses, classes) or from one CAD mesh file."""
    cad = Path(cad)
    if cad.suffix.lower() in SPEC_SUFFIXES:
        spec = load_scene(cad)
        scene = build_scene(spec, cad, width=8, height=8)
        return Structure(tuple(posed_objects(scene)), cad_models(scene), tuple(spec.classes),
                         frozenset(o.name for o in spec.objects if o.movable))
    model = load_cad(cad, unit, class_name="structure")
    return Structure((PosedObject(model.name, 1, 1, Rigid3.identity()),), {1: model}, ("background", "structure"))
