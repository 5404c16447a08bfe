"""RuntimeWarnings are errors in the geometry tests."""

from __future__ import annotations

from pathlib import Path

import pytest


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """A RuntimeWarning (NaN, inf, overflow, divide by zero) fails the tests of this folder (issue 11)."""
    here = Path(__file__).parent
    for item in items:
        if here in item.path.parents:
            item.add_marker(pytest.mark.filterwarnings("error::RuntimeWarning"))
