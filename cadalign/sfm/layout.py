"""The paths of one SfM output folder (:func:`cadalign.sfm.pipeline.run`), shared by the pipeline and its steps."""

from __future__ import annotations

import dataclasses
from pathlib import Path

REPORT_NAME = "sfm_report.json"


@dataclasses.dataclass(frozen=True)
class Layout:
    """Paths of one SfM output folder."""

    root: Path

    @property
    def images(self) -> Path:
        return self.root / "images"

    @property
    def masks(self) -> Path:
        return self.root / "masks"

    @property
    def database(self) -> Path:
        return self.root / "database.db"

    @property
    def model(self) -> Path:
        return self.root / "sparse" / "0"

    @property
    def depth(self) -> Path:
        return self.root / "depth"

    @property
    def report(self) -> Path:
        return self.root / REPORT_NAME

    def marker(self, step: str) -> Path:
        return self.root / "steps" / f"{step}.json"
