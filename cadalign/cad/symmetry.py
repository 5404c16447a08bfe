"""Object symmetries in the BOP convention (metres inside cadalign).

BOP (``models_info.json``) describes a symmetric object by

- ``symmetries_discrete``: a list of (4, 4) rigid transforms ``T`` (identity
  excluded) such that the object looks the same after ``x -> T x``;
- ``symmetries_continuous``: a list of ``{axis, offset}``: the object is
  invariant to any rotation about the line through ``offset`` along ``axis``.

BOP stores translations and offsets in millimetres; :class:`Symmetry` stores
metres and converts only in :mod:`cadalign.cad.models_info`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from cadalign.errors import InputError

SymmetryKind = Literal["none", "discrete", "continuous"]

#: Names accepted by :meth:`Symmetry.from_name` (the scene spec's ``symmetry`` values).
SYMMETRY_NAMES = ("none", "continuous_x", "continuous_y", "continuous_z", "discrete_x2", "discrete_y2", "discrete_z2",
                  "discrete_x4", "discrete_y4", "discrete_z4")

_AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}


def axis_angle_matrix(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """Rodrigues' formula: the (3, 3) rotation by ``angle_rad`` about unit ``axis`` (3,)."""
    k = np.asarray(axis, dtype=np.float64)
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle_rad) * K + (1.0 - np.cos(angle_rad)) * (K @ K)


def rotation_about_line(axis: np.ndarray, offset_m: np.ndarray, angle_rad: float) -> np.ndarray:
    """The (4, 4) rigid transform rotating by ``angle_rad`` about the line ``offset_m + s * axis``."""
    R = axis_angle_matrix(axis, angle_rad)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = offset_m - R @ offset_m
    return T


def _check_rigid(T: np.ndarray, i: int) -> np.ndarray:
    T = np.array(T, dtype=np.float64)
    if T.shape == (16,):
        T = T.reshape(4, 4)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise InputError(f"discrete symmetry #{i} must be a finite (4, 4) matrix, got shape {T.shape}")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise InputError(f"discrete symmetry #{i} is not a proper rotation (R R^T != I or det < 0): {R.tolist()}")
    if not np.allclose(T[3], [0, 0, 0, 1]):
        raise InputError(f"discrete symmetry #{i} has last row {T[3].tolist()}; expected [0, 0, 0, 1]")
    T.setflags(write=False)
    return T


def _unit_vec(v: object, name: str) -> np.ndarray:
    a = np.array(v, dtype=np.float64)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise InputError(f"symmetry {name} must be a finite 3-vector, got {a.tolist()}")
    n = np.linalg.norm(a)
    if n < 1e-12:
        raise InputError(f"symmetry {name} must be non-zero, got {a.tolist()}")
    return a / n


