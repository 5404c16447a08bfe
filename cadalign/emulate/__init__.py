"""Sensor emulation (GenLaM): layered meshes, planar panes, LiDAR, multibeam sonar and novel views.

Everything ray casts one :class:`~cadalign.emulate.mesh.LayeredMesh` (triangles + per-face colour, class,
part and pane layers) with one of two engines that agree (:mod:`cadalign.emulate.raycast_engines`): Open3D's
BVH or exact Möller–Trumbore in torch. Sources (:mod:`cadalign.emulate.sources`): a CAD scene spec, a mesh
PLY (e.g. a fused map) or one RGB-D image (:mod:`cadalign.emulate.layered_mesh`). The stage on disk is
:func:`cadalign.emulate.run.run`. Submodules are imported explicitly (torch and Open3D load lazily).
"""
