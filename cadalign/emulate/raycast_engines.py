"""Two ray-casting engines that must agree: Open3D's BVH (fast, CPU) and exact batched Möller–Trumbore in torch.

Both take world-frame ray origins and directions ``(N, 3)`` (directions need not be unit: they are
normalised here, so the hit parameter is the Euclidean range in metres) and return :class:`RayHits`:
range, face index and barycentrics ``(u, v)`` of the hit point ``(1 - u - v) A + u B + v C`` on the face
``(A, B, C)``, so every hit can be given the mesh's colour, class, part and pane layers.

Both engines work relative to the mesh's bounding-box centre (like :mod:`cadalign.raycast.core`), so
worlds far from the origin (UTM coordinates) keep their precision: Open3D casts in float32 on the shifted
coordinates, the torch engine in float64 by default.

The torch engine is a brute-force Möller–Trumbore made practical by batched culling: faces are sorted
along a Morton curve into clusters of ``cluster_size`` faces, the clusters' (slightly padded) bounding boxes
are grouped ``BRANCH`` at a time into boxes of boxes up to at most ``TOP_MAX`` top boxes, every ray is
slab-tested down this implicit tree level by level (all rays of a chunk at once: no per-ray traversal, so
it runs as a few large tensor operations on a GPU), and only the (ray, cluster) pairs that survive are
tested exactly. The culling is conservative, so the result is the exact nearest hit. Parallel and grazing rays
(``|det|`` below a relative tolerance) miss; hits on a shared edge or vertex are accepted by both faces
(barycentric tolerance) and the tie goes to the lower face index, so no ray slips between two triangles.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Literal

import numpy as np

from cadalign.errors import InputError

log = logging.getLogger(__name__)

EngineName = Literal["bvh", "torch"]
BRANCH = 4
"""Children per box of the torch engine's culling hierarchy (boxes of boxes ... of clusters of faces)."""
TOP_MAX = 16
"""Most boxes at the top of the hierarchy (every ray is tested against all of them)."""
FAR = 1e30
"""Where boxes holding only padding are put: a point no ray passes."""


@dataclass(frozen=True)
class RayHits:
    """The nearest hit of each ray.

    Attributes:
        range_m: (N,) float64 distance from the ray origin along the unit direction; inf for a miss.
        face: (N,) int64 face index into the mesh; -1 for a miss.
        bary: (N, 2) float64 barycentrics ``(u, v)`` of the hit (weights of the face's 2nd and 3rd
            vertex); 0 for a miss.
    """

    range_m: np.ndarray
    face: np.ndarray
    bary: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        """(N,) bool: the ray hit a face."""
        return self.face >= 0


