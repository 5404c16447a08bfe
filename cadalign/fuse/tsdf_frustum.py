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
               log_floor: float, find_rows: Callable[[np.ndarray], np.ndarray]) -> bool:
        """Bayes-update the (N, C) ``label`` rows of the samples of pixels ``pix`` in place; False (nothing
        done) if their blocks span more than :data:`~cadalign.fuse.tsdf_labels.MAX_TABLE_CELLS` cells.

        ``probs`` (C, H W) float32; ``rays`` the per-pixel slopes; ``depth`` (H W,) float32 metres; ``T_vox``
        local-from-camera with voxel units; ``find_rows`` maps (K, 3) int32 block keys to (K,) int32 buffer
        rows (-1: not allocated).
        """
        p, n, C = len(pix), len(offsets), label.shape[1]
        parts = min(self.threads, max(1, n * p // MIN_SAMPLES_PER_THREAD))
        runs = segments(n, p, parts)
        block = np.empty((3, n * p), dtype=np.int32)
        local = np.empty(n * p, dtype=np.int32)
        obs = np.empty((p, C), dtype=np.float32)

        def voxels(i: int) -> tuple[np.ndarray, np.ndarray]:
            for j, p0, p1 in runs[i]:
                pp = pix[p0:p1]
                vox = sample_voxels(rays[0][pp], rays[1][pp], depth[pp], T_vox, offsets[j:j + 1])
                block[:, j * p + p0:j * p + p1], local[j * p + p0:j * p + p1] = split_blocks(vox, res)
            q0, q1 = p * i // parts, p * (i + 1) // parts
            obs[q0:q1] = clamped_log_probs(np.take(probs, pix[q0:q1], axis=1), min_prob).T
            mine = np.concatenate([block[:, j * p + p0:j * p + p1] for j, p0, p1 in runs[i]], axis=1)
            return mine.min(axis=1), mine.max(axis=1)

        ranges = self._map(voxels, list(range(parts)))
        lo = np.min([r[0] for r in ranges], axis=0).astype(np.int64)
        shape = np.max([r[1] for r in ranges], axis=0).astype(np.int64) - lo + 1
        n_cells = int(np.prod(shape))
        if n_cells > tsdf_labels.MAX_TABLE_CELLS:
            return False
        cells = np.empty(n * p, dtype=np.int64)

        def to_cells(i: int) -> None:
            for j, p0, p1 in runs[i]:
                s = slice(j * p + p0, j * p + p1)
                cells[s] = tsdf_labels.block_cells(block[:, s], lo, shape)

        self._map(to_cells, list(range(parts)))
        mark = np.zeros(n_cells, dtype=bool)
        mark[cells] = True
        key_cells = np.flatnonzero(mark)
        table = np.empty(n_cells, dtype=np.int32)  # only cells of keys are ever read
        table[key_cells] = find_rows(tsdf_labels.keys_of_cells(key_cells, lo, shape))
        flat = np.empty(n * p, dtype=np.int64)
        post = np.empty((n * p, C), dtype=np.float32)

        def bayes(i: int) -> bool:
            missing = False
            for j, p0, p1 in runs[i]:
                s = slice(j * p + p0, j * p + p1)
                rows = table[cells[s]]
                np.multiply(rows, res**3, out=flat[s], dtype=np.int64)
                flat[s] += local[s]
                if rows.min() < 0:
                    flat[s][rows < 0] = -1
                    missing = True
                post[s] = gather_rows(label, flat[s])  # -1 reads the last row: a dummy, never written back
                post[s] += obs[p0:p1]
                renormalise(post[s], log_floor)
            return missing

        if any(self._map(bayes, list(range(parts)))):  # samples outside allocated blocks (rare)
            keep = flat >= 0
            flat, post = flat[keep], take_rows(post, keep)
        scatter_rows(label, flat, post)
        return True
