"""Sensor emulation (GenLaM): layered meshes, planar panes, LiDAR, multibeam sonar and novel views.

Everything ray casts one :class:`~cadalign.emulate.mesh.LayeredMesh` (triangles + per-face colour, class,
part and pane layers) with one of two engines that agree (:mod:`cadalign.emulate.raycast_engines`): Open3D's
BVH or exact Möller–Trumbore in torch. Sources (:mod:`cadalign.emulate.sources`): a CAD scene spec, a mesh
PLY (e.g. a fused map) or one RGB-D image (:mod:`cadalign.emulate.layered_mesh`, with planar panes from
:mod:`cadalign.emulate.panes`); a plain photograph goes through :mod:`cadalign.emulate.photo` (the user's
pretrained depth / segmentation checkpoints, :mod:`cadalign.emulate.pretrained`). The stage on disk is
:func:`cadalign.emulate.run.run`; the CLI is
``cadalign emulate (lidar|sonar|view|mesh) SOURCE --out DIR [--pose P] [--look-at X] [--preset P]``.
Submodules are imported explicitly (torch and Open3D load lazily).

Example:
    >>> from cadalign.emulate import lidar, sources  # doctest: +SKIP
    >>> mesh = sources.load_source("datasets/scenes/default.toml")  # doctest: +SKIP
    >>> scan = lidar.scan(mesh, Rigid3(np.eye(3), [11, 0, 4]), lidar.PRESETS["hdl32"])  # doctest: +SKIP
    >>> scan.xyz_world.shape, scan.class_id[:5]  # doctest: +SKIP
"""
