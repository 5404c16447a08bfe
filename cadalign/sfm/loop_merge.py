"""Closing loops in a finished model instead of mapping again.

After pose-guided loop pairs are matched (:func:`cadalign.sfm.refine.model_loop_pairs`), the first model already
holds every frame; what the new matches add is that a point seen at the end of an orbit is the same point seen
at its start. :func:`merge_loop_tracks` gives the model exactly that: it triangulates the new correspondences
(continuing existing tracks), merges tracks that now share observations, and runs COLMAP's iterative global
bundle adjustment, the steps the incremental mapper itself runs after registering images. A second mapping
from scratch costs as much as the first pass; this costs one global adjustment.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any


def merge_loop_tracks(rec: Any, database: Path, opts: Any, loss_scale_px: float | None = None) -> dict[str, int]:
    """Add ``database``'s correspondences (loop pairs included) to the tracks of ``rec`` in place, merge the tracks
    they join, and re-adjust ``rec`` globally; ``opts``: the mapping's ``IncrementalPipelineOptions``.
    ``loss_scale_px``: a Cauchy loss of this scale in the adjustment (None: the mapper's own loss); the new
    observations are not filtered yet, so a robust loss keeps the wrong ones from moving the poses.

    Returns observations added by triangulation and merged tracks, and the points before and after.
    """
    import pycolmap  # lazy: heavy dependency (pycolmap)

    cache_opts = pycolmap.DatabaseCacheOptions()
    cache_opts.min_num_matches = opts.min_num_matches
    if opts.image_names:
        cache_opts.image_names = set(opts.image_names)
    with pycolmap.Database.open(database) as db:
        cache = pycolmap.DatabaseCache.create(db, cache_opts)
    points_before = rec.num_points3D()
    mapper = pycolmap.IncrementalMapper(cache)
    mapper.begin_reconstruction(rec)
    tri = opts.get_triangulation()
    triangulated = sum(mapper.triangulate_image(tri, image_id) for image_id in rec.reg_image_ids())
    merged = mapper.complete_and_merge_tracks(tri)
    ba = opts.get_global_bundle_adjustment()
    if loss_scale_px is not None:
        ba.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
        ba.ceres.loss_function_scale = loss_scale_px
    mapper.iterative_global_refinement(opts.ba_global_max_refinements, opts.ba_global_max_refinement_change,
                                       opts.get_mapper(), ba, tri,
                                       normalize_reconstruction=False)
    mapper.end_reconstruction(False)
    return {"observations_triangulated": int(triangulated), "tracks_completed_or_merged": int(merged),
            "points_before": int(points_before), "points_after": int(rec.num_points3D())}
