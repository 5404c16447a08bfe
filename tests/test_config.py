from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import pytest

from cadalign.config import bounded, from_dict, read_mapping, resolve, to_dict
from cadalign.errors import ConfigError


@dataclass(frozen=True)
class Inner:
    voxel_m: float = bounded(0.02, gt=0.0)
    mode: Literal["tsdf", "surfel"] = "tsdf"


@dataclass(frozen=True)
class Outer:
    name: str = "x"
    iters: int = bounded(10, ge=1)
    scales: tuple[float, ...] = (1.0, 0.5)
    inner: Inner = Inner()
    size: tuple[int, int] | None = None


PRESETS = {"fast": Outer(iters=2), "accurate": Outer(iters=100)}


def _write(tmp_path: Path, name: str, text: str) -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_misspelled_key_names_file_key_and_suggestion(tmp_path):
    p = _write(tmp_path, "cfg.toml", "itres = 5\n")
    with pytest.raises(ConfigError) as err:
        resolve(Outer, path=p)
    msg = str(err.value)
    assert str(p) in msg and "'itres'" in msg and "did you mean 'iters'" in msg


def test_nested_bad_literal_lists_allowed_values(tmp_path):
    p = _write(tmp_path, "cfg.yaml", "inner:\n  mode: voxels\n")
    with pytest.raises(ConfigError) as err:
        resolve(Outer, path=p)
    msg = str(err.value)
    assert "inner.mode" in msg and "'tsdf'" in msg and "'surfel'" in msg and str(p) in msg


def test_bounds_and_types_are_checked(tmp_path):
    with pytest.raises(ConfigError, match=r"inner.voxel_m.*must be > 0"):
        from_dict(Outer, {"inner": {"voxel_m": -1.0}}, source="f.toml")
    with pytest.raises(ConfigError, match="iters.*an integer"):
        from_dict(Outer, {"iters": 2.5})
    with pytest.raises(ConfigError, match="must have 2 elements"):
        from_dict(Outer, {"size": [1, 2, 3]})
    with pytest.raises(ConfigError, match="wrong type"):
        from_dict(Outer, {"iters": True})


def test_preset_then_file_then_overrides(tmp_path):
    p = _write(tmp_path, "cfg.toml", "name = 'from_file'\n[inner]\nvoxel_m = 0.05\n")
    cfg = resolve(Outer, PRESETS, "fast", p, {"scales": [2, 1]})
    assert cfg.iters == 2 and cfg.name == "from_file" and cfg.inner.voxel_m == 0.05 and cfg.inner.mode == "tsdf"
    assert cfg.scales == (2.0, 1.0)
    assert to_dict(cfg)["inner"] == {"voxel_m": 0.05, "mode": "tsdf"}


def test_unknown_preset_lists_presets():
    with pytest.raises(ConfigError, match="accurate, fast"):
        resolve(Outer, PRESETS, "balanced")


def test_unparseable_and_missing_files_name_the_file(tmp_path):
    p = _write(tmp_path, "bad.toml", "a = [\n")
    with pytest.raises(ConfigError, match="bad.toml.*could not parse"):
        read_mapping(p)
    with pytest.raises(ConfigError, match="not found"):
        read_mapping(tmp_path / "nope.toml")
    with pytest.raises(ConfigError, match="unsupported config format"):
        read_mapping(_write(tmp_path, "cfg.ini", "a=1"))


def test_merge_mappings_merges_tables_and_replaces_the_rest():
    from cadalign.config import merge_mappings

    a = {"overlay": False, "refine": {"yaw_hypotheses": 4, "method": "both"}, "ids": [1, 2]}
    b = {"refine": {"yaw_hypotheses": 1}, "ids": [3], "enhance": "none"}
    assert merge_mappings(a, b) == {"overlay": False, "refine": {"yaw_hypotheses": 1, "method": "both"}, "ids": [3],
                                    "enhance": "none"}
    assert a["refine"]["yaw_hypotheses"] == 4  # the inputs are left alone
    assert merge_mappings({"refine": 1}, {"refine": {"x": 2}}) == {"refine": {"x": 2}}
