"""Accuracy-versus-time trade-offs: the Pareto front, the recommended setting and the Pareto plot.

A setting is a point ``(cost, accuracy)``; cost is always "lower is better" (seconds, ms per frame),
accuracy is either "higher is better" (IoU, delta1, fidelity) or "lower is better" (an error).

* :func:`pareto_front`: the settings no other setting beats on both axes (ties on both axes are all kept).
* :func:`recommend`: the setting within ``tol`` (5 %) of the best accuracy at the least cost. "Within 5 %"
  is relative to the best value: ``acc >= (1 - tol) * best`` when higher is better, ``err <= (1 + tol) * best``
  when lower is better (a best error of exactly 0 only admits other zeros). Among equally cheap candidates
  the more accurate one wins, then the first listed. Settings with a non-finite accuracy or cost never win.

Example:
    >>> recommend([1.0, 2.0, 4.0], [0.80, 0.95, 0.97], higher_is_better=True)
    1
    >>> pareto_front([1.0, 2.0, 3.0], [0.5, 0.4, 0.9], higher_is_better=True)
    [0, 2]
"""

from __future__ import annotations

import math
import textwrap
from collections.abc import Sequence
from pathlib import Path

import numpy as np

TOLERANCE = 0.05
"""Default relative accuracy tolerance of :func:`recommend` (the issue's "within 5 % of the best")."""


def _finite(costs: Sequence[float], accs: Sequence[float]) -> list[int]:
    if len(costs) != len(accs):
        raise ValueError(f"costs and accuracies differ in length: {len(costs)} vs {len(accs)}")
    return [i for i, (c, a) in enumerate(zip(costs, accs, strict=True)) if math.isfinite(c) and math.isfinite(a)]


def _better_or_equal(a: float, b: float, higher_is_better: bool) -> bool:
    return a >= b if higher_is_better else a <= b


def pareto_front(costs: Sequence[float], accs: Sequence[float], *, higher_is_better: bool) -> list[int]:
    """Indices (ascending) of the non-dominated settings.

    Setting ``j`` dominates ``i`` when it costs no more, is no less accurate, and is strictly better on at
    least one of the two. Non-finite entries are never on the front.
    """
    ok = _finite(costs, accs)
    front = []
    for i in ok:
        dominated = False
        for j in ok:
            if j == i:
                continue
            no_worse = costs[j] <= costs[i] and _better_or_equal(accs[j], accs[i], higher_is_better)
            strictly = costs[j] < costs[i] or accs[j] != accs[i]
            if no_worse and strictly:
                dominated = True
                break
        if not dominated:
            front.append(i)
    return front


def accuracy_threshold(best: float, *, higher_is_better: bool, tol: float = TOLERANCE) -> float:
    """The accuracy a setting needs to count as "within ``tol`` of ``best``" (see the module doc)."""
    if tol < 0:
        raise ValueError(f"tol must be >= 0, got {tol}")
    if higher_is_better:
        return best - tol * abs(best)
    return best + tol * abs(best)


def recommend(costs: Sequence[float], accs: Sequence[float], *, higher_is_better: bool,
              tol: float = TOLERANCE) -> int | None:
    """Index of the cheapest setting within ``tol`` of the best accuracy; None when no setting is finite."""
    ok = _finite(costs, accs)
    if not ok:
        return None
    best = max(accs[i] for i in ok) if higher_is_better else min(accs[i] for i in ok)
    thr = accuracy_threshold(best, higher_is_better=higher_is_better, tol=tol)
    good = [i for i in ok if _better_or_equal(accs[i], thr, higher_is_better)]
    sign = -1.0 if higher_is_better else 1.0
    return min(good, key=lambda i: (costs[i], sign * accs[i], i))


def plot_pareto(path: Path, names: Sequence[str], costs: Sequence[float], accs: Sequence[float], *,
                higher_is_better: bool, cost_label: str, acc_label: str, title: str,
                notes: Sequence[str] | None = None, tol: float = TOLERANCE) -> Path:
    """Scatter of every setting (cost on x, accuracy on y), the Pareto front as a step line, the
    recommended setting as a star and each point annotated with its name (points on the front also with
    their ``notes``: knob values).

    An axis is logarithmic when its (positive) values span more than a factor of 20. Writes a PNG and
    returns its path.
    """

    # the object API draws without pyplot's backend: matplotlib.use("Agg") here turned a notebook's inline plots off
    from matplotlib.figure import Figure  # lazy: heavy dependency (matplotlib)

    c, a = np.asarray(costs, dtype=float), np.asarray(accs, dtype=float)
    ok = np.isfinite(c) & np.isfinite(a)
    front = pareto_front(list(c), list(a), higher_is_better=higher_is_better)
    rec = recommend(list(c), list(a), higher_is_better=higher_is_better, tol=tol)
    fig = Figure(figsize=(8.0, 5.0))
    ax = fig.subplots()
    ax.scatter(c[ok], a[ok], s=28, color="tab:blue", zorder=3, label="setting")
    if front:
        order = sorted(front, key=lambda i: c[i])
        ax.step(c[order], a[order], where="post", color="tab:orange", lw=1.2, zorder=2, label="Pareto front")
    if rec is not None:
        ax.scatter([c[rec]], [a[rec]], marker="*", s=260, color="tab:red", zorder=4,
                   label=f"recommended (within {100 * tol:.0f}% of best, least time)")
        best = np.nanmax(a[ok]) if higher_is_better else np.nanmin(a[ok])
        ax.axhline(accuracy_threshold(float(best), higher_is_better=higher_is_better, tol=tol), color="tab:red",
                   lw=0.7, ls=":", zorder=1)
    for n, i in enumerate(sorted(np.flatnonzero(ok), key=lambda j: c[j])):
        text = names[i] + (f"\n{notes[i]}" if notes and notes[i] and i in front else "")
        ax.annotate(text, (c[i], a[i]), textcoords="offset points", xytext=(6, 6 if n % 2 == 0 else -16),
                    fontsize=7, color="#333")
    for vals, set_scale in ((c[ok], ax.set_xscale), (a[ok], ax.set_yscale)):
        if len(vals) and vals.min() > 0 and vals.max() / vals.min() > 20:
            set_scale("log")
    ax.set_xlabel(textwrap.fill(f"{cost_label} (lower is better)", 70), fontsize=9)
    ax.set_ylabel(textwrap.fill(f"{acc_label} ({'higher' if higher_is_better else 'lower'} is better)", 45),
                  fontsize=9)
    ax.set_title(textwrap.fill(title, 80), fontsize=9)
    ax.grid(alpha=0.3)
    ax.margins(x=0.15, y=0.12)
    ax.legend(fontsize=7, loc="best")
    if not ok.any():
        ax.text(0.5, 0.5, "no finished setting", transform=ax.transAxes, ha="center")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp.png")
    fig.savefig(tmp, dpi=110)
    tmp.replace(path)
    return path
