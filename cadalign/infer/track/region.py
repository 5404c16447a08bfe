"""The region term of the contour fit: where along each contour normal the part's colours end.

Edges alone fail where a part hardly differs from its background in brightness (a yellow part on a white
desk, a grey valve in turbid water) and are fooled by texture next to the outline. As in region-based trackers
(PWP3D, SRT3D), each part keeps colour histograms of its own pixels (foreground) and of the pixels just beyond
its outline (background), learned on tracked frames. Along a contour sample's normal the colours give each
pixel a foreground probability ``pf``; the contour's position ``d`` along the normal is scored by how well
"foreground before ``d``, background after" explains the line::

    E(d) = sum_{t < d} log pf(t) + sum_{t > d} log(1 - pf(t))

and the mean of ``exp(E)`` over ``d`` is the sample's region offset: a 1-D correspondence along the normal
like the edge search's, fitted by the same IRLS (:func:`cadalign.align.edge_refine.fit_correction`).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class RegionConfig:
    """Colour histograms per part and the region correspondences along contour normals."""

    enabled: bool = True
    """Add region correspondences to the contour fit once a tracked frame has taught the colours."""
    bins: int = 16
    """Histogram bins per colour channel (16 -> 4096 RGB bins, as SRT3D)."""
    line_px: int = 8
    """Pixels inside and beyond each contour sample that teach a part's colours (full resolution)."""
    learn_rate: float = 0.2
    """Share of a tracked frame's histograms blended into the kept ones (the first frame sets them)."""
    min_gain: float = 2.0
    """A sample's region offset counts when splitting the line at its best position explains the colours
    better, by this log-likelihood, than calling the whole line foreground or background."""
    p_clip: float = 0.05
    """Foreground probabilities are clipped to [p_clip, 1 - p_clip]: one odd pixel cannot decide a line."""


