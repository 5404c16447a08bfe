"""Issue 46 interop: SfM and simulation write ``trajectory.tum`` (camera-in-world), and the SfM report's ATE / RPE
are the numbers evo computes from those two files (``evo_ape`` / ``evo_rpe`` with ``--align --correct_scale``)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from cadalign.formats.tum import read_tum, write_cameras_tum
from cadalign.geometry.rotations import quaternion_to_matrix
from cadalign.io import read_json

GT_SCENE = Path("gt") / "sim" / "000000"


@pytest.fixture(scope="module")
def sfm_with_gt(five_frames: Path, tiny_dive: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    from cadalign.evaluate.sfm import run as evaluate
    from cadalign.sfm import PRESETS, run

    cfg = dataclasses.replace(PRESETS["fast"], num_threads=1)  # one thread: deterministic
    out = run(cfg, five_frames, tmp_path_factory.mktemp("tum") / "sfm")
    evaluate(out, tiny_dive)
    return out


def test_tum_files_hold_the_camera_in_world_poses(sfm_with_gt: Path, tiny_dive: Path) -> None:
    for folder in (sfm_with_gt, tiny_dive / GT_SCENE):
        cams = read_json(folder / "cameras.json")["frames"]
        stamps, xyz, q_xyzw = read_tum(folder / "trajectory.tum")
        names = sorted(n for n in cams if "R_cam_from_world" in cams[n])
        assert stamps.tolist() == [float(int(Path(n).stem)) for n in names]
        for k, n in enumerate(names):
            R_cw = np.reshape(cams[n]["R_cam_from_world"], (3, 3))
            C = -R_cw.T @ np.asarray(cams[n]["t_cam_from_world_m"])
            np.testing.assert_allclose(xyz[k], C, atol=1e-12)
            R_wc = quaternion_to_matrix(np.roll(q_xyzw[k], 1))  # x y z w -> w x y z
            np.testing.assert_allclose(R_wc, R_cw.T, atol=1e-12)


def test_report_ate_and_rpe_match_evo(sfm_with_gt: Path, tiny_dive: Path) -> None:
    from evo.core import metrics, sync
    from evo.tools import file_interface

    ref = file_interface.read_tum_trajectory_file(str(tiny_dive / GT_SCENE / "trajectory.tum"))
    est = file_interface.read_tum_trajectory_file(str(sfm_with_gt / "trajectory.tum"))
    ref, est = sync.associate_trajectories(ref, est)
    est.align(ref, correct_scale=True)
    gt = read_json(sfm_with_gt / "sfm_report.json")["gt"]
    assert gt["registered_with_gt"] == est.num_poses == 5

    def evo(metric: metrics.PE) -> float:
        metric.process_data((ref, est))
        return float(metric.get_statistic(metrics.StatisticsType.rmse))

    ape = evo(metrics.APE(metrics.PoseRelation.translation_part))
    rpe_t = evo(metrics.RPE(metrics.PoseRelation.translation_part, delta=1, delta_unit=metrics.Unit.frames))
    rpe_r = evo(metrics.RPE(metrics.PoseRelation.rotation_angle_deg, delta=1, delta_unit=metrics.Unit.frames))
    assert ape > 0 and rpe_t > 0 and rpe_r > 0  # a real, imperfect SfM model: the comparison is not 0 == 0
    print(f"ATE {ape:.6g} m, RPE {rpe_t:.6g} m / {rpe_r:.6g} deg (evo) vs report {gt['ate_m']:.6g}, "
          f"{gt['rpe_m']:.6g}, {gt['rpe_deg']:.6g}")
    np.testing.assert_allclose([gt["ate_m"], gt["rpe_m"], gt["rpe_deg"]], [ape, rpe_t, rpe_r], rtol=1e-9, atol=0)


def test_names_without_numbers_are_ranked(tmp_path: Path) -> None:
    cams = {"frames": {n: {"R_cam_from_world": np.eye(3).ravel().tolist(), "t_cam_from_world_m": [i, 0, 0]}
                       for i, n in enumerate(["b.png", "a.png", "c.png"])}, "units": "sfm"}
    write_cameras_tum(cams, tmp_path / "t.tum")
    stamps, xyz, _ = read_tum(tmp_path / "t.tum")
    assert stamps.tolist() == [0.0, 1.0, 2.0] and xyz[:, 0].tolist() == [-1.0, 0.0, -2.0]
    assert "SfM units" in (tmp_path / "t.tum").read_text().splitlines()[0]
