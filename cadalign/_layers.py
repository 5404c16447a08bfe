"""The layer order of the package, lowest first: a module imports only from its own layer and the layers below.

This is the one place the order is written down (STYLE.md, "Layout"); ``tests/test_architecture.py`` checks every
import of every module against it, imports inside functions included, and checks that the import graph has no
cycles. A room is a module or a package prefix; a module belongs to the room with the longest matching prefix.

Some rooms sit where STYLE.md's layout will put them, not where their files are today (moving the files is a
later, mechanical step): the camera and edge refinement (``render/camera_refine``, ``render/edge_refine``) are
the align stage's; the image preparation shared by SfM, training and inference (``data/image_prep``) is a stage
helper; the metric functions of ``eval/`` (``*_metrics``, ``pose_symmetry`` and ``pose_eval``, the BOP scoring
shared by training, inference and ``cadalign eval``) are the metrics layer.
"""

from __future__ import annotations

LAYERS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("base", ("cadalign", "cadalign._version", "cadalign._layers", "cadalign.types", "cadalign.errors",
              "cadalign.io", "cadalign.config", "cadalign.geometry")),
    ("formats", ("cadalign.formats", "cadalign.data")),
    ("cad", ("cadalign.cad",)),
    ("raycast", ("cadalign.render",)),
    ("metrics", ("cadalign.eval.seg_metrics", "cadalign.eval.depth_metrics", "cadalign.eval.pose_metrics",
                 "cadalign.eval.dataset_metrics", "cadalign.eval.map_metrics", "cadalign.eval.sfm_metrics",
                 "cadalign.eval.pose_symmetry", "cadalign.eval.pose_eval")),
    ("stages", ("cadalign.sim", "cadalign.sfm", "cadalign.align", "cadalign.render.camera_refine",
                "cadalign.render.edge_refine", "cadalign.render.verify", "cadalign.render.verify_config",
                "cadalign.render.verify_evidence", "cadalign.render.verify_run", "cadalign.build_dataset",
                "cadalign.scale", "cadalign.data.image_prep", "cadalign.models", "cadalign.train", "cadalign.infer",
                "cadalign.fuse", "cadalign.emulate")),
    ("top", ("cadalign.eval", "cadalign.demo", "cadalign.demo_stages", "cadalign.cli")),
)
"""(layer name, rooms) pairs, lowest layer first."""

KNOWN_UPWARD_IMPORTS: frozenset[tuple[str, str]] = frozenset({
    # The dataset build scores itself against the simulator's truth and writes its HTML report, both of which
    # live in the evaluation layer; the scoring moves to metrics/ and the report to the CLI's caller later.
    ("cadalign.build_dataset", "cadalign.eval.dataset_eval"),
    # SfM's metrics read cameras.json centres and draw the trajectory plot with the SfM stage's report helpers;
    # the plot and the cameras.json reader belong below (formats/, an evaluate/ figure), not in sfm/.
    ("cadalign.eval.sfm_metrics", "cadalign.sfm.report"),
})
"""(importer, imported) pairs that break the layer order today; a new one fails the architecture test. Shrink it."""


def layer_of(module: str) -> int | None:
    """Index in :data:`LAYERS` of the room with the longest prefix of ``module`` (None: no room holds it).

    >>> layer_of("cadalign.geometry.camera"), layer_of("cadalign.eval.pose_metrics"), layer_of("cadalign.eval.bench")
    (0, 4, 6)
    >>> layer_of("numpy") is None
    True
    """
    best: tuple[int, int] | None = None
    for i, (_, rooms) in enumerate(LAYERS):
        for room in rooms:
            if (module == room or module.startswith(room + ".")) and (best is None or len(room) > best[1]):
                best = (i, len(room))
    return None if best is None else best[0]
