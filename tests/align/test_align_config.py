"""The stage config: presets, strict loading, and the style contract (a docstring under every field)."""

from __future__ import annotations

import ast
import dataclasses
import inspect

import pytest

from cadalign.align import config as align_config
from cadalign.align.config import PRESETS, AlignConfig, GlobalRegConfig, Sim3ICPConfig
from cadalign.config import resolve, to_dict
from cadalign.errors import ConfigError


def test_presets_exist_and_balanced_is_the_default():
    assert set(PRESETS) == {"fast", "balanced", "accurate"}
    assert PRESETS["balanced"] == AlignConfig()


@pytest.mark.parametrize(
    "knob",
    [
        ("cad_samples",),
        ("global_reg", "voxel_rel"),
        ("global_reg", "ransac_max_iters"),
        ("icp", "iters_per_level"),
        ("icp", "corr_dist_schedule_rel"),
        ("refine", "max_iters"),
    ],
)
def test_presets_differ_in_the_speed_knobs(knob):
    values = []
    for name in ("fast", "balanced", "accurate"):
        v = PRESETS[name]
        for k in knob:
            v = getattr(v, k)
        values.append(v)
    assert len({repr(v) for v in values}) == 3, f"{'.'.join(knob)} is the same in two presets: {values}"


def test_presets_go_from_cheap_to_thorough():
    f, b, a = (PRESETS[n] for n in ("fast", "balanced", "accurate"))
    assert f.global_reg.voxel_rel > b.global_reg.voxel_rel > a.global_reg.voxel_rel
    assert f.global_reg.ransac_max_iters < b.global_reg.ransac_max_iters < a.global_reg.ransac_max_iters
    assert f.cad_samples < b.cad_samples < a.cad_samples


def test_resolve_preset_file_and_overrides(tmp_path):
    path = tmp_path / "align.toml"
    path.write_text("seed = 3\n[icp]\ntrim_keep = 0.8\n")
    cfg = resolve(AlignConfig, PRESETS, "fast", path=path, overrides={"gates": {"min_fitness": 0.7}})
    assert cfg.seed == 3 and cfg.icp.trim_keep == 0.8 and cfg.gates.min_fitness == 0.7
    assert cfg.global_reg == PRESETS["fast"].global_reg  # untouched sections keep the preset


@pytest.mark.parametrize(
    ("data", "match"),
    [
        ({"icp": {"trim_kep": 0.8}}, "did you mean 'icp.trim_keep'"),
        ({"coarse": "magic"}, "allowed values"),
        ({"icp": {"trim_keep": 1.5}}, "out of range"),
        ({"global_reg": {"voxel_rel": 0}}, "out of range"),
    ],
)
def test_strict_loading(data, match):
    with pytest.raises(ConfigError, match=match):
        resolve(AlignConfig, PRESETS, "balanced", overrides=data)


def test_unknown_preset():
    with pytest.raises(ConfigError, match="allowed presets: accurate, balanced, fast"):
        resolve(AlignConfig, PRESETS, "quick")


def test_config_round_trips_through_to_dict():
    for cfg in PRESETS.values():
        assert resolve(AlignConfig, overrides=to_dict(cfg)) == cfg


def test_every_field_has_a_docstring():
    tree = ast.parse(inspect.getsource(align_config))
    for cls in (n for n in tree.body if isinstance(n, ast.ClassDef)):
        body = cls.body
        for i, node in enumerate(body):
            if isinstance(node, ast.AnnAssign):
                nxt = body[i + 1] if i + 1 < len(body) else None
                assert isinstance(nxt, ast.Expr) and isinstance(nxt.value, ast.Constant), (
                    f"{cls.name}.{node.target.id} has no docstring")


def test_configs_are_frozen():
    with pytest.raises(dataclasses.FrozenInstanceError):
        Sim3ICPConfig().trim_keep = 0.5  # type: ignore[misc]
    assert dataclasses.fields(GlobalRegConfig)
