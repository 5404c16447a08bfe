"""CAD length units: conversion to metres, detection from size, and sanity checks.

The classic pose-estimation bug is a mesh in millimetres read as metres (or the
reverse): everything downstream is silently 1000x off. cadalign converts every
model to metres at load time, records the unit the file was in, and refuses
sizes that are implausible for subsea hardware.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Protocol

import numpy as np

from cadalign.errors import UnitError

logger = logging.getLogger(__name__)

#: Metres per file unit.
UNIT_TO_M: dict[str, float] = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254}

#: Largest extent (metres) a subsea part is expected to have: a bolt head to a manifold.
PLAUSIBLE_SIZE_M: tuple[float, float] = (0.01, 50.0)



class SizedModel(Protocol):
    """What :func:`check_unit` reads of a model (a :class:`~cadalign.cad.model.CadModel`); a protocol so this
    module, which the model imports, does not import the model back."""

    @property
    def extent(self) -> np.ndarray: ...  # (3,) metres
    @property
    def source(self) -> Path | None: ...
    @property
    def name(self) -> str: ...
    @property
    def class_name(self) -> str: ...
    @property
    def unit(self) -> str: ...


_UNIT_WORDS = {"m": "metres", "cm": "centimetres", "mm": "millimetres", "in": "inches"}


def unit_scale(unit: str) -> float:
    """Metres per ``unit`` (one of ``m``, ``cm``, ``mm``, ``in``); raises :class:`UnitError` otherwise."""
    if unit not in UNIT_TO_M:
        raise UnitError(f"unknown unit {unit!r}; allowed: {', '.join(UNIT_TO_M)}")
    return UNIT_TO_M[unit]


def unit_from_metres_per_unit(m_per_unit: float, rtol: float = 1e-4) -> str | None:
    """The unit code whose size is ``m_per_unit`` metres, or ``None`` when none matches."""
    for code, scale in UNIT_TO_M.items():
        if abs(m_per_unit - scale) <= rtol * scale:
            return code
    return None


def _plausible(size_m: float) -> bool:
    lo, hi = PLAUSIBLE_SIZE_M
    return lo <= size_m <= hi


def detect_unit(largest_extent: float, source: str, declared: str | None = None) -> str:
    """Guess the unit of a CAD file from its largest extent (in file units).

    Rule for subsea hardware (expected 0.01–50 m across): a unit the file itself
    declares (COLLADA ``<unit>``) is used when the size is plausible in it;
    otherwise the numbers are read as metres when that is plausible, as
    millimetres when they are > 50 (a 600 mm valve), and rejected when even
    millimetres would exceed 50 m. Any assumption other than a plausible
    declared unit is logged as a WARNING naming how to override it.

    Args:
        largest_extent: largest axis-aligned extent of the mesh in file units.
        source: the file name, for messages.
        declared: unit declared by the file's metadata, if any.

    Returns:
        the unit code (``m`` or ``mm``, or ``declared``).
    """
    lo, hi = PLAUSIBLE_SIZE_M
    if declared is not None and _plausible(largest_extent * UNIT_TO_M[declared]):
        logger.info("CAD '%s': using the unit it declares (%s)", source, declared)
        return declared
    note = f" (it declares {_UNIT_WORDS[declared]}, implausible here)" if declared else ""
    if largest_extent <= hi:
        if largest_extent < lo:
            logger.warning(
                "CAD '%s' is only %.4g across in file units%s; reading it as metres (%.4g m) although subsea "
                "parts are expected %g–%g m. If the file is in another unit, pass unit=... to load_cad.",
                source, largest_extent, note, largest_extent, lo, hi)
        elif declared is not None:
            logger.warning("CAD '%s' is %.4g across%s; assuming metres. Pass unit= to load_cad to override.",
                           source, largest_extent, note)
        return "m"
    size_mm = largest_extent * UNIT_TO_M["mm"]
    if size_mm > hi:
        raise UnitError(
            f"CAD '{source}' is {largest_extent:.4g} across in file units: {size_mm:.4g} m even if in millimetres, "
            f"but subsea parts are expected {lo:g}–{hi:g} m. Check the export, or pass unit= explicitly to load_cad "
            "and then check_unit() with the size you expect.")
    logger.warning(
        "CAD '%s' is %.4g across in file units%s: too big for metres (subsea parts are %g–%g m), so assuming "
        "millimetres (%.4g m). If that is wrong, pass unit='m' (or 'cm', 'in') to load_cad.",
        source, largest_extent, note, lo, hi, size_mm)
    return "mm"


def _suggest_unit(size_m: float, unit: str, expected_size_m: tuple[float, float]) -> str | None:
    raw = size_m / UNIT_TO_M[unit]
    lo, hi = expected_size_m
    for cand in ("mm", "cm", "in", "m"):
        if cand != unit and lo <= raw * UNIT_TO_M[cand] <= hi:
            return cand
    return None


def check_unit(model: SizedModel, expected_size_m: tuple[float, float]) -> float:
    """Check that a model's largest extent lies in the size range expected for its class.

    Catches a 600 mm valve loaded as metres (600 m across) before it poisons
    a registration or a training set.

    Args:
        model: the loaded model (metres).
        expected_size_m: (min, max) plausible largest extent in metres for this object.

    Returns:
        the largest extent in metres.

    Raises:
        UnitError: naming the file, its size, the expected range and the ``unit=`` that would fit.
    """
    lo, hi = (float(x) for x in expected_size_m)
    if not 0 < lo <= hi:
        raise UnitError(f"expected_size_m must be (min, max) with 0 < min <= max, got {expected_size_m}")
    size = float(model.extent.max())
    if lo <= size <= hi:
        return size
    what = model.source.name if model.source is not None else model.name
    article = "an" if model.class_name[:1].lower() in "aeiou" else "a"
    msg = f"CAD '{what}' is {size:.4g} m across; {article} {model.class_name} is expected {lo:g}–{hi:g} m."
    cand = _suggest_unit(size, model.unit, (lo, hi))
    if cand is not None:
        msg += f" Was it exported in {_UNIT_WORDS[cand]}? Pass unit='{cand}'."
    else:
        msg += f" It was read as {_UNIT_WORDS[model.unit]}; no unit fits, so check the model or the expected size."
    raise UnitError(msg)
