"""User-picked point correspondences between the SfM cloud and the CAD, and the similarity they define.

Picks file format (JSON)::

    {
      "pairs": [
        {"name": "post NE top", "sfm": [1.25, -0.40, 3.10], "cad_m": [4.35, 4.85, 6.00]},
        {"name": "valve wheel", "sfm": [0.10, 0.22, 2.05], "cad_m": [-2.50, 0.00, 3.59]},
        {"sfm": [-1.70, 0.95, 0.15], "cad_m": [-4.35, -4.85, 0.00]}
      ]
    }

``sfm`` is a point of the SfM reconstruction in its own (arbitrary) frame and unit, ``cad_m`` the same
physical point in the CAD/world frame in metres (the frame the posed CAD parts are given in), ``name``
is optional. At least three pairs are needed, not all on one line; four or more, spread over the whole
structure, make the estimate robust and let a mistaken pick show up in the residuals. A pick only
needs to be roughly right (a few percent of the structure's size): ICP refines the result.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cadalign.errors import DegenerateGeometryError, InputError
from cadalign.geometry import umeyama
from cadalign.types import Sim3

log = logging.getLogger(__name__)

_PAIR_KEYS = {"name", "sfm", "cad_m"}

PICK_MIN_THICKNESS = 0.01
"""Picks whose second principal spread is below this fraction of the first are rejected as collinear:
a pick is a few centimetres off, so a sliver triangle leaves the rotation about its long axis undefined."""

PICK_RESIDUAL_WARN_REL = 0.05
"""A pick whose residual after the fit exceeds this fraction of the picks' spread is logged as suspect."""


@dataclass(frozen=True)
class Picks:
    """Point correspondences.

    Attributes:
        sfm: (K, 3) points in the SfM frame (SfM units).
        cad_m: (K, 3) the same points in the CAD/world frame, metres.
        names: (K,) names (``pick_<i>`` when not given).
        source: where they came from, for messages.
    """

    sfm: np.ndarray
    cad_m: np.ndarray
    names: tuple[str, ...]
    source: str = "<picks>"


def _vec3(value: Any, where: str) -> np.ndarray:
    ok = isinstance(value, (list, tuple)) and len(value) == 3 and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
    arr = np.asarray(value, dtype=np.float64) if ok else None
    if arr is None or not np.all(np.isfinite(arr)):
        raise InputError(f"{where} must be a list of three finite numbers [x, y, z], got {value!r}")
    return arr


def parse_picks(data: Any, source: str = "<picks>") -> Picks:
    """Validate a decoded picks document (see the module docstring) into :class:`Picks`.

    Raises:
        InputError: naming ``source``, the entry and what is wrong.
    """
    if not isinstance(data, dict) or "pairs" not in data:
        raise InputError(f"{source}: a picks file must be a JSON object with a 'pairs' list; see "
                         "cadalign.align.picks for the format")
    unknown = set(data) - {"pairs"}
    if unknown:
        raise InputError(f"{source}: unknown top-level key(s) {sorted(unknown)}; allowed: 'pairs'")
    pairs = data["pairs"]
    if not isinstance(pairs, list) or len(pairs) < 3:
        n = len(pairs) if isinstance(pairs, list) else type(pairs).__name__
        raise InputError(f"{source}: 'pairs' must be a list of at least 3 correspondences, got {n}; "
                         "pick 3 or more points spread over the structure")
    sfm, cad, names = [], [], []
    for i, p in enumerate(pairs):
        where = f"{source}: pairs[{i}]"
        if not isinstance(p, dict):
            raise InputError(f"{where} must be an object with 'sfm' and 'cad_m', got {p!r}")
        bad = set(p) - _PAIR_KEYS
        if bad or not {"sfm", "cad_m"} <= set(p):
            raise InputError(f"{where} has keys {sorted(p)}; required: 'sfm', 'cad_m'; optional: 'name'")
        name = p.get("name", f"pick_{i}")
        if not isinstance(name, str):
            raise InputError(f"{where}.name must be a string, got {name!r}")
        sfm.append(_vec3(p["sfm"], f"{where}.sfm"))
        cad.append(_vec3(p["cad_m"], f"{where}.cad_m"))
        names.append(name)
    return Picks(np.array(sfm), np.array(cad), tuple(names), source)


def read_picks(path: str | Path) -> Picks:
    """Read and validate a picks JSON file.

    Raises:
        InputError: missing file, invalid JSON or an invalid entry; the message names the file.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"picks file not found: {path}")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: not valid JSON ({exc}); see cadalign.align.picks for the format") from exc
    return parse_picks(data, str(path))


def sim3_from_picks(picks: Picks) -> Sim3:
    """``cad_from_sfm`` fitted to the picks by Umeyama with scale (least squares).

    Raises:
        DegenerateGeometryError: the picks are coincident or (nearly) collinear on either side, or
            do not determine a rotation; the message names the picks and the fix.
    """
    for side, pts in (("sfm", picks.sfm), ("cad_m", picks.cad_m)):
        sv = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False)
        if not sv[0] > 0 or sv[1] < PICK_MIN_THICKNESS * sv[0]:
            raise DegenerateGeometryError(
                f"{picks.source}: the '{side}' points of picks {list(picks.names)} are (nearly) "
                f"{'coincident' if not sv[0] > 0 else 'collinear'} (principal spreads {sv[0]:.3g}, {sv[1]:.3g}); "
                "the rotation about their line is undefined. Pick at least 3 points that are not on one line, "
                "spread over the structure"
            )
    try:
        T = umeyama(picks.sfm, picks.cad_m, with_scale=True)
    except DegenerateGeometryError as exc:
        raise DegenerateGeometryError(
            f"{picks.source}: the {len(picks.names)} picks {list(picks.names)} do not define a similarity "
            f"({exc}); pick at least 3 points that are not on one line, spread over the structure"
        ) from exc
    res = np.linalg.norm(T.apply(picks.sfm) - picks.cad_m, axis=1)
    spread = float(np.sqrt(np.mean(np.sum((picks.cad_m - picks.cad_m.mean(0)) ** 2, axis=1))))
    for name, r in zip(picks.names, res, strict=True):
        if len(res) > 3 and r > PICK_RESIDUAL_WARN_REL * spread:
            log.warning("%s: pick '%s' is %.3g m off after the fit (picks spread %.3g m); is it mismatched?",
                        picks.source, name, r, spread)
    log.info("picks fit: scale %.6g, residuals (m) %s", T.s, np.round(res, 4).tolist())
    return T