@dataclass(frozen=True, eq=False)
class Symmetry:
    """An object's symmetry group (BOP convention, metres).

    Attributes:
        kind: ``"none"``, ``"discrete"`` or ``"continuous"``.
        discrete: tuple of (4, 4) rigid transforms (translation in metres), identity
            excluded. For ``kind="continuous"`` it may hold extra discrete
            symmetries combined with the rotation (BOP allows both, e.g. a
            cylinder that can also be flipped end over end).
        axis: (3,) unit axis of the continuous symmetry, else ``None``.
        offset_m: (3,) point on the continuous axis in metres, else ``None``.
    """

    kind: SymmetryKind = "none"
    discrete: tuple[np.ndarray, ...] = field(default=())
    axis: np.ndarray | None = None
    offset_m: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.kind not in ("none", "discrete", "continuous"):
            raise InputError(f"unknown symmetry kind {self.kind!r}; allowed: none, discrete, continuous")
        object.__setattr__(self, "discrete", tuple(_check_rigid(T, i) for i, T in enumerate(self.discrete)))
        if self.kind == "continuous":
            if self.axis is None:
                raise InputError("a continuous symmetry needs an axis (3,)")
            offset = np.zeros(3) if self.offset_m is None else np.array(self.offset_m, dtype=np.float64)
            if offset.shape != (3,) or not np.all(np.isfinite(offset)):
                raise InputError(f"symmetry offset_m must be a finite 3-vector, got {offset.tolist()}")
            axis = _unit_vec(self.axis, "axis")
            axis.setflags(write=False)
            offset.setflags(write=False)
            object.__setattr__(self, "axis", axis)
            object.__setattr__(self, "offset_m", offset)
            return
        if self.axis is not None or self.offset_m is not None:
            raise InputError(f"symmetry kind {self.kind!r} takes no axis/offset; use kind='continuous'")
        if self.kind == "discrete" and not self.discrete:
            raise InputError("a discrete symmetry needs at least one (4, 4) transform")
        if self.kind == "none" and self.discrete:
            raise InputError("symmetry kind 'none' takes no transforms; use kind='discrete'")

    @staticmethod
    def none() -> Symmetry:
        """No symmetry."""
        return Symmetry()

    @staticmethod
    def continuous(axis: object, offset_m: object = (0.0, 0.0, 0.0)) -> Symmetry:
        """Invariance to any rotation about the line through ``offset_m`` (metres) along ``axis``."""
        return Symmetry("continuous", (), np.asarray(axis, float), np.asarray(offset_m, float))

    @staticmethod
    def discrete_from(transforms: object) -> Symmetry:
        """A discrete symmetry from (4, 4) (or flattened (16,)) transforms, translations in metres."""
        return Symmetry("discrete", tuple(np.asarray(T, float) for T in transforms))  # type: ignore[union-attr]

    @staticmethod
    def cyclic(axis: object, order: int, offset_m: object = (0.0, 0.0, 0.0)) -> Symmetry:
        """The ``order``-fold rotational symmetry about a line (``order`` >= 2)."""
        if int(order) < 2:
            raise InputError(f"a cyclic symmetry needs order >= 2, got {order}")
        a = _unit_vec(axis, "axis")
        o = np.asarray(offset_m, dtype=np.float64)
        Ts = [rotation_about_line(a, o, 2 * np.pi * k / order) for k in range(1, int(order))]
        return Symmetry.discrete_from(Ts)

    @staticmethod
    def from_name(name: str) -> Symmetry:
        """Parse a spec name: ``none``, ``continuous_{x,y,z}``, ``discrete_{x,y,z}{2,4}`` (half or quarter
        turns about a model axis).

        Axes pass through the model origin.
        """
        if name == "none":
            return Symmetry.none()
        if name.startswith("continuous_") and name[-1] in _AXES and len(name) == len("continuous_x"):
            return Symmetry.continuous(_AXES[name[-1]])
        if name in SYMMETRY_NAMES and name.startswith("discrete_"):
            return Symmetry.cyclic(_AXES[name[-2]], int(name[-1]))
        raise InputError(f"unknown symmetry name {name!r}; allowed: {', '.join(SYMMETRY_NAMES)}")

    def discretize(self, n: int = 36) -> list[np.ndarray]:
        """Sample the symmetry group as (4, 4) rigid transforms (identity first).

        For a continuous symmetry this returns ``n`` rotations by ``2 pi k / n``
        about the axis line (times each discrete symmetry, if any); for a
        discrete one, the identity plus its transforms (``n`` is ignored); for
        none, ``[identity]``. Used by symmetry-aware losses and metrics.

        Args:
            n: number of samples of a continuous rotation, >= 1.

        Returns:
            list of (4, 4) float64 transforms, translations in metres.
        """
        if int(n) < 1:
            raise InputError(f"discretize needs n >= 1, got {n}")
        base = [np.eye(4), *(T.copy() for T in self.discrete)]
        if self.kind != "continuous":
            return base
        assert self.axis is not None and self.offset_m is not None
        rots = [rotation_about_line(self.axis, self.offset_m, 2 * np.pi * k / n) for k in range(int(n))]
        return [Rk @ D for D in base for Rk in rots]

    def __repr__(self) -> str:
        if self.kind == "continuous":
            return f"Symmetry(continuous, axis={np.round(self.axis, 6).tolist()}, offset_m={self.offset_m.tolist()})"
        return f"Symmetry({self.kind}, {len(self.discrete)} transforms)"
