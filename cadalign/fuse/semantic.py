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
import torch

from cadalign.errors import InputError


def bayes_update(stored: torch.Tensor, obs_log_probs: torch.Tensor, log_floor: float) -> torch.Tensor:
    """One recursive Bayes update of (N, C) stored relative log-probabilities with (N, C) observations.

    ``obs_log_probs`` must already be clamped (see :func:`clamped_log_probs`). Returns the new stored values:
    the largest entry of each row is 0 and every entry is >= ``log_floor``; ``softmax`` gives probabilities.
    """
    post = stored + obs_log_probs
    post -= post.amax(dim=-1, keepdim=True)
    return post.clamp_(min=log_floor)


def clamped_log_probs(probs: torch.Tensor, min_prob: float) -> torch.Tensor:
    """Log of probabilities clamped to ``[min_prob, 1]`` (non-finite inputs count as ``min_prob``)."""
    p = torch.nan_to_num(probs.float(), nan=min_prob, posinf=1.0, neginf=min_prob)
    return p.clamp(min=min_prob, max=1.0).log()


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
