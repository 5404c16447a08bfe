"""Differentiable, batched rotation functions in torch (float32 or float64, any device).

The conventions are those of :mod:`cadalign.geometry.rotations` (wxyz
quaternions with the same canonical sign, 6D = first two columns of ``R``,
rotation vectors in radians); tests check that both modules agree. Unlike the
numpy versions these never raise on degenerate values, since a data-dependent
check would force a device sync inside training loops: small norms are
clamped by ``eps`` instead, so outputs and gradients stay finite.

This module imports torch at the top and is deliberately not imported by
``cadalign.geometry``; import it explicitly.
"""

from __future__ import annotations

import torch

_TAYLOR_ANGLE_SQ = 1e-6
"""Below this squared angle (rad^2) the Rodrigues coefficients use their Taylor series."""


def _normalize(v: torch.Tensor, eps: float) -> torch.Tensor:
    return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True).clamp_min(eps)


def rotation_6d_to_matrix(d6: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Rotation matrices ``(..., 3, 3)`` from 6D vectors ``(..., 6)`` by Gram-Schmidt.

    Same construction as the numpy version; norms are clamped at ``eps`` rather
    than raising, so (near-)parallel inputs give a finite but meaningless result.
    """
    a1, a2 = d6[..., :3], d6[..., 3:]
    b1 = _normalize(a1, eps)
    b2 = a2 - (b1 * a2).sum(-1, keepdim=True) * b1
    b2 = _normalize(b2 - (b1 * b2).sum(-1, keepdim=True) * b1, eps)  # second pass, as in numpy
    return torch.stack([b1, b2, torch.linalg.cross(b1, b2, dim=-1)], dim=-1)


def matrix_to_rotation_6d(R: torch.Tensor) -> torch.Tensor:
    """6D vectors ``(..., 6)``: the first two columns of ``R (..., 3, 3)`` concatenated."""
    return torch.cat([R[..., :, 0], R[..., :, 1]], dim=-1)


def quaternion_to_matrix(q: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Rotation matrices ``(..., 3, 3)`` from wxyz quaternions ``(..., 4)`` (normalised first)."""
    w, x, y, z = _normalize(q, eps).unbind(-1)
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return torch.stack([torch.stack(r, -1) for r in rows], -2)


def matrix_to_quaternion(R: torch.Tensor) -> torch.Tensor:
    """Canonical unit wxyz quaternions ``(..., 4)`` from rotation matrices ``(..., 3, 3)``.

    Shepperd's method as in the numpy version: the row of ``4 q q^T`` with the
    largest diagonal is normalised (its norm is ``4 |q_k| >= 2``, so the
    gradient is bounded). The sign is then made canonical: the first non-zero
    component in ``(w, x, y, z)`` order is positive.
    """
    r = [[R[..., i, j] for j in range(3)] for i in range(3)]
    tr = r[0][0] + r[1][1] + r[2][2]
    qq = torch.stack(
        [
            torch.stack([1 + tr, r[2][1] - r[1][2], r[0][2] - r[2][0], r[1][0] - r[0][1]], -1),
            torch.stack([r[2][1] - r[1][2], 1 + r[0][0] - r[1][1] - r[2][2], r[0][1] + r[1][0], r[0][2] + r[2][0]], -1),
            torch.stack([r[0][2] - r[2][0], r[0][1] + r[1][0], 1 - r[0][0] + r[1][1] - r[2][2], r[1][2] + r[2][1]], -1),
            torch.stack([r[1][0] - r[0][1], r[0][2] + r[2][0], r[1][2] + r[2][1], 1 - r[0][0] - r[1][1] + r[2][2]], -1),
        ],
        -2,
    )
    k = torch.diagonal(qq, dim1=-2, dim2=-1).argmax(-1)
    q = torch.gather(qq, -2, k[..., None, None].expand(*k.shape, 1, 4)).squeeze(-2)
    q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    first = (q != 0).to(torch.int8).argmax(-1, keepdim=True)
    lead = torch.gather(q, -1, first)
    # + 0.0 turns -0.0 into +0.0, as in the numpy version, so both agree bitwise on signs of zeros
    return q * torch.where(lead < 0, -1.0, 1.0).to(q.dtype) + 0.0


def axis_angle_to_matrix(rotvec: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``(..., 3, 3)`` from rotation vectors ``(..., 3)`` (radians).

    Rodrigues' formula with the Taylor series below 1e-3 rad; both branches are
    evaluated on safe values so gradients are finite at the zero rotation.
    """
    t2 = (rotvec * rotvec).sum(-1)
    small = t2 < _TAYLOR_ANGLE_SQ
    t = torch.sqrt(torch.where(small, torch.ones_like(t2), t2))
    a = torch.where(small, 1 - t2 / 6 + t2 * t2 / 120, torch.sin(t) / t)
    b = torch.where(small, 0.5 - t2 / 24 + t2 * t2 / 720, 2 * (torch.sin(t / 2) / t) ** 2)
    cos = torch.where(small, 1 - t2 / 2 + t2 * t2 / 24, torch.cos(t))
    x, y, z = rotvec.unbind(-1)
    o = torch.zeros_like(x)
    K = torch.stack([torch.stack([o, -z, y], -1), torch.stack([z, o, -x], -1), torch.stack([-y, x, o], -1)], -2)
    eye = torch.eye(3, dtype=rotvec.dtype, device=rotvec.device)
    return (
        cos[..., None, None] * eye
        + a[..., None, None] * K
        + b[..., None, None] * (rotvec[..., :, None] * rotvec[..., None, :])
    )


def geodesic_angle(R1: torch.Tensor, R2: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Angle (radians, ``[0, pi]``) of ``R1^T R2`` for ``(..., 3, 3)`` batches.

    ``atan2(|vee(M - M^T)| / 2, (trace(M) - 1) / 2)`` with ``M = R1^T R2``. The
    squared norm is clamped at ``eps^2`` before the square root, so the value is
    biased by at most ``eps / 2`` and the gradient is finite (zero) at 0 and pi.
    """
    M = R1.transpose(-1, -2) @ R2
    v = torch.stack([M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1]], -1)
    sin = 0.5 * torch.sqrt((v * v).sum(-1).clamp_min(eps * eps))
    cos = 0.5 * (M.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0)
    return torch.atan2(sin, cos)
