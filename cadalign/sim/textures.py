"""Procedural material textures: painted steel, rust, marine growth, seabed sediment.

Textures are tileable RGB images made from multi-octave value noise plus
blotches and speckles at several scales, so SIFT finds many stable features
on them at ROV stand-off distances. Deterministic for a seed.
"""

from __future__ import annotations

import numpy as np

BASE_COLOURS: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    # (main colour, secondary colour), linear-ish RGB in [0, 1]
    "painted_steel": ((0.85, 0.62, 0.12), (0.35, 0.30, 0.25)),
    "yellow_paint": ((0.92, 0.80, 0.10), (0.30, 0.28, 0.22)),
    "rust": ((0.55, 0.25, 0.10), (0.25, 0.12, 0.06)),
    "marine_growth": ((0.45, 0.55, 0.35), (0.85, 0.85, 0.75)),
    "sediment": ((0.62, 0.56, 0.42), (0.35, 0.32, 0.25)),
    "galvanised": ((0.62, 0.64, 0.66), (0.35, 0.36, 0.38)),
}


def value_noise(size: int, cells: int, rng: np.random.Generator) -> np.ndarray:
    """Tileable smooth noise in [0, 1]: a random ``cells``×``cells`` lattice, bicubic-ish upsampled."""
    lattice = rng.random((cells, cells))
    coords = np.arange(size) * cells / size
    i0 = np.floor(coords).astype(int)
    f = coords - i0
    f = f * f * (3 - 2 * f)  # smoothstep
    i1 = (i0 + 1) % cells
    a = lattice[np.ix_(i0, i0)]
    b = lattice[np.ix_(i0, i1)]
    c = lattice[np.ix_(i1, i0)]
    d = lattice[np.ix_(i1, i1)]
    fx, fy = f[None, :], f[:, None]
    return (a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + d * fx) * fy


def fractal_noise(size: int, rng: np.random.Generator, octaves: int = 6, base_cells: int = 4) -> np.ndarray:
    """Sum of value-noise octaves (each twice the frequency, 0.55 the amplitude), normalised to [0, 1]."""
    total = np.zeros((size, size))
    amp, norm = 1.0, 0.0
    for k in range(octaves):
        cells = min(base_cells * 2**k, size)
        total += amp * value_noise(size, cells, rng)
        norm += amp
        amp *= 0.55
    return total / norm


def _blotches(size: int, rng: np.random.Generator, count: int, r_px: tuple[float, float]) -> np.ndarray:
    """A mask in [0, 1] of soft round blotches (tileable by wrapping)."""
    yy, xx = np.mgrid[0:size, 0:size]
    mask = np.zeros((size, size))
    for _ in range(count):
        cx, cy = rng.random(2) * size
        r = rng.uniform(*r_px)
        dx = np.minimum(np.abs(xx - cx), size - np.abs(xx - cx))
        dy = np.minimum(np.abs(yy - cy), size - np.abs(yy - cy))
        mask = np.maximum(mask, np.clip(1.5 - np.hypot(dx, dy) / r, 0, 1))
    return mask


def make_texture(name: str, seed: int, size: int = 512) -> np.ndarray:
    """A tileable (size, size, 3) uint8 RGB texture for material ``name``."""
    if name not in BASE_COLOURS:
        raise ValueError(f"unknown texture {name!r}; allowed: {', '.join(BASE_COLOURS)}")
    rng = np.random.default_rng([seed, sum(map(ord, name))])
    main, second = (np.array(c) for c in BASE_COLOURS[name])
    coarse = fractal_noise(size, rng, octaves=7, base_cells=4)
    mix = np.clip((coarse - 0.35) * 2.2, 0, 1)
    blot = _blotches(size, rng, count=60, r_px=(3, size / 16))
    speck = (rng.random((size, size)) > 0.985).astype(float)
    weight = np.clip(0.55 * mix + 0.6 * blot, 0, 1)[..., None]
    rgb = main * (1 - weight) + second * weight
    shade = 0.75 + 0.5 * fractal_noise(size, rng, octaves=5, base_cells=16)[..., None]
    rgb = rgb * shade + 0.25 * speck[..., None]
    return (np.clip(rgb, 0, 1) * 255).astype(np.uint8)
