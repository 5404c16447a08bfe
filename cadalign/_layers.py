"""The layer order of the package, lowest first: a module imports only from its own layer and the layers below.

This is the one place the order is written down (STYLE.md, "Layout"; ``docs/architecture.md`` draws it);
``tests/test_architecture.py`` checks every import of every module against it, imports inside functions included,
and checks that the import graph has no cycles. A room is a module or a package prefix; a module belongs to the
room with the longest matching prefix.

- base: shared types, errors, atomic I/O, strict configs, geometry (the only projection, rotation error, IoUs);
- formats: the code that knows file formats (BOP, COCO, calibration files, bags, STEP, TUM, the class map, dataset
  splits, the pieces of the HTML reports);
- cad: CAD models (loading in a unit, symmetries, models_info);
- raycast: the CAD ray caster shared by sim, build, align, infer and emulate, and the writer of its frames as BOP
  files;
- metrics: pure metric functions (pose, BOP scores with symmetries, seg, depth, dataset, map) and ``CroppedMask``;
- stages: sim (with the scene's CAD structure, ``load_structure``), sfm (with the image preparation shared by
  training and inference), align (with camera/edge refinement and image verification), build (the dataset builder
  and its scale-out), models, train, infer, fuse, emulate; a stage may use another stage;
- testing: the tiny scene and the ground-truth oracle detector (tests, the demo and ``--oracle-gt`` use them);
- top: ``cadalign eval`` (evaluate), the benchmarks (bench), the demo and the CLI.
"""

from __future__ import annotations

LAYERS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("base", ("cadalign", "cadalign._version", "cadalign._layers", "cadalign.types", "cadalign.errors",
              "cadalign.io", "cadalign.config", "cadalign.geometry")),
    ("formats", ("cadalign.formats",)),
    ("cad", ("cadalign.cad",)),
    ("raycast", ("cadalign.raycast",)),
    ("metrics", ("cadalign.metrics",)),
    ("stages", ("cadalign.sim", "cadalign.sfm", "cadalign.align", "cadalign.build", "cadalign.models",
                "cadalign.train", "cadalign.infer", "cadalign.fuse", "cadalign.emulate")),
    ("testing", ("cadalign.testing",)),
    ("top", ("cadalign.evaluate", "cadalign.bench", "cadalign.demo", "cadalign.cli")),
)
"""(layer name, rooms) pairs, lowest layer first."""

KNOWN_UPWARD_IMPORTS: frozenset[tuple[str, str]] = frozenset()
"""(importer, imported) pairs that break the layer order; a new one fails the architecture test. Empty: keep it so."""


HEAVY_DEPENDENCIES: frozenset[str] = frozenset({
    "torch", "torchvision", "kornia", "open3d", "pycolmap", "ray", "transformers", "safetensors", "OCP", "matplotlib",
    "cv2", "scipy", "trimesh", "pyrender", "pymeshlab", "rosbags", "cascadio", "imageio",
})
"""Third-party packages slow to import (or optional) that a module may import inside a function, with a ``# lazy:``
reason on the line (or the line above): so a path that does not need them (``cadalign --help``, a CPU-only or
torch-free command, ``import cadalign.geometry``) does not pay for them. Every other import stands at module top.
``cv2``, ``scipy`` and ``trimesh`` are lazy only where they would slow ``cadalign --help``."""


def layer_of(module: str) -> int | None:
    """Index in :data:`LAYERS` of the room with the longest prefix of ``module`` (None: no room holds it).

    >>> layer_of("cadalign.geometry.camera"), layer_of("cadalign.metrics.pose"), layer_of("cadalign.bench.registry")
    (0, 4, 7)
    >>> layer_of("numpy") is None
    True
    """
    best: tuple[int, int] | None = None
    for i, (_, rooms) in enumerate(LAYERS):
        for room in rooms:
            if (module == room or module.startswith(room + ".")) and (best is None or len(room) > best[1]):
                best = (i, len(room))
    return None if best is None else best[0]
