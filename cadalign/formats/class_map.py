"""The class map of a BOP scene: class names and each ``obj_id``'s class index (``objects.json``, a classes file, or
one class per object id of a plain BOP scene). Read by training, inference and fusion; no torch."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from cadalign.errors import InputError
from cadalign.io import read_json


@dataclass(frozen=True)
class ClassMap:
    names: tuple[str, ...]
    """Class names; index 0 is background."""
    class_of_obj: dict[int, int]
    """BOP obj_id -> class index."""


def load_class_map(scene_dir: Path, classes: Path | None = None) -> ClassMap:
    """The class names and obj_id -> class map of a BOP scene, from (first found):

    - ``classes``: a JSON ``{obj_id: class name}`` (objects of one name share a class; "background" is 0);
    - ``scene_dir/objects.json`` (written by ``cadalign sim`` and ``cadalign build-dataset``);
    - a plain BOP scene: one class per object id of ``scene_gt.json``, named ``obj_000001`` ...

    Raises:
        InputError: an unreadable classes file, one that misses object ids of the scene, or a scene with neither
            objects.json nor scene_gt.json.
    """
    scene_dir = Path(scene_dir)
    if classes is not None:
        return _class_map_file(Path(classes), _scene_obj_ids(scene_dir))
    path = scene_dir / "objects.json"
    if path.is_file():
        data = read_json(path)
        return ClassMap(tuple(data["classes"]), {int(o["obj_id"]): int(o["class_id"]) for o in data["objects"]})
    ids = _scene_obj_ids(scene_dir)
    if ids is None:
        raise InputError(f"{scene_dir} has no class map: neither objects.json nor scene_gt.json; pass a classes "
                         "file (JSON {obj_id: class name}) or re-run the stage that wrote the scene")
    return ClassMap(("background", *(f"obj_{i:06d}" for i in ids)), {i: k + 1 for k, i in enumerate(ids)})


def _scene_obj_ids(scene_dir: Path) -> list[int] | None:
    """Sorted object ids of ``scene_gt.json``, or None without one."""
    path = scene_dir / "scene_gt.json"
    if not path.is_file():
        return None
    data = read_json(path)
    return sorted({int(g["obj_id"]) for gts in data.values() for g in gts})


def _class_map_file(path: Path, scene_ids: list[int] | None) -> ClassMap:
    data = read_json(path)
    if not isinstance(data, dict) or not all(isinstance(v, str) for v in data.values()):
        raise InputError(f"{path}: a classes file is a JSON object {{obj_id: class name}}, e.g. "
                         '{"1": "valve", "2": "structure"}; fix it')
    try:
        named = {int(k): v for k, v in data.items()}
    except ValueError:
        raise InputError(f"{path}: keys must be BOP object ids (integers), got {sorted(data)[:5]}; fix it") from None
    missing = sorted(set(scene_ids or []) - set(named))
    if missing:
        raise InputError(f"{path} names no class for object ids {missing[:10]} of the scene; add them "
                         '(e.g. "background" for objects to ignore)')
    names = ["background"]
    for oid in sorted(named):
        if named[oid] not in names:
            names.append(named[oid])
    return ClassMap(tuple(names), {oid: names.index(c) for oid, c in named.items()})
