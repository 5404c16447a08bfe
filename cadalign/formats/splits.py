"""Train/val/test splits of a video by contiguous time blocks.

Neighbouring video frames are near duplicates, so a random frame split leaks the test set into
training. Frames are cut into contiguous blocks, whole blocks are dealt to the splits, and ``gap``
frames at each boundary between blocks of different splits are dropped.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from cadalign.errors import ConfigError

SPLITS = ("train", "val", "test")


def time_block_splits(ids: Sequence[int], fractions: Sequence[float] = (0.7, 0.15, 0.15), *,
                      block: int = 10, gap: int = 1, seed: int = 0) -> dict[str, list[int]]:
    """Split frame ids (in time order) into train/val/test by blocks of ``block`` consecutive frames.

    Blocks are dealt so each split's share of blocks is as close as possible to ``fractions``
    (a seeded shuffle decides which blocks); ``gap`` frames are dropped on both sides of every
    boundary between different splits. Every split with a non-zero fraction gets at least one block
    when there are enough blocks.

    Raises:
        ConfigError: fractions not 3 non-negative numbers summing to 1, block < 1, or gap < 0.
    """
    fr = np.asarray(fractions, dtype=float)
    if fr.shape != (3,) or (fr < 0).any() or not np.isclose(fr.sum(), 1.0):
        raise ConfigError(f"split fractions must be 3 non-negative numbers summing to 1, got {list(fractions)}")
    if block < 1 or gap < 0:
        raise ConfigError(f"block must be >= 1 and gap >= 0, got block={block}, gap={gap}")
    ids = list(ids)
    blocks = [ids[i : i + block] for i in range(0, len(ids), block)]
    n = len(blocks)
    want = fr * n
    count = np.floor(want).astype(int)
    for i in np.argsort(-(want - count))[: n - count.sum()]:
        count[i] += 1
    for i in range(3):  # a split asked for should not end up empty when blocks allow
        if fr[i] > 0 and count[i] == 0 and count.max() > 1:
            count[int(np.argmax(count))] -= 1
            count[i] += 1
    labels = np.repeat(np.arange(3), count)
    np.random.default_rng(seed).shuffle(labels)
    out: dict[str, list[int]] = {s: [] for s in SPLITS}
    for b, (frames, lab) in enumerate(zip(blocks, labels, strict=True)):
        lo = gap if b > 0 and labels[b - 1] != lab else 0
        hi = len(frames) - (gap if b + 1 < n and labels[b + 1] != lab else 0)
        out[SPLITS[lab]].extend(frames[lo:max(hi, lo)])
    return out
