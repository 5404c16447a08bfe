"""Bayesian label fusion in the log domain (SemanticFusion-style), shared by the TSDF and surfel maps.

Each map element (voxel or surfel) holds class log-probabilities. An observation with class probabilities
``p_obs`` multiplies the element's distribution and renormalises (a recursive Bayes update that assumes
independent observations)::

    L  <-  L + log clamp(p_obs, p_min, 1)  -  max_c(...)          p = softmax(L)

The renormalisation is done in the log domain by subtracting the largest entry, so the stored values are
log-probabilities *relative to the most likely class* (``L_c = log p_c - log p_max``): the exact posterior
is ``softmax(L)``, and a logsumexp per update (the costly part at a million voxels a frame) is avoided.

Stability over thousands of frames comes from three choices: inputs are clamped to ``[p_min, 1]`` (one frame
moves a log-ratio by at most ``-log p_min``), the result is renormalised every update (the largest entry is
exactly 0, nothing can overflow or drift), and every entry is floored at ``log_floor`` (a long confident
history never makes a class impossible, so the map can still change its mind, and values stay finite).
A zero-filled (freshly allocated) element means the uniform distribution, so new voxel blocks need no
initialisation pass.
"""

from __future__ import annotations

import numpy as np

from cadalign.errors import InputError


def bayes_update(stored: np.ndarray, obs_log_probs: np.ndarray, log_floor: float) -> np.ndarray:
    """One recursive Bayes update of (N, C) stored relative log-probabilities with (N, C) observations.

    ``obs_log_probs`` must already be clamped (see :func:`clamped_log_probs`). Returns the new stored values
    (float32): the largest entry of each row is 0 and every entry is >= ``log_floor``; ``softmax`` gives the
    probabilities. (NumPy, column by column: with few classes this is ~10x faster than a row-wise max.)
    """
    return renormalise(np.add(stored, obs_log_probs, dtype=np.float32), log_floor)


def renormalise(post: np.ndarray, log_floor: float) -> np.ndarray:
    """In place: subtract each row's largest entry from an (N, C) float32 array, then floor it at ``log_floor``."""
    top = post[:, 0].copy()
    for c in range(1, post.shape[1]):  # column by column into one buffer: no temporaries
        np.maximum(top, post[:, c], out=top)
    post -= top[:, None]
    return np.maximum(post, np.float32(log_floor), out=post)


def clamped_log_probs(probs: np.ndarray, min_prob: float) -> np.ndarray:
    """(N, C) float32 log of probabilities clamped to ``[min_prob, 1]`` (non-finite inputs count as ``min_prob``)."""
    p = np.fmax(np.asarray(probs, dtype=np.float32), np.float32(min_prob))  # fmax maps NaN to min_prob
    np.fmin(p, np.float32(1.0), out=p)
    return np.log(p, out=p)


def take_rows(a: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """``a[keep]`` for a C-contiguous (N, C) array and an (N,) bool mask, moving whole rows at once."""
    return _as_void(a)[keep].view(a.dtype).reshape(-1, a.shape[1])


def gather_rows(table: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """``table[rows]`` for a C-contiguous (N, C) table, copying whole rows at once."""
    return _as_void(table)[rows].view(table.dtype).reshape(len(rows), table.shape[1])


def scatter_rows(table: np.ndarray, rows: np.ndarray, values: np.ndarray) -> None:
    """``table[rows] = values`` (whole rows at once; with repeated rows one of the values is kept)."""
    _as_void(table)[rows] = _as_void(np.ascontiguousarray(values, dtype=table.dtype))


def _as_void(a: np.ndarray) -> np.ndarray:
    return a.view(np.dtype((np.void, a.dtype.itemsize * a.shape[1]))).reshape(a.shape[0])


def probs_from_labels(labels: np.ndarray, n_classes: int, confidence: float) -> np.ndarray:
    """(C, H, W) float32 probabilities from an (H, W) class-index map.

    The labelled class gets ``confidence`` and the others share the rest equally: ground-truth labels are
    treated as a very confident classifier rather than a certainty, so a wrong pixel (an edge, a pose error)
    can be outvoted by other frames.
    """
    labels = np.asarray(labels)
    if labels.ndim != 2:
        raise InputError(f"a label map must be (H, W), got shape {labels.shape}")
    if labels.size and (labels.min() < 0 or labels.max() >= n_classes):
        raise InputError(f"label values must lie in [0, {n_classes - 1}] for {n_classes} classes; "
                         f"got [{labels.min()}, {labels.max()}] (check the class list)")
    if not 0.0 < confidence <= 1.0:
        raise InputError(f"label confidence must be in (0, 1], got {confidence}")
    rest = (1.0 - confidence) / max(n_classes - 1, 1)
    out = np.full((n_classes, *labels.shape), rest, dtype=np.float32)
    np.put_along_axis(out, labels[None].astype(np.int64), np.float32(confidence), axis=0)
    return out


def check_probs(probs: np.ndarray, n_classes: int, shape: tuple[int, int]) -> np.ndarray:
    """Validate a (C, H, W) probability map for a frame of ``shape`` (H, W); returns it as float32."""
    probs = np.asarray(probs)
    if probs.shape != (n_classes, *shape):
        raise InputError(f"class probabilities must have shape ({n_classes}, {shape[0]}, {shape[1]}) "
                         f"(classes, height, width); got {probs.shape}")
    return probs.astype(np.float32, copy=False)
