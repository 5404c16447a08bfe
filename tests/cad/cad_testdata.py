"""Shared test data for the CAD tests (imported by the test modules; not a conftest so the name is unique)."""

from __future__ import annotations

import numpy as np

#: The UUV Simulator COLLADA meshes, relative to ``shared/data/uuv_subsea_cad``.
UUV_DAE = (
    "rov_bop_panel/meshes/BOP_Panel.dae",
    "rov_bop_panel/meshes/Valve.dae",
    "rov_bop_panel/meshes/SmallValve.dae",
    "hot_stab/meshes/HotStab.dae",
    "torque_tool/meshes/TorqueTool.dae",
    "t_bar_fork_tool/meshes/TBarForkTool.dae",
    "bop_panel/meshes/Valve.dae",
)


def unit_cube_mesh() -> tuple[np.ndarray, np.ndarray]:
    """The unit cube [0, 1]^3 as 8 vertices and 12 outward-facing triangles."""
    v = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=np.float64)
    f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], dtype=np.int64)
    return v, f
