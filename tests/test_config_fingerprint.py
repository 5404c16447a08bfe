"""Config fingerprints ignore fields at their defaults, so adding a defaulted field keeps old runs valid.

An "old run" is simulated the way it happens: its stored config is the ``to_dict`` of a config class that did
not have the new field yet (the same dict minus that key), with the fingerprint that version computed (over
the full dict).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cadalign.config import config_differences, config_fingerprint_dict, stored_fingerprint_dict, to_dict
from cadalign.errors import ConfigError
from cadalign.io import MANIFEST_NAME, fingerprint, prepare_stage_dir, read_json, write_json
from cadalign.sfm.config import PRESETS, SfMConfig


@dataclass(frozen=True)
class Inner:
    a: int = 1
    """A setting."""
    b: tuple[float, ...] = (0.5, 2.0)
    """A tuple setting."""


@dataclass(frozen=True)
class Outer:
    inner: Inner = field(default_factory=Inner)
    """A nested config at its class defaults."""
    tuned: Inner = Inner(a=7)
    """A nested config whose default differs from its class defaults."""
    extra: Inner | None = None
    """An optional nested config."""
    x: float = 0.25
    """A number."""


def test_view_drops_defaults_recursively():
    assert config_fingerprint_dict(Outer()) == {}
    assert config_fingerprint_dict(Outer(x=1.0, inner=Inner(b=(3.0,)))) == {"x": 1.0, "inner": {"b": [3.0]}}
    # a nested default counts from the parent's default: Inner() is not the default of 'tuned'
    assert config_fingerprint_dict(Outer(tuned=Inner())) == {"tuned": {"a": 1}}
    assert config_fingerprint_dict(Outer(tuned=Inner(a=7))) == {}
    # an optional config set to its class defaults still differs from None
    assert config_fingerprint_dict(Outer(extra=Inner())) == {"extra": {}}
    # plain containers are walked, their configs reduced
    assert config_fingerprint_dict({"cfg": Outer(x=2.0), "src": ("a", 3)}) == {"cfg": {"x": 2.0}, "src": ["a", 3]}


def test_stored_view_of_an_old_config_lacking_a_field():
    old = to_dict(Outer(x=1.0))
    del old["tuned"]  # written before 'tuned' existed
    assert stored_fingerprint_dict(old, Outer(x=1.0)) == config_fingerprint_dict(Outer(x=1.0))
    assert config_differences(old, Outer(x=1.0)) == []
    assert config_differences(old, Outer(x=1.0, tuned=Inner(a=8))) == ["tuned.a"]
    assert config_differences(old, Outer(x=0.5)) == ["x"]
    # a stored key the class no longer has counts
    assert config_differences({**old, "gone": 3}, Outer(x=1.0)) == ["gone"]
    assert config_differences({"extra": None}, Outer(extra=Inner())) == ["extra"]


def test_plain_values_compare_as_before():
    assert config_differences(["bg", "valve"], ("bg", "valve")) == []
    assert config_differences(["bg", "valve"], ["bg", "pipe"]) == [""]
    assert config_differences({"k": [1, 2]}, {"k": (1, 2), "new": 0}) == ["new"]


@st.composite
def _outers(draw):
    fl = st.floats(-1e6, 1e6, allow_nan=False).map(lambda v: v + 0.0)  # no -0.0: equal to 0.0, printed apart
    inner = st.builds(Inner, a=st.integers(-3, 3), b=st.tuples(fl) | st.just((0.5, 2.0)))
    return Outer(inner=draw(inner), tuned=draw(inner | st.just(Inner(a=7))), extra=draw(st.none() | inner),
                 x=draw(fl | st.just(0.25)))


@settings(max_examples=60, deadline=None)
@given(_outers(), _outers())
def test_differences_empty_exactly_when_configs_equal(a, b):
    import json

    stored = json.loads(json.dumps(to_dict(a)))  # as read back from disk
    assert (config_differences(stored, b) == []) == (a == b)
    assert (fingerprint(config_fingerprint_dict(a)) == fingerprint(config_fingerprint_dict(b))) == (a == b)


def _old_sfm_manifest(out, cfg: SfMConfig, drop: str) -> dict:
    """The manifest an older cadalign wrote for ``cfg``, whose MapperConfig lacked ``drop``."""
    config = {"sfm": to_dict(cfg), "source": {"path": "/data/frames", "files": "abc", "count": 64}}
    del config["sfm"]["mapper"][drop]
    record = {"stage": "sfm", "config": config, "version": "0.0.9", "fingerprint": fingerprint(config)}
    write_json(out / MANIFEST_NAME, record)
    return record


def _sfm_config(cfg: SfMConfig) -> dict:
    return {"sfm": cfg, "source": {"path": "/data/frames", "files": "abc", "count": 64}}


def test_stage_made_before_a_defaulted_field_is_reused(tmp_path):
    old = _old_sfm_manifest(tmp_path, SfMConfig(), drop="on_break")
    assert prepare_stage_dir(tmp_path, "sfm", _sfm_config(SfMConfig())) is True
    assert read_json(tmp_path / MANIFEST_NAME) == old  # reused as is, nothing rewritten
    accurate = PRESETS["accurate"]
    other = tmp_path / "acc"
    other.mkdir()
    _old_sfm_manifest(other, accurate, drop="segment_overlap")
    assert prepare_stage_dir(other, "sfm", _sfm_config(accurate)) is True


def test_stage_refuses_the_new_field_at_a_non_default_value(tmp_path):
    _old_sfm_manifest(tmp_path, SfMConfig(), drop="on_break")
    cfg = dataclasses.replace(SfMConfig(), mapper=dataclasses.replace(SfMConfig().mapper, on_break="keep_all"))
    with pytest.raises(ConfigError, match=r"another config .*differs in: sfm\.mapper\.on_break\).*--overwrite"):
        prepare_stage_dir(tmp_path, "sfm", _sfm_config(cfg))
    assert prepare_stage_dir(tmp_path, "sfm", _sfm_config(cfg), overwrite=True) is False


def test_stage_refuses_changed_values_and_other_stages(tmp_path):
    assert prepare_stage_dir(tmp_path, "sfm", _sfm_config(SfMConfig())) is False
    assert prepare_stage_dir(tmp_path, "sfm", _sfm_config(SfMConfig())) is True
    longer = dataclasses.replace(SfMConfig(), matching=dataclasses.replace(SfMConfig().matching, overlap=12))
    with pytest.raises(ConfigError, match=r"another config .*differs in: sfm\.matching\.overlap\)"):
        prepare_stage_dir(tmp_path, "sfm", _sfm_config(longer))
    with pytest.raises(ConfigError, match=r"differs in: sfm\.features\.peak_threshold, sfm\.mapper"):
        prepare_stage_dir(tmp_path, "sfm", _sfm_config(PRESETS["accurate"]))
    with pytest.raises(ConfigError, match="holds 'sfm' results"):
        prepare_stage_dir(tmp_path, "align", _sfm_config(SfMConfig()))
    changed_input = {"sfm": SfMConfig(), "source": {"path": "/data/frames", "files": "abd", "count": 64}}
    with pytest.raises(ConfigError, match=r"source\.files"):
        prepare_stage_dir(tmp_path, "sfm", changed_input)


def test_plain_dict_configs_behave_as_before(tmp_path):
    """Callers that pass ``to_dict`` output (no defaults known) get the old exact comparison and fingerprint."""
    plain = {"fuse": to_dict(SfMConfig().depth), "source": "s"}
    prepare_stage_dir(tmp_path, "fuse", plain)
    assert read_json(tmp_path / MANIFEST_NAME)["fingerprint"] == fingerprint(plain)
    with pytest.raises(ConfigError, match="another config"):
        prepare_stage_dir(tmp_path, "fuse", {**plain, "new": 1})


def test_ignored_keys_are_stored_but_not_compared(tmp_path):
    cfg = {"config": Outer(inner=Inner(a=4)), "dataset": "d"}
    prepare_stage_dir(tmp_path, "train", cfg, ignore=("config.inner.a",))
    assert read_json(tmp_path / MANIFEST_NAME)["config"]["config"]["inner"]["a"] == 4
    assert prepare_stage_dir(tmp_path, "train", {"config": Outer(inner=Inner(a=9)), "dataset": "d"},
                             ignore=("config.inner.a",)) is True
    with pytest.raises(ConfigError, match=r"config\.x"):
        prepare_stage_dir(tmp_path, "train", {"config": Outer(x=3.0), "dataset": "d"}, ignore=("config.inner.a",))
