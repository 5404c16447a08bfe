"""The project's exceptions.

Every error a user can cause derives from :class:`CadalignError` and says which
input is at fault and how to fix it. ``assert`` is reserved for internal
invariants.
"""

from __future__ import annotations


class CadalignError(Exception):
    """Base class for all user-facing cadalign errors."""


class ConfigError(CadalignError, ValueError):
    """A config or spec file has an unknown key or an invalid value."""


class InputError(CadalignError, ValueError):
    """An input file or array is missing, corrupt or unusable."""


class DegenerateGeometryError(CadalignError, ValueError):
    """A geometric estimate is undefined for the given input.

    Raised instead of returning garbage, e.g. Umeyama on fewer than three
    points, collinear or coincident points, or a plane fit on a line.
    """


class CorrespondenceError(InputError, DegenerateGeometryError):
    """Two point sets meant to correspond one to one hold different numbers of points.

    Both an :class:`InputError` (the arrays are wrong) and a :class:`DegenerateGeometryError`
    (no alignment is defined for them), so callers catching either see it.
    """


class UnitError(InputError):
    """A CAD model's unit is wrong or ambiguous (the classic mm/m mix-up)."""


class AlignmentError(CadalignError):
    """A registration failed its quality gate; nothing was written."""


class VerificationError(AlignmentError):
    """The images do not confirm the alignment (outcome ``wrong``) or cannot decide it (``uncertain``); no dataset
    was written. ``verification`` holds the evidence (a :class:`cadalign.align.verify.core.Verification`)."""

    def __init__(self, message: str, verification: object = None):
        super().__init__(message)
        self.verification = verification


class TrainingError(CadalignError):
    """Training hit a non-finite input or loss (naming the sample and step), or a checkpoint of another
    model or class list was offered to resume or evaluate."""
