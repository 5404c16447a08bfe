"""SDF parsing of the UUV Simulator models: parts, poses and the Euler convention."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cadalign.cad import load_cad, load_sdf_model, rpy_to_matrix
from cadalign.errors import InputError

# (link, mesh, x y z, roll pitch yaw) as written in rov_bop_panel/model.sdf
ROV_BOP_PANEL = [
    ("panel", "BOP_Panel", (0, 0, 0), (0, 0, 0)),
    ("valve_1", "Valve", (-0.15, -0.2, 0.18), (0, 0, 1.57)),
    ("valve_2", "Valve", (0.15, -0.2, 0.18), (0, 0, 1.57)),
    ("valve_3", "Valve", (-0.15, 0, 0.18), (0, 0, 1.57)),
    ("valve_4", "SmallValve", (0, -0.2, 0.14), (0, 0, 0)),
    ("valve_5", "SmallValve", (0, 0, 0.14), (0, 0, 0)),
]


def test_rov_bop_panel_parts_and_poses(uuv_cad_dir: Path) -> None:
    parts = load_sdf_model(uuv_cad_dir / "rov_bop_panel/model.sdf")
    assert [p[0] for p in parts] == [p[0] for p in ROV_BOP_PANEL]
    for (name, model, T), (ename, mesh, xyz, rpy) in zip(parts, ROV_BOP_PANEL, strict=True):
        assert name == ename and model.name == mesh and model.unit == "m"
        assert model.source == uuv_cad_dir / "rov_bop_panel/meshes" / f"{mesh}.dae"
        np.testing.assert_allclose(T.t, xyz, atol=1e-12)
        np.testing.assert_allclose(T.R, rpy_to_matrix(*rpy), atol=1e-12)
    valve_R = parts[1][2].R
    np.testing.assert_allclose(valve_R @ [1.0, 0, 0], [np.cos(1.57), np.sin(1.57), 0], atol=1e-12)  # yaw about z
    assert parts[1][1] is parts[2][1]  # the same mesh file is loaded once
    # the valves sit on the panel's front face (panel is 0.36 m tall; valves at z = 0.14-0.18 m)
    assert parts[0][1].extent.max() == pytest.approx(0.8, abs=1e-3)


def test_rpy_convention_is_extrinsic_xyz() -> None:
    rng = np.random.default_rng(0)
    for r, p, y in rng.uniform(-np.pi, np.pi, size=(20, 3)):
        Rx = Rotation.from_rotvec([r, 0, 0]).as_matrix()
        Ry = Rotation.from_rotvec([0, p, 0]).as_matrix()
        Rz = Rotation.from_rotvec([0, 0, y]).as_matrix()
        np.testing.assert_allclose(rpy_to_matrix(r, p, y), Rz @ Ry @ Rx, atol=1e-12)
        np.testing.assert_allclose(rpy_to_matrix(r, p, y), Rotation.from_euler("xyz", [r, p, y]).as_matrix(),
                                   atol=1e-12)


def test_inertial_pose_ignored_and_scale_applied(uuv_cad_dir: Path, tmp_path: Path) -> None:
    # hot_stab: the only non-zero <pose> is the <inertial>'s, which must not move the mesh
    (name, model, T), = load_sdf_model(uuv_cad_dir / "hot_stab/model.sdf")
    assert name == "hot_stab" and model.name == "HotStab"
    np.testing.assert_array_equal(T.matrix(), np.eye(4))
    # bop_panel: VentilBlock meshes are absent from the snapshot; valves are scaled 1.0 1.2 1.2
    with pytest.raises(InputError, match=r"VentilBlock\.obj' not found .*skip_missing=True"):
        load_sdf_model(uuv_cad_dir / "bop_panel/model.sdf")
    parts = load_sdf_model(uuv_cad_dir / "bop_panel/model.sdf", skip_missing=True)
    assert parts and all("valve" in n for n, _, _ in parts)
    base = load_cad(uuv_cad_dir / "bop_panel/meshes/Valve.dae")
    np.testing.assert_allclose(parts[0][1].extent, base.extent * [1.0, 1.2, 1.2], rtol=1e-9)


def _write_model(tmp_path: Path, uuv_cad_dir: Path, link_xml: str) -> Path:
    model_dir = tmp_path / "toy"
    (model_dir / "meshes").mkdir(parents=True)
    shutil.copy(uuv_cad_dir / "rov_bop_panel/meshes/Valve.dae", model_dir / "meshes" / "Valve.dae")
    sdf = model_dir / "model.sdf"
    sdf.write_text(f'<?xml version="1.0"?><sdf version="1.6"><model name="toy">{link_xml}</model></sdf>')
    return sdf


def test_multiple_visuals_and_primitives(uuv_cad_dir: Path, tmp_path: Path) -> None:
    mesh = "<geometry><mesh><uri>model://toy/meshes/Valve.dae</uri></mesh></geometry>"
    sdf = _write_model(tmp_path, uuv_cad_dir, (
        '<link name="l"><pose>1 0 0 0 0 0</pose>'
        f'<visual name="a">{mesh}</visual>'
        f'<visual name="b"><pose>0 0 1 0 1.5707963267948966 0</pose>{mesh}</visual>'
        '<visual name="tag"><geometry><box><size>1 1 1</size></box></geometry></visual></link>'))
    parts = load_sdf_model(sdf)
    assert [p[0] for p in parts] == ["l/a", "l/b"]
    np.testing.assert_allclose(parts[1][2].t, [1, 0, 1], atol=1e-12)
    np.testing.assert_allclose(parts[1][2].R @ [0, 0, 1.0], [1, 0, 0], atol=1e-12)  # pitch +90: z -> x


@pytest.mark.parametrize("link_xml,match", [
    ('<link name="l"><pose relative_to="x">0 0 0 0 0 0</pose></link>', "relative_to"),
    ('<link name="l"><pose>0 0 0</pose></link>', "6 numbers"),
    ('<link name="l"><pose>a b c d e f</pose></link>', "6 numbers"),
    ('<link name="l"><visual name="v"><geometry><mesh><uri>model://toy/meshes/Valve.dae</uri>'
     '<scale>1 2</scale></mesh></geometry></visual></link>', "<scale>"),
])
def test_malformed_sdf_raises(uuv_cad_dir: Path, tmp_path: Path, link_xml: str, match: str) -> None:
    with pytest.raises(InputError, match=match):
        load_sdf_model(_write_model(tmp_path, uuv_cad_dir, link_xml))


def test_missing_or_invalid_sdf(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="SDF file not found"):
        load_sdf_model(tmp_path / "model.sdf")
    bad = tmp_path / "bad.sdf"
    bad.write_text("<sdf><model")
    with pytest.raises(InputError, match="cannot parse SDF"):
        load_sdf_model(bad)
    empty = tmp_path / "empty.sdf"
    empty.write_text("<sdf><world/></sdf>")
    with pytest.raises(InputError, match="no <model>"):
        load_sdf_model(empty)
