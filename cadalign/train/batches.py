"""Batches of the training loop: the seeded infinite sample stream, DDP sharding, non-finite input checks.

The stream is the concatenation of per-epoch permutations of the dataset indices, each depending only on
``(seed, epoch)``; global step ``s`` takes stream positions ``[s*B, (s+1)*B)`` and DDP rank ``r`` of ``W``
takes the ``r``-th ``B/W`` of them. The sampler position is therefore just the step count.
"""

from __future__ import annotations

from collections.abc import Iterator

import torch

from cadalign.errors import TrainingError


def stream_indices(n: int, seed: int, start: int, count: int) -> list[int]:
    """Dataset indices at stream positions ``[start, start+count)`` of the seeded infinite sample stream."""
    out: list[int] = []
    perms: dict[int, torch.Tensor] = {}
    for pos in range(start, start + count):
        epoch = pos // n
        if epoch not in perms:
            g = torch.Generator().manual_seed(seed * 1_000_003 + epoch)
            perms[epoch] = torch.randperm(n, generator=g)
        out.append(int(perms[epoch][pos % n]))
    return out


class StepBatchSampler:
    """Index lists of this rank's share of global batches ``start_step .. steps-1``."""

    def __init__(self, n: int, steps: int, batch_size: int, seed: int, start_step: int, rank: int, world: int) -> None:
        self.n, self.steps, self.batch, self.seed = n, steps, batch_size, seed
        self.start, self.rank, self.world = start_step, rank, world
        self.per_rank = batch_size // world

    def __iter__(self) -> Iterator[list[int]]:
        for step in range(self.start, self.steps):
            idx = stream_indices(self.n, self.seed, step * self.batch, self.batch)
            yield idx[self.rank * self.per_rank : (self.rank + 1) * self.per_rank]

    def __len__(self) -> int:
        return max(self.steps - self.start, 0)


def sample_names(batch: dict, rows: list[int] | None = None) -> str:
    for key in ("im_id", "name"):
        if key in batch:
            v = batch[key]
            vals = v.tolist() if isinstance(v, torch.Tensor) else list(v)
            if rows is not None:
                vals = [vals[i] for i in rows if i < len(vals)]
            return f"{key}={vals}"
    return "(the batch has no 'im_id' or 'name')"


def check_finite_batch(batch: dict, step: int) -> None:
    """Raise :class:`TrainingError` naming the sample(s) and key of any non-finite float input."""
    for key, v in batch.items():
        items = v if isinstance(v, (list, tuple)) else [v]
        bad: list[int] = []
        for j, t in enumerate(items):
            if isinstance(t, torch.Tensor) and t.is_floating_point() and not bool(torch.isfinite(t).all()):
                if t is v and t.ndim > 0:  # a stacked tensor: find the rows
                    bad = [i for i in range(t.shape[0]) if not bool(torch.isfinite(t[i]).all())]
                else:
                    bad.append(j)
        if bad:
            raise TrainingError(
                f"non-finite values (NaN/inf) in input '{key}' of sample {sample_names(batch, bad)} at step {step}; "
                "fix or remove that sample from the dataset"
            )
