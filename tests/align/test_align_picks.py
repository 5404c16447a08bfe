"""User picks: file format, validation, degenerate picks, and the picks -> ICP path."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from align_testdata import sim3_errors
from hypothesis import given, settings
from hypothesis import strategies as st

from cadalign.align import PRESETS, align, parse_picks, read_picks, sim3_from_picks
from cadalign.align.picks import Picks
from cadalign.errors import DegenerateGeometryError, InputError
from cadalign.geometry import random_rotation
from cadalign.types import Sim3

# Recognisable points of the frame (world metres): post tops/bottoms, the tree body top, a valve.
CAD_PICKS_M = np.array([
    [4.35, 4.85, 6.0],
    [-4.35, -4.85, 6.0],
    [4.35, -4.85, 0.0],
    [-2.5, 0.0, 3.6],
    [0.0, 0.0, 5.0],
])


def _picks_doc(sfm: np.ndarray, cad: np.ndarray, names: bool = True) -> dict:
    pairs = []
    for i, (a, b) in enumerate(zip(sfm, cad, strict=True)):
        p = {"sfm": a.tolist(), "cad_m": b.tolist()}
        if names:
            p["name"] = f"p{i}"
        pairs.append(p)
    return {"pairs": pairs}


def _write(tmp_path: Path, doc: object, name: str = "picks.json") -> Path:
    path = tmp_path / name
    path.write_text(doc if isinstance(doc, str) else json.dumps(doc))
    return path


def _noisy_picks(cloud, n: int, noise_m: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """SfM picks of the first ``n`` CAD points, each clicked ``noise_m`` off (in metres) in the SfM view."""
    rng = np.random.default_rng(seed)
    cad = CAD_PICKS_M[:n]
    clicked = cad + rng.normal(0.0, noise_m, cad.shape)
    return cloud.cad_from_sfm.inverse().apply(clicked), cad


@pytest.mark.parametrize("n", [3, 4])
def test_picks_then_icp_recover(n, cloud, surface, tmp_path):
    sfm, cad = _noisy_picks(cloud, n, noise_m=0.05)
    picks = read_picks(_write(tmp_path, _picks_doc(sfm, cad)))
    coarse = sim3_from_picks(picks)
    rot0, _, sc0 = sim3_errors(coarse, cloud.cad_from_sfm, cloud.points_sfm)
    assert rot0 < 3.0 and sc0 < 0.05  # rough clicks give a rough start ...
    r = align(cloud.points_sfm, surface, PRESETS["fast"], picks=picks)
    rot, trans, scale = sim3_errors(r.cad_from_sfm, cloud.cad_from_sfm, cloud.points_sfm)
    assert r.coarse_from == "picks"
    assert rot < 0.05 and trans < 0.005 and scale < 5e-4  # ... that ICP makes exact


@settings(max_examples=30, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**31 - 1), log_s=st.floats(np.log(0.05), np.log(20.0)), n=st.integers(3, 5))
def test_exact_picks_give_the_exact_sim3(seed, log_s, n):
    rng = np.random.default_rng(seed)
    sfm_from_cad = Sim3(float(np.exp(log_s)), random_rotation(rng), rng.uniform(-100, 100, 3))
    picks = Picks(sfm_from_cad.apply(CAD_PICKS_M[:n]), CAD_PICKS_M[:n], tuple(map(str, range(n))))
    T = sim3_from_picks(picks)
    gt = sfm_from_cad.inverse()
    assert np.allclose(T.matrix(), gt.matrix(), atol=1e-7 * max(1.0, np.abs(gt.t).max()))


def test_collinear_picks_raise_naming_the_file(tmp_path):
    cad = np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0], [3.5, 0.001, 0]])  # a near-line (1 mm off)
    path = _write(tmp_path, _picks_doc(cad * 2.0, cad))
    with pytest.raises(DegenerateGeometryError, match="collinear") as exc:
        sim3_from_picks(read_picks(path))
    assert str(path) in str(exc.value) and "not on one line" in str(exc.value)


def test_coincident_picks_raise(tmp_path):
    cad = np.ones((3, 3))
    with pytest.raises(DegenerateGeometryError, match="coincident"):
        sim3_from_picks(read_picks(_write(tmp_path, _picks_doc(cad, cad))))


def test_degenerate_picks_fail_through_align(cloud, surface):
    cad = np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]])
    with pytest.raises(DegenerateGeometryError):
        align(cloud.points_sfm, surface, PRESETS["fast"], picks=Picks(cad, cad, ("a", "b", "c")))


@pytest.mark.parametrize(
    ("doc", "problem"),
    [
        ("{not json", "not valid JSON"),
        ([1, 2, 3], "'pairs' list"),
        ({"points": []}, "'pairs' list"),
        ({"pairs": [], "extra": 1}, "unknown top-level key"),
        ({"pairs": [{"sfm": [0, 0, 0], "cad_m": [0, 0, 0]}] * 2}, "at least 3"),
        ({"pairs": "abc"}, "at least 3"),
        ({"pairs": [{"sfm": [0, 0, 0], "cad_m": [0, 0, 0]}] * 2 + [{"sfm": [0, 0], "cad_m": [1, 2, 3]}]},
         r"pairs\[2\]\.sfm must be a list of three"),
        ({"pairs": [{"sfm": [0, 0, 0], "cad_m": [0, 0, 0]}] * 2 + [{"sfm": [0, 0, "x"], "cad_m": [1, 2, 3]}]},
         r"pairs\[2\]\.sfm"),
        ({"pairs": [{"sfm": [0, 0, 0], "cad": [0, 0, 0]}] * 3}, r"pairs\[0\] has keys \['cad', 'sfm'\]"),
        ({"pairs": [{"sfm": [0, 0, 0], "cad_m": [0, 0, 1e999]}] * 3}, r"pairs\[0\]\.cad_m"),
        ({"pairs": [{"sfm": [0, 0, 0], "cad_m": [0, 0, 0], "name": 3}] * 3}, r"pairs\[0\]\.name must be a string"),
        ({"pairs": [[0, 0, 0]] * 3}, r"pairs\[0\] must be an object"),
    ],
)
def test_malformed_picks_file_names_file_and_problem(tmp_path, doc, problem):
    path = _write(tmp_path, doc)
    with pytest.raises(InputError, match=problem) as exc:
        read_picks(path)
    assert str(path) in str(exc.value)


def test_missing_picks_file(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_picks(tmp_path / "nope.json")


def test_names_default_and_round_trip(tmp_path):
    sfm, cad = CAD_PICKS_M[:3] * 2, CAD_PICKS_M[:3]
    picks = parse_picks(_picks_doc(sfm, cad, names=False), "mem")
    assert picks.names == ("pick_0", "pick_1", "pick_2")
    assert np.array_equal(picks.sfm, sfm) and np.array_equal(picks.cad_m, cad) and picks.source == "mem"


def test_a_mismatched_pick_is_logged(caplog):
    sfm = CAD_PICKS_M.copy()
    sfm[[0, 1]] = sfm[[1, 0]]  # two picks swapped
    with caplog.at_level("WARNING"):
        sim3_from_picks(Picks(sfm, CAD_PICKS_M, tuple("abcde")))
    assert "mismatched" in caplog.text
