"""A tiny benchmark folder made through the CLI (render, align, emulate, fuse at --size tiny), shared by the tests."""

from __future__ import annotations

from pathlib import Path

import pytest
from bench_testdata import CHEAP_STAGES
from typer.testing import CliRunner

from cadalign.cli.main import app


@pytest.fixture(scope="session")
def tiny_bench(tmp_path_factory: pytest.TempPathFactory, shared_data: Path) -> Path:
    """``cadalign bench STAGE --size tiny --repeats 1 --out OUT`` for each cheap stage; returns OUT."""
    out = tmp_path_factory.mktemp("bench") / "tiny"
    runner = CliRunner()
    for stage in CHEAP_STAGES:
        res = runner.invoke(app, ["bench", stage, "--size", "tiny", "--repeats", "1", "--out", str(out)])
        assert res.exit_code == 0, res.output
    return out
