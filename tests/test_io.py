from __future__ import annotations

import numpy as np
import pytest

from cadalign.errors import ConfigError, InputError
from cadalign.io import atomic_path, prepare_stage_dir, read_image, read_json, read_jsonl, write_image, write_json


def test_atomic_write_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.json"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("partial")
            raise RuntimeError("interrupted")
    assert not target.exists()
    assert list(tmp_path.iterdir()) == []


def test_image_round_trip_rgb_and_uint16(tmp_path):
    rgb = np.random.default_rng(0).integers(0, 255, (5, 7, 3), dtype=np.uint8)
    write_image(tmp_path / "a.png", rgb)
    assert np.array_equal(read_image(tmp_path / "a.png"), rgb)
    d = np.array([[0, 1, 65535]], dtype=np.uint16)
    write_image(tmp_path / "d.png", d)
    assert np.array_equal(read_image(tmp_path / "d.png", unchanged=True), d)


def test_corrupt_image_and_json_name_the_file(tmp_path):
    (tmp_path / "bad.png").write_bytes(b"not a png")
    with pytest.raises(InputError, match="bad.png"):
        read_image(tmp_path / "bad.png")
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(InputError, match="bad.json"):
        read_json(tmp_path / "bad.json")


def test_jsonl_records_and_a_cut_last_line(tmp_path):
    p = tmp_path / "track.jsonl"
    p.write_text('{"frame": 0, "state": "ok"}\n\n{"frame": 1, "state": "lost"}\n')
    assert [r["state"] for r in read_jsonl(p)] == ["ok", "lost"]  # blank lines skipped
    p.write_text('{"frame": 0}\n{"frame": 1, "sta')  # a run cut short
    with pytest.raises(InputError, match="line 2"):
        read_jsonl(p)
    with pytest.raises(InputError, match="missing file"):
        read_jsonl(tmp_path / "none.jsonl")


def test_stage_dir_reuses_same_config_and_refuses_another(tmp_path):
    assert prepare_stage_dir(tmp_path / "s", "sim", {"a": 1}) is False
    assert prepare_stage_dir(tmp_path / "s", "sim", {"a": 1}) is True
    with pytest.raises(ConfigError, match="--overwrite"):
        prepare_stage_dir(tmp_path / "s", "sim", {"a": 2})
    assert prepare_stage_dir(tmp_path / "s", "sim", {"a": 2}, overwrite=True) is False
    write_json(tmp_path / "x.json", {"v": np.float32(1.5)})
    assert read_json(tmp_path / "x.json") == {"v": 1.5}