class RegionModel:
    """Per-part (ray-cast instance) colour histograms and the region offsets they give."""

    def __init__(self, cfg: RegionConfig) -> None:
        self.cfg = cfg
        self.fg: dict[int, np.ndarray] = {}
        self.bg: dict[int, np.ndarray] = {}
        # pixels each part's histograms were taught per lesson (blended as they are): weighs the parts in the pool
        self.fg_pixels: dict[int, float] = {}
        self.bg_pixels: dict[int, float] = {}
        self._luts: tuple[np.ndarray, np.ndarray] | None = None  # log pf, log (1 - pf) per (part, bin)
        self._byte_bins = np.arange(256, dtype=np.int32) * cfg.bins // 256  # each channel byte's bin

    @property
    def ready(self) -> bool:
        """Whether a tracked frame has taught any part's colours."""
        return self.cfg.enabled and bool(self.fg)

    def _bin(self, rgb: np.ndarray) -> np.ndarray:
        """Histogram bin of each colour (..., 3) (0-255)."""
        b = self.cfg.bins
        if rgb.dtype == np.uint8:  # a frame's own pixels: one table lookup per channel
            lut = self._byte_bins
            return (lut[rgb[..., 0]] * b + lut[rgb[..., 1]]) * b + lut[rgb[..., 2]]
        q = np.clip(rgb, 0, 255).astype(np.int32) * b // 256
        return (q[..., 0] * b + q[..., 1]) * b + q[..., 2]

    def learn(self, rgb: np.ndarray, uv: np.ndarray, normal: np.ndarray, sample_instance: np.ndarray,
              instance: np.ndarray) -> None:
        """Blend in the colours along the contour samples of a tracked frame: ``rgb`` (H, W, 3), ``uv`` (N, 2)
        array-convention contour positions and ``normal`` (N, 2) at full resolution, ``sample_instance`` (N,)
        each sample's part, ``instance`` (H, W) the ray-cast instance map at the pose. A pixel teaches a part's
        foreground only where the map shows the part, its background only where it does not."""
        if len(uv) == 0:
            return
        H, W = instance.shape
        t = np.arange(self.cfg.line_px) + 0.5
        nb, k_of = self.cfg.bins**3, sample_instance.astype(np.int64)  # parts: small non-negative ids
        parts = np.flatnonzero(np.bincount(k_of))
        for store, pixels, sign in ((self.fg, self.fg_pixels, -1.0), (self.bg, self.bg_pixels, 1.0)):  # inside, beyond
            st = sign * t
            x = np.floor(uv[:, 0, None] + st[None, :] * normal[:, 0, None] + 0.5).astype(int)
            y = np.floor(uv[:, 1, None] + st[None, :] * normal[:, 1, None] + 0.5).astype(int)
            inside = (x >= 0) & (x < W) & (y >= 0) & (y < H)
            x, y = np.clip(x, 0, W - 1), np.clip(y, 0, H - 1)
            own = instance.ravel()[y * W + x] == sample_instance[:, None]
            keep = inside & (own if store is self.fg else ~own)
            # (part, colour bin) of each pixel kept
            flat = np.broadcast_to(k_of[:, None], keep.shape)[keep] * nb + self._bin(rgb[y[keep], x[keep]])
            counts = np.bincount(flat, minlength=(k_of.max() + 1) * nb).reshape(-1, nb)
            for k in parts:
                c = counts[k]
                n = float(c.sum())
                if n < 20:
                    continue
                h = c / n
                k = int(k)
                a = self.cfg.learn_rate if k in store else 1.0
                store[k] = (1 - a) * store.get(k, h) + a * h
                pixels[k] = (1 - a) * pixels.get(k, 0.0) + a * n
        self._luts = None

    def pooled_log_odds(self, rgb: np.ndarray) -> np.ndarray | None:
        """(H, W) each pixel's log odds ``log pf / (1 - pf)`` of showing the structure, ``pf`` clipped as the lines'
        are, from the parts' histograms pooled by the pixels each taught: the colours of every pixel learned inside
        a part against every pixel learned beyond one, so a part weighs as much as it shows (a whole structure's
        silhouette is mostly its frame; docs/tuning/tracker.md#colours-pooled-by-pixels-s63). None before any part
        is learned."""
        known = [k for k in self.fg if k in self.bg]
        if not known:
            return None
        f = sum(self.fg_pixels[k] * self.fg[k] for k in known) / sum(self.fg_pixels[k] for k in known)
        b = sum(self.bg_pixels[k] * self.bg[k] for k in known) / sum(self.bg_pixels[k] for k in known)
        pf = self._share(f, b)
        return (np.log(pf) - np.log1p(-pf))[self._bin(rgb)]

    def foreground(self, colours: np.ndarray, sample_instance: np.ndarray) -> np.ndarray:
        """(N, M) foreground probability of colours (N, M, 3) along the lines of samples of parts
        ``sample_instance`` (N,); 0.5 for a part (or a colour) neither histogram knows."""
        return np.exp(self._log_probabilities(colours, sample_instance)[0])

    def _log_probabilities(self, colours: np.ndarray, sample_instance: np.ndarray,
                           ) -> tuple[np.ndarray, np.ndarray]:
        """(log pf, log (1 - pf)) (N, M) of colours (N, M, 3) along the lines of samples of parts
        ``sample_instance`` (N,), looked up per (part, colour bin) in tables made once per learned frame."""
        if self._luts is None:
            self._luts = self._tables()
        logf, logb = self._luts
        k = sample_instance.astype(np.int64)
        k = np.where((k >= 0) & (k < len(logf)), k, len(logf) - 1)  # beyond the tables: no histogram (0.5)
        bins = self._bin(colours)
        return logf[k[:, None], bins], logb[k[:, None], bins]

    def _tables(self) -> tuple[np.ndarray, np.ndarray]:
        """log pf and log (1 - pf) per (part, colour bin), pf = fg / (fg + bg) clipped to [p_clip, 1 - p_clip];
        pf = 0.5 in the rows of parts without both histograms and in the last row (parts beyond the tables)."""
        known = [k for k in self.fg if k in self.bg]
        pf = np.full((max(known, default=0) + 2, self.cfg.bins**3), 0.5)
        for k in known:
            pf[k] = self._share(self.fg[k], self.bg[k])
        return np.log(pf), np.log(1 - pf)

    def _share(self, f: np.ndarray, b: np.ndarray) -> np.ndarray:
        """pf = f / (f + b) per colour bin of foreground and background histograms, 0.5 where neither has mass,
        clipped to [p_clip, 1 - p_clip]."""
        s = f + b
        return np.clip(np.where(s > 1e-9, f / np.maximum(s, 1e-12), 0.5), self.cfg.p_clip, 1 - self.cfg.p_clip)

    def offsets(self, rgb: np.ndarray, uv: np.ndarray, normal: np.ndarray, sample_instance: np.ndarray,
                search_px: float) -> np.ndarray:
        """Region offset (pixels of ``rgb``'s scale, along ``normal``; NaN: the colours do not place the
        contour) of each contour sample at ``uv`` (array convention, the predicted contour)."""
        S = max(int(round(search_px)), 1)
        t = np.arange(-S, S) + 0.5  # pixel centres along the line, the predicted contour at 0
        mx = (uv[:, 0, None] + t[None, :] * normal[:, 0, None]).astype(np.float32)
        my = (uv[:, 1, None] + t[None, :] * normal[:, 1, None]).astype(np.float32)
        cols = cv2.remap(np.ascontiguousarray(rgb, dtype=np.float32), mx, my, cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE)
        lf, lb = self._log_probabilities(cols, sample_instance)
        # E(d) for d at the 2S + 1 boundaries -S .. S: foreground before d, background after
        cf = np.concatenate([np.zeros((len(lf), 1)), np.cumsum(lf, axis=1)], axis=1)
        cb = np.concatenate([np.zeros((len(lb), 1)), np.cumsum(lb, axis=1)], axis=1)
        E = cf + (cb[:, -1:] - cb)
        d = np.arange(-S, S + 1, dtype=np.float64)
        k = np.argmax(E, axis=1)
        rows = np.arange(len(k))
        gain = E[rows, k] - np.maximum(E[:, 0], E[:, -1])
        ok = (gain >= self.cfg.min_gain) & (k > 0) & (k < 2 * S)
        w = np.exp(E - E[rows, k][:, None])
        mean = (w * d).sum(axis=1) / w.sum(axis=1)
        return np.where(ok, mean, np.nan)


def sample_instances(uv: np.ndarray, normal: np.ndarray, instance: np.ndarray) -> np.ndarray:
    """(N,) the ray-cast instance of each contour sample's near pixel (half a pixel back along the normal)."""
    H, W = instance.shape
    near = np.floor(uv - 0.5 * normal + 0.5).astype(int)
    return instance[np.clip(near[:, 1], 0, H - 1), np.clip(near[:, 0], 0, W - 1)]
