"""Frozen dataclasses shared by the stages.

Transform naming: ``T_a_from_b`` maps coordinates expressed in frame ``b`` to
frame ``a``: ``x_a = T_a_from_b.apply(x_b)``. Units are metres and radians.

Pixel convention (used everywhere in cadalign): pixel ``(u, v)`` with integer
``u`` covers ``[u, u+1)``; its centre is at ``u + 0.5``. So with intrinsics
``K``, the ray through the centre of pixel column ``i`` and row ``j`` is
``K^-1 @ (i + 0.5, j + 0.5, 1)``. This is COLMAP's convention and OpenGL's
window convention (so pyrender renders and cadalign ray casts agree); OpenCV
puts pixel centres at integers, so subtract 0.5 when handing points to cv2.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cadalign.errors import DegenerateGeometryError, InputError

Progress = Callable[[Iterable[Any], str, int | None], Iterable[Any]]
"""A progress wrapper, ``progress(items, description, total) -> items``: yields ``items`` while showing progress
(``total``: how many, None when unknown). The CLI passes a rich bar; the library never draws one itself."""


def _as_f64(a: object, shape: tuple[int, ...], name: str, *, finite: bool = False) -> np.ndarray:
    try:
        arr = np.array(a, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be a {shape} array of numbers, got {a!r:.80}") from exc
    if arr.shape != shape:
        raise InputError(f"{name} must have shape {shape}, got {arr.shape}")
    if finite and not np.all(np.isfinite(arr)):
        raise InputError(f"{name} must be finite, got {arr.tolist()}; a transform with NaN/inf is undefined")
    arr.setflags(write=False)
    return arr


def _checked_apply(out: np.ndarray, x: np.ndarray, what: str) -> np.ndarray:
    """``out`` unless finite input points overflowed to inf/NaN (then a DegenerateGeometryError)."""
    if not np.all(np.isfinite(out)) and np.all(np.isfinite(x)):
        raise DegenerateGeometryError(
            f"{what}.apply overflowed float64 (points up to {np.abs(x).max():.3g} m); the transform's scale or "
            "translation is out of range - check the units of the inputs"
        )
    return out


@dataclass(frozen=True)
class Rigid3:
    """A rigid transform ``x_a = R @ x_b + t`` (``a_from_b``).

    Construction raises :class:`~cadalign.errors.InputError` for a wrong shape or a NaN/inf entry.

    Attributes:
        R: (3, 3) rotation matrix.
        t: (3,) translation in metres.
    """

    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        object.__setattr__(self, "R", _as_f64(self.R, (3, 3), "Rigid3.R", finite=True))
        object.__setattr__(self, "t", _as_f64(self.t, (3,), "Rigid3.t", finite=True))

    @staticmethod
    def identity() -> Rigid3:
        return Rigid3()

    @staticmethod
    def from_matrix(M: np.ndarray) -> Rigid3:
        """Build from a (4, 4) homogeneous matrix."""
        M = np.asarray(M, dtype=np.float64)
        if M.shape != (4, 4):
            raise InputError(f"Rigid3.from_matrix expects a (4, 4) homogeneous matrix, got shape {M.shape}")
        return Rigid3(M[:3, :3], M[:3, 3])

    def matrix(self) -> np.ndarray:
        """The (4, 4) homogeneous matrix."""
        M = np.eye(4)
        M[:3, :3] = self.R
        M[:3, 3] = self.t
        return M

    def inverse(self) -> Rigid3:
        return Rigid3(self.R.T, -self.R.T @ self.t)

    def __matmul__(self, other: Rigid3) -> Rigid3:
        """Compose: ``(T_a_from_b @ T_b_from_c) -> T_a_from_c``."""
        return Rigid3(self.R @ other.R, self.R @ other.t + self.t)

    def apply(self, x: np.ndarray) -> np.ndarray:
        """Transform points ``(..., 3)``."""
        x = np.asarray(x, dtype=np.float64)
        with np.errstate(over="ignore", invalid="ignore"):
            return _checked_apply(x @ self.R.T + self.t, x, "Rigid3")


@dataclass(frozen=True)
class Sim3:
    """A similarity ``x_a = s * R @ x_b + t`` (``a_from_b``); ``s > 0``.

    A scale that is not finite and positive (also after ``inverse`` or ``@`` overflow) raises
    :class:`~cadalign.errors.DegenerateGeometryError`; a wrong shape or NaN/inf in ``R``/``t`` raises
    :class:`~cadalign.errors.InputError`. Both are ``ValueError`` subclasses.
    """

    s: float = 1.0
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        try:
            s = float(self.s)
        except (TypeError, ValueError) as exc:
            raise InputError(f"Sim3 scale must be a number, got {self.s!r:.80}") from exc
        if not np.isfinite(s) or s <= 0:
            raise DegenerateGeometryError(
                f"Sim3 scale must be finite and > 0, got {s}; a zero, negative or overflowing scale has no "
                "similarity (check the alignment that produced it and the units of its inputs)"
            )
        object.__setattr__(self, "s", s)
        object.__setattr__(self, "R", _as_f64(self.R, (3, 3), "Sim3.R", finite=True))
        object.__setattr__(self, "t", _as_f64(self.t, (3,), "Sim3.t", finite=True))

    @staticmethod
    def identity() -> Sim3:
        return Sim3()

    @staticmethod
    def from_rigid(T: Rigid3, s: float = 1.0) -> Sim3:
        return Sim3(s, T.R, T.t)

    def matrix(self) -> np.ndarray:
        M = np.eye(4)
        M[:3, :3] = self.s * self.R
        M[:3, 3] = self.t
        return M

    def inverse(self) -> Sim3:
        """The inverse similarity; raises DegenerateGeometryError when ``1 / s`` or ``t / s`` overflows."""
        inv_s = 1.0 / self.s
        with np.errstate(over="ignore", invalid="ignore"):
            return Sim3(inv_s, self.R.T, -inv_s * (self.R.T @ self.t))

    def __matmul__(self, other: Sim3) -> Sim3:
        """Compose; raises DegenerateGeometryError when the product's scale or translation overflows."""
        with np.errstate(over="ignore", invalid="ignore"):
            return Sim3(self.s * other.s, self.R @ other.R, self.s * (self.R @ other.t) + self.t)

    def apply(self, x: np.ndarray) -> np.ndarray:
        """Transform points ``(..., 3)``; finite points that overflow float64 raise DegenerateGeometryError."""
        x = np.asarray(x, dtype=np.float64)
        with np.errstate(over="ignore", invalid="ignore"):
            return _checked_apply(self.s * (x @ self.R.T) + self.t, x, "Sim3")

    def carry_pose(self, T_world_from_cam: Rigid3) -> Rigid3:
        """A camera pose ``T_world_from_cam`` of frame b as a pose of frame a: its centre moved by the similarity and
        its axes turned by ``R`` (the scale changes no direction), e.g. an SfM camera in the CAD frame."""
        return Rigid3(self.R @ T_world_from_cam.R, self.apply(T_world_from_cam.t[None])[0])

    def rigid(self) -> Rigid3:
        """The rotation and translation, dropping the scale."""
        return Rigid3(self.R, self.t)


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: intrinsics and image size (pixels).

    Attributes:
        K: (3, 3) intrinsic matrix, pixel-centre convention of this module.
        width: image width in pixels.
        height: image height in pixels.
    """

    K: np.ndarray
    width: int
    height: int

    def __post_init__(self) -> None:
        object.__setattr__(self, "K", _as_f64(self.K, (3, 3), "Camera.K", finite=True))
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise InputError(f"Camera image size must be positive, got {self.width}x{self.height}")
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    def scaled(self, width: int, height: int) -> Camera:
        """The same camera resampled to another resolution."""
        sx, sy = width / self.width, height / self.height
        K = self.K.copy()
        K[0] *= sx
        K[1] *= sy
        return Camera(K, width, height)


@dataclass(frozen=True)
class Detection:
    """One detected part instance in an image (what a detector hands to pose refinement and fusion)."""

    box_xyxy: np.ndarray
    """(4,) pixels in the input image."""
    label: int
    """Class index in the detector's class list (0 = background, never returned)."""
    score: float
    """Classification score in [0, 1]."""
    mask: np.ndarray
    """(H, W) bool in the input image."""
    R_cam_from_obj: np.ndarray
    """(3, 3) rotation object -> camera."""
    t_cam_from_obj_m: np.ndarray
    """(3,) translation object -> camera, metres."""
    obj_id: int | None = None
    """The CAD model (BOP obj_id) when the detector knows it; a network reports only the class."""
