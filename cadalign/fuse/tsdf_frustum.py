"""The frustum label update of the semantic TSDF (see :mod:`cadalign.fuse.tsdf_labels`), split over threads.

The offset-major samples (``n`` per pixel, ``n P`` in all) are cut into contiguous runs, one per thread;
each run computes its samples' voxels, blocks, rows and updated values into its own slices of shared
arrays (NumPy releases the GIL inside its loops, so the runs use separate cores). What needs every sample
(the distinct blocks, the hash query, the final write) runs once. Sample order, arithmetic and the write
order are those of the single-threaded path, so the result does not depend on the number of threads.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from cadalign.fuse import tsdf_labels
from cadalign.fuse.semantic import clamped_log_probs, gather_rows, renormalise, scatter_rows, take_rows
from cadalign.fuse.tsdf_labels import sample_voxels, split_blocks

Segment = tuple[int, int, int]
"""``(offset index j, first pixel, end pixel)``: samples ``j P + p0 .. j P + p1`` of the offset-major order."""
MIN_SAMPLES_PER_THREAD = 50_000
"""Below this many samples per thread the hand-over costs more than it saves."""


def segments(n: int, p: int, parts: int) -> list[list[Segment]]:
    """Split the ``n p`` offset-major samples into ``parts`` contiguous runs of nearly equal length."""
    total = n * p
    bounds = [round(total * i / parts) for i in range(parts + 1)]
    out = []
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        run, s = [], a
        while s < b:
            j, p0 = divmod(s, p)
            p1 = min(p, p0 + (b - s))
            run.append((j, p0, p1))
            s += p1 - p0
        out.append(run)
    return out


class FrustumLabeler:
    """Runs the frustum label update with ``threads`` threads (a pool kept for the map's lifetime)."""

    def __init__(self, threads: int) -> None:
        self.threads = max(1, int(threads))
        self._pool: ThreadPoolExecutor | None = None

    def _map(self, fn: Callable[[Any], Any], items: list[Any]) -> list[Any]:
        if len(items) <= 1:
            return [fn(item) for item in items]
        if self._pool is None:
            self._pool = ThreadPoolExecutor(self.threads - 1, thread_name_prefix="cadalign-fuse-labels")
        futures = [self._pool.submit(fn, item) for item in items[1:]]
        first = fn(items[0])
        return [first] + [f.result() for f in futures]

    def update(self, label: np.ndarray, probs: np.ndarray, pix: np.ndarray, rays: tuple[np.ndarray, np.ndarray],
               depth: np.ndarray, T_vox: np.ndarray, offsets: np.ndarray, res: int, min_prob: float,
               log_floor: float, find_rows: Callable[[np.ndarray], np.ndarray], cell_voxels: int = 1) -> bool:
        """Bayes-update the (N, C) ``label`` rows of the samples of pixels ``pix`` in place; False (nothing
        done) if their blocks span more than :data:`~cadalign.fuse.tsdf_labels.MAX_TABLE_CELLS` cells.

        ``probs`` (C, H W) float32; ``rays`` the per-pixel slopes; ``depth`` (H W,) float32 metres; ``T_vox``
        local-from-camera with voxel units; ``find_rows`` maps (K, 3) int32 block keys to (K,) int32 buffer
        rows (-1: not allocated); ``cell_voxels`` the label cell edge in voxels.
        """
        parts = min(self.threads, max(1, len(offsets) * len(pix) // MIN_SAMPLES_PER_THREAD))
        w = _LabelPass(label, probs, pix, rays, depth, T_vox, offsets, res, min_prob, log_floor, parts, cell_voxels)
        ranges = self._map(w.voxels, list(range(parts)))
        lo = np.min([r[0] for r in ranges], axis=0).astype(np.int64)
        shape = np.max([r[1] for r in ranges], axis=0).astype(np.int64) - lo + 1
        n_cells = int(np.prod(shape))
        if n_cells > tsdf_labels.MAX_TABLE_CELLS:
            return False
        self._map(lambda i: w.to_cells(i, lo, shape), list(range(parts)))
        mark = np.zeros(n_cells, dtype=bool)
        mark[w.cells] = True
        key_cells = np.flatnonzero(mark)
        table = np.empty(n_cells, dtype=np.int32)  # only cells of keys are ever read
        table[key_cells] = find_rows(tsdf_labels.keys_of_cells(key_cells, lo, shape))
        flat, post = w.flat, w.post
        if any(self._map(lambda i: w.bayes(i, table), list(range(parts)))):  # samples outside blocks (rare)
            keep = flat >= 0
            flat, post = flat[keep], take_rows(post, keep)
        scatter_rows(label, flat, post)
        return True


class _LabelPass:
    """One frame's label update: inputs, the shared per-sample arrays, and the work of run ``i``."""

    def __init__(self, label: np.ndarray, probs: np.ndarray, pix: np.ndarray, rays: tuple[np.ndarray, np.ndarray],
                 depth: np.ndarray, T_vox: np.ndarray, offsets: np.ndarray, res: int, min_prob: float,
                 log_floor: float, parts: int, cell_voxels: int = 1) -> None:
        self.label, self.probs, self.pix, self.rays, self.depth = label, probs, pix, rays, depth
        self.T_vox, self.offsets, self.res, self.min_prob, self.log_floor = T_vox, offsets, res, min_prob, log_floor
        self.p, self.parts, self.cell_voxels = len(pix), parts, cell_voxels
        self.runs = segments(len(offsets), self.p, parts)
        m = len(offsets) * self.p
        self.block = np.empty((3, m), dtype=np.int32)
        self.local = np.empty(m, dtype=np.int32)
        self.obs = np.empty((self.p, label.shape[1]), dtype=np.float32)
        self.cells = np.empty(m, dtype=np.int64)
        self.flat = np.empty(m, dtype=np.int64)
        self.post = np.empty((m, label.shape[1]), dtype=np.float32)

    def _slices(self, i: int) -> list[tuple[slice, int, int]]:
        return [(slice(j * self.p + p0, j * self.p + p1), p0, p1) for j, p0, p1 in self.runs[i]]

    def voxels(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Blocks and in-block offsets of run ``i``'s samples, its share of the observations; block key range."""
        for (s, p0, p1), (j, _, _) in zip(self._slices(i), self.runs[i], strict=True):
            pp = self.pix[p0:p1]
            vox = sample_voxels(self.rays[0][pp], self.rays[1][pp], self.depth[pp], self.T_vox, self.offsets[j:j + 1],
                                self.cell_voxels)
            self.block[:, s], self.local[s] = split_blocks(vox, self.res)
        q0, q1 = self.p * i // self.parts, self.p * (i + 1) // self.parts
        self.obs[q0:q1] = clamped_log_probs(np.take(self.probs, self.pix[q0:q1], axis=1), self.min_prob).T
        mine = np.concatenate([self.block[:, s] for s, _, _ in self._slices(i)], axis=1)
        return mine.min(axis=1), mine.max(axis=1)

    def to_cells(self, i: int, lo: np.ndarray, shape: np.ndarray) -> None:
        for s, _, _ in self._slices(i):
            self.cells[s] = tsdf_labels.block_cells(self.block[:, s], lo, shape)

    def bayes(self, i: int, table: np.ndarray) -> bool:
        """Voxel rows and updated values of run ``i``'s samples; True if some sample has no voxel (-1)."""
        missing = False
        for s, p0, p1 in self._slices(i):
            rows = table[self.cells[s]]
            np.multiply(rows, self.res**3, out=self.flat[s], dtype=np.int64)
            self.flat[s] += self.local[s]
            if rows.min() < 0:
                self.flat[s][rows < 0] = -1
                missing = True
            self.post[s] = gather_rows(self.label, self.flat[s])  # -1 reads the last row: a dummy, never written
            self.post[s] += self.obs[p0:p1]
            renormalise(self.post[s], self.log_floor)
        return missing