def _check_mesh(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise InputError(f"ray casting needs vertices (V, 3) and faces (F, 3), got {v.shape} and {f.shape}")
    if len(f) == 0:
        raise InputError("ray casting needs at least one triangle; the mesh has no faces")
    centre = (v.min(0) + v.max(0)) / 2
    return v - centre, f, centre


def _check_rays(origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    o = np.asarray(origins, dtype=np.float64)
    d = np.asarray(directions, dtype=np.float64)
    if o.ndim == 1:
        o = np.broadcast_to(o, d.shape)
    if d.ndim != 2 or d.shape[1] != 3 or o.shape != d.shape:
        raise InputError(f"rays need origins and directions of shape (N, 3), got {o.shape} and {d.shape}")
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    if not np.all(np.isfinite(d)) or np.any(norm == 0) or not np.all(np.isfinite(o)):
        raise InputError("ray origins and directions must be finite and directions non-zero")
    return o, d / norm


class BVHEngine:
    """Open3D ``RaycastingScene`` (Embree BVH, float32, all CPU threads unless ``nthreads`` is set)."""

    name = "bvh"

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, *, nthreads: int = 0) -> None:
        import open3d as o3d  # lazy: heavy dependency (open3d)

        v, f, self._centre = _check_mesh(vertices, faces)
        self._n_faces = len(f)
        self._nthreads = int(nthreads)
        mesh = o3d.t.geometry.TriangleMesh()
        mesh.vertex.positions = o3d.core.Tensor(np.ascontiguousarray(v, dtype=np.float32))
        mesh.triangle.indices = o3d.core.Tensor(np.ascontiguousarray(f, dtype=np.int32))
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(mesh)

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> RayHits:
        """Nearest hits of rays ``origins + t * directions / |directions|`` (world frame, metres)."""
        o, d = _check_rays(origins, directions)
        return self.cast_unit(o - self._centre, d, local=True)

    def cast_unit(self, origins: np.ndarray, unit_dirs: np.ndarray, *, local: bool = False) -> RayHits:
        """Like :meth:`cast` for already-unit directions (no checks; the fast path of the sensors)."""
        import open3d as o3d  # lazy: heavy dependency (open3d)

        rays = np.empty((len(unit_dirs), 6), dtype=np.float32)
        rays[:, :3] = origins if local else origins - self._centre
        rays[:, 3:] = unit_dirs
        ans = self._scene.cast_rays(o3d.core.Tensor.from_numpy(rays), nthreads=self._nthreads)
        t = ans["t_hit"].numpy().astype(np.float64)  # inf for a miss
        miss = ~np.isfinite(t)
        face = ans["primitive_ids"].numpy().astype(np.int64)
        face[miss] = -1
        bary = ans["primitive_uvs"].numpy().astype(np.float64)
        bary[miss] = 0.0
        return RayHits(t, face, bary)


def torch_as(a: np.ndarray, engine: TorchEngine):  # noqa: ANN201
    """``a`` as a tensor of the engine's dtype on its device."""
    return engine._torch.as_tensor(a, dtype=engine._dtype, device=engine._dev)


def _slab(o, inv, lo, hi):
    """Boolean slab test of rays (origins ``o``, inverse directions ``inv``) against boxes ``[lo, hi]``."""
    t0, t1 = (lo - o) * inv, (hi - o) * inv
    enter = t0.minimum(t1).amax(-1).clamp(min=0)
    return enter <= t0.maximum(t1).amin(-1)


def _morton_order(points: np.ndarray) -> np.ndarray:
    """Indices sorting (N, 3) points along a 30-bit Morton (Z-order) curve of their bounding box."""
    lo, hi = points.min(0), points.max(0)
    q = ((points - lo) / np.maximum(hi - lo, 1e-12) * 1023).astype(np.uint64)

    def spread(x: np.ndarray) -> np.ndarray:
        x = x & np.uint64(0x3FF)
        x = (x | (x << np.uint64(16))) & np.uint64(0x030000FF)
        x = (x | (x << np.uint64(8))) & np.uint64(0x0300F00F)
        x = (x | (x << np.uint64(4))) & np.uint64(0x030C30C3)
        return (x | (x << np.uint64(2))) & np.uint64(0x09249249)

    code = spread(q[:, 0]) | (spread(q[:, 1]) << np.uint64(1)) | (spread(q[:, 2]) << np.uint64(2))
    return np.argsort(code, kind="stable")


class TorchEngine:
    """Exact batched Möller–Trumbore in torch (CPU or GPU), culled by clusters of faces.

    Args:
        vertices: (V, 3) world positions, metres.
        faces: (F, 3) vertex indices.
        device: torch device, e.g. ``"cpu"`` or ``"cuda"``.
        dtype: ``"float64"`` (exact; default) or ``"float32"`` (faster on GPUs).
        cluster_size: faces per culling cluster.
        budget: largest number of (ray, cluster) slab tests or (ray, face) tests held in memory at once.
        det_tol: rays with ``|det| <= det_tol * |e1| |e2|`` (sine of the ray-plane angle) are parallel: miss.
        bary_tol: barycentric slack accepting hits exactly on an edge or vertex.
    """

    name = "torch"

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, *, device: str = "cpu",
                 dtype: Literal["float64", "float32"] = "float64", cluster_size: int = 8,
                 budget: int = 4_000_000, det_tol: float = 1e-12, bary_tol: float = 1e-9) -> None:
        import torch  # lazy: heavy dependency (torch)

        v, f, self._centre = _check_mesh(vertices, faces)
        self._torch = torch
        self._dev = torch.device(device)
        self._dtype = getattr(torch, dtype)
        self._budget, self._det_tol, self._bary_tol = int(budget), float(det_tol), float(bary_tol)
        tri = v[f]  # (F, 3, 3)
        order = _morton_order(tri.mean(1))
        G, B = int(cluster_size), BRANCH
        n_clusters = -(-len(f) // G)
        levels = max(0, int(np.ceil(np.log(max(n_clusters / TOP_MAX, 1.0)) / np.log(B))))
        n_top = -(-n_clusters // B**levels)
        n_pad = n_top * B**levels * G - len(f)
        order = np.concatenate([order, np.full(n_pad, order[-1])])  # pad with repeats of the last face
        tri = tri[order]
        lo = tri.min(1).reshape(-1, G, 3).min(1)
        hi = tri.max(1).reshape(-1, G, 3).max(1)
        pad = 1e-9 * max(1.0, float(np.abs(v).max())) + 1e-7 * np.maximum(hi - lo, 0).max(1, keepdims=True)
        lo, hi = lo - pad, hi + pad
        self._G, self._B = G, B
        self._face_ids = torch.as_tensor(order, device=self._dev)
        self._boxes = self._hierarchy(lo, hi, np.arange(len(lo)) < n_clusters, levels)
        t = torch.as_tensor(tri, dtype=self._dtype, device=self._dev)
        e1, e2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
        scale = (torch.linalg.norm(e1, dim=1) * torch.linalg.norm(e2, dim=1))[:, None]
        self._packed = torch.cat([t[:, 0], e1, e2, scale], 1)  # (F', 10): one gather per test batch

    def _hierarchy(self, lo: np.ndarray, hi: np.ndarray, valid: np.ndarray, levels: int) -> list:
        """(lo, hi) tensors per level, top first, down to the clusters; boxes of padding only sit at FAR."""
        boxes = []
        for level in range(levels + 1):
            boxes.insert(0, tuple(torch_as(np.where(valid[:, None], a, FAR), self) for a in (lo, hi)))
            if level < levels:  # parents bound their real children only
                lo = np.where(valid[:, None], lo, np.inf).reshape(-1, self._B, 3).min(1)
                hi = np.where(valid[:, None], hi, -np.inf).reshape(-1, self._B, 3).max(1)
                valid = valid.reshape(-1, self._B).any(1)
        return boxes

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> RayHits:
        """Nearest hits of rays ``origins + t * directions / |directions|`` (world frame, metres)."""
        o, d = _check_rays(origins, directions)
        return self.cast_unit(o - self._centre, d, local=True)

    def cast_unit(self, origins: np.ndarray, unit_dirs: np.ndarray, *, local: bool = False) -> RayHits:
        """Like :meth:`cast` for already-unit directions."""
        torch = self._torch
        o_all = np.asarray(origins, dtype=np.float64) - (0.0 if local else self._centre)
        o_all = np.broadcast_to(o_all, np.shape(unit_dirs))
        n = len(unit_dirs)
        rng, face, bary = np.full(n, np.inf), np.full(n, -1, np.int64), np.zeros((n, 2))
        chunk = max(64, self._budget // (len(self._boxes[0][0]) * self._B))
        for s in range(0, n, chunk):
            o = torch.as_tensor(np.array(o_all[s:s + chunk]), dtype=self._dtype, device=self._dev)
            d = torch.as_tensor(np.array(unit_dirs[s:s + chunk]), dtype=self._dtype, device=self._dev)
            t_c, f_c, b_c = self._cast_chunk(o, d)
            rng[s:s + chunk] = t_c.double().cpu().numpy()
            face[s:s + chunk] = f_c.cpu().numpy()
            bary[s:s + chunk] = b_c.double().cpu().numpy()
        return RayHits(rng, face, bary)

    def _slab_pairs(self, o, d):  # -> (ray index (P,), cluster index (P,))
        """(ray, cluster) pairs whose padded boxes the rays enter at t >= 0, descending the box hierarchy."""
        torch = self._torch
        # a zero direction component becomes a tiny one: the slab is then (-huge, huge) or empty, no NaN
        eps = torch.finfo(d.dtype).tiny
        tiny = torch.where(d >= 0, torch.full_like(d, eps), torch.full_like(d, -eps))
        inv = 1.0 / torch.where(d == 0, tiny, d)
        lo, hi = self._boxes[0]
        rays, nodes = _slab(o[:, None], inv[:, None], lo[None], hi[None]).nonzero(as_tuple=True)
        children = torch.arange(self._B, device=self._dev)[None]
        for lo, hi in self._boxes[1:]:
            idx = nodes[:, None] * self._B + children  # (P, B)
            p, k = _slab(o[rays][:, None], inv[rays][:, None], lo[idx], hi[idx]).nonzero(as_tuple=True)
            rays, nodes = rays[p], idx[p, k]
        return rays, nodes

    def _cast_chunk(self, o, d):
        torch = self._torch
        R = len(o)
        best_t = torch.full((R,), float("inf"), dtype=self._dtype, device=self._dev)
        best_f = torch.full((R,), -1, dtype=torch.int64, device=self._dev)
        best_b = torch.zeros((R, 2), dtype=self._dtype, device=self._dev)
        rays, clusters = self._slab_pairs(o, d)
        step = max(1, self._budget // self._G)
        for s in range(0, len(rays), step):
            r, c = rays[s:s + step], clusters[s:s + step]
            t, f, b = self._test_pairs(o[r], d[r], c)
            self._merge(best_t, best_f, best_b, r, t, f, b)
        return best_t, best_f, best_b

    def _test_pairs(self, o, d, clusters):
        """Möller–Trumbore of each pair's ray (P, 3) against its cluster's G faces -> nearest (t, face, bary)."""
        torch = self._torch
        idx = clusters[:, None] * self._G + torch.arange(self._G, device=self._dev)[None]  # (P, G)
        pk = self._packed[idx]
        v0, e1, e2, scale = pk[..., 0:3], pk[..., 3:6], pk[..., 6:9], pk[..., 9]
        dd = d[:, None].expand_as(e2)
        pvec = torch.linalg.cross(dd, e2)
        det = (e1 * pvec).sum(-1)
        parallel = det.abs() <= self._det_tol * scale
        inv_det = 1.0 / torch.where(parallel, torch.ones_like(det), det)
        tvec = o[:, None] - v0
        u = (tvec * pvec).sum(-1) * inv_det
        qvec = torch.linalg.cross(tvec, e1)
        v = (dd * qvec).sum(-1) * inv_det
        t = (e2 * qvec).sum(-1) * inv_det
        eps = self._bary_tol
        ok = ~parallel & (u >= -eps) & (v >= -eps) & (u + v <= 1 + eps) & (t > 0)
        t = torch.where(ok, t, torch.full_like(t, float("inf")))
        tmin = t.amin(1)
        ids = self._face_ids[idx]
        big = torch.iinfo(torch.int64).max
        cand = torch.where((t == tmin[:, None]) & ok, ids, torch.full_like(ids, big))
        f = cand.amin(1)
        pos = (cand == f[:, None]).to(torch.int64).argmax(1)  # the column of the winning face
        u_w = u.gather(1, pos[:, None])[:, 0].clamp(0, 1)
        v_w = v.gather(1, pos[:, None])[:, 0].clamp(0, 1)
        f = torch.where(torch.isfinite(tmin), f, torch.full_like(f, -1))
        return tmin, f, torch.stack([u_w, v_w], 1)

    def _merge(self, best_t, best_f, best_b, r, t, f, b) -> None:
        """Fold pair results into the per-ray bests: nearest t, ties to the lowest face index."""
        torch = self._torch
        hit = f >= 0
        r, t, f, b = r[hit], t[hit], f[hit], b[hit]
        if len(r) == 0:
            return
        old_t = best_t[r]
        best_t.scatter_reduce_(0, r, t, reduce="amin")
        new_t = best_t[r]
        win = t == new_t
        big = torch.iinfo(torch.int64).max
        fmin = torch.full_like(best_f, big)
        fmin.scatter_reduce_(0, r, torch.where(win, f, torch.full_like(f, big)), reduce="amin")
        # a strictly nearer hit replaces the old face; an equally near one only a higher old face index
        take = win & (f == fmin[r]) & ((new_t < old_t) | (f < best_f[r]))
        best_f[r[take]] = f[take]
        best_b[r[take]] = b[take]


def make_engine(name: EngineName, vertices: np.ndarray, faces: np.ndarray, *, device: str = "cpu",
                nthreads: int = 0) -> BVHEngine | TorchEngine:
    """The engine called ``name`` ("bvh" or "torch") over a mesh."""
    if name == "bvh":
        return BVHEngine(vertices, faces, nthreads=nthreads)
    if name == "torch":
        return TorchEngine(vertices, faces, device=device)
    raise InputError(f"unknown ray-casting engine {name!r}; allowed: bvh, torch")
