"""Shared hypothesis strategies, settings and exact-answer helpers for the geometry tests."""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np
from hypothesis import strategies as st

from cadalign.geometry import geodesic_angle, random_rotation

DETERMINISTIC: dict[str, Any] = {"deadline": None, "derandomize": True, "database": None}
"""Hypothesis settings shared by every geometry test: same examples on every run, no timing flakes."""

EULER_SEQS: list[str] = ["".join(p) for p in itertools.product("xyz", repeat=3) if p[0] != p[1] and p[1] != p[2]]
"""The 12 axis sequences in lowercase (extrinsic); ``.upper()`` gives the intrinsic ones."""

ALL_EULER_SEQS: list[str] = EULER_SEQS + [s.upper() for s in EULER_SEQS]
"""All 24 sequences: 12 extrinsic and 12 intrinsic."""

seeds = st.integers(0, 2**32 - 1)
"""Seeds for ``numpy.random.default_rng``: hypothesis shrinks seeds, numpy draws the bulk data."""

unit_vectors = (
    st.lists(st.floats(-1, 1, allow_nan=False), min_size=3, max_size=3)
    .map(np.array)
    .filter(lambda v: np.linalg.norm(v) > 1e-3)
    .map(lambda v: v / np.linalg.norm(v))
)
"""Unit (3,) vectors, including axis-aligned and near-axis-aligned ones."""

rotations = seeds.map(lambda s: random_rotation(np.random.default_rng(s)))
"""Haar-uniform (3, 3) rotations."""

log_scales = st.floats(-3.0, 3.0).map(lambda e: float(10.0**e))
"""Scales from 1e-3 to 1e3, log-uniform."""


def rotation_error(R1: np.ndarray, R2: np.ndarray) -> float:
    """Largest geodesic angle (radians) between two (..., 3, 3) rotation batches."""
    return float(np.max(geodesic_angle(R1, R2)))


def rot_about(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation by ``angle`` about unit ``axis`` via Rodrigues in plain numpy (independent of cadalign)."""
    k = np.asarray(axis, dtype=np.float64)
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * (K @ K)


def nearest_rotation_horn(M: np.ndarray) -> np.ndarray:
    """Rotation maximising ``trace(R^T M)`` (= Frobenius-nearest) by Horn's quaternion eigenproblem.

    An oracle independent of SVD: the maximiser's wxyz quaternion is the top
    eigenvector of the symmetric (4, 4) matrix below (Bar-Itzhack 2000).
    """
    (a, b, c), (d, e, f), (g, h, i) = M
    N = np.array(
        [
            [a + e + i, h - f, c - g, d - b],
            [h - f, a - e - i, b + d, c + g],
            [c - g, b + d, e - a - i, f + h],
            [d - b, c + g, f + h, i - a - e],
        ]
    )
    _, vecs = np.linalg.eigh(N)
    w, x, y, z = vecs[:, -1]
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def random_sim3_parts(rng: np.random.Generator) -> tuple[float, np.ndarray, np.ndarray]:
    """A random similarity ``(s, R (3, 3), t (3,))`` with ``s`` log-uniform in [1e-2, 1e2]."""
    return float(10.0 ** rng.uniform(-2, 2)), random_rotation(rng), rng.uniform(-10, 10, 3)
