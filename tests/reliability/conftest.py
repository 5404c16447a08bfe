"""Fixtures for the reliability tests: a tiny simulated BOP scene and the bad-input catalogue recorder.

Set ``CADALIGN_BAD_INPUT_TABLE=path.md`` to write the catalogue (bad input -> the message the user
sees) as a markdown table when the session ends.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from reliability_testdata import CATALOGUE, markdown_table

from cadalign.sim.run import SCENE_SUBDIR
from cadalign.testing.tiny_scene import simulate_tiny


@pytest.fixture(scope="session")
def tiny_bop(tmp_path_factory: pytest.TempPathFactory, shared_data: Path) -> Path:
    """The BOP scene folder of a 2-frame effect-free 160x120 simulation (read-only: copy before corrupting)."""
    return simulate_tiny(tmp_path_factory.mktemp("rel_bop"), frames=2) / SCENE_SUBDIR


@pytest.fixture(scope="session", autouse=True)
def _write_catalogue() -> object:
    yield
    target = os.environ.get("CADALIGN_BAD_INPUT_TABLE")
    if target and CATALOGUE:
        head = ("# Bad inputs -> what the user sees\n\nWritten by the reliability tests (each row is a test that ran "
                "the input and checked the message):\n`CADALIGN_BAD_INPUT_TABLE=THIS_FILE .venv/bin/python -m pytest "
                "tests/reliability -m 'slow or not slow' -n 0 -p no:cacheprovider`\n\n")
        Path(target).write_text(head + markdown_table(CATALOGUE), encoding="utf-8")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """A RuntimeWarning (NaN, inf, overflow, divide by zero) fails the tests of this folder (issue 11)."""
    here = Path(__file__).parent
    for item in items:
        if here in item.path.parents:
            item.add_marker(pytest.mark.filterwarnings("error::RuntimeWarning"))
