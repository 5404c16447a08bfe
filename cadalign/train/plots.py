"""Loss and validation-metric curves of a training run (matplotlib, Agg backend)."""

from __future__ import annotations

from pathlib import Path

from cadalign.io import atomic_path


def plot_metrics(rows: list[dict[str, float]], path: Path) -> Path:
    """Plot ``loss``/``loss_avg`` and every ``val_*`` column of the metrics rows against the step into a PNG."""
    # the object API draws without pyplot, so no backend is set: matplotlib.use("Agg") here switched a notebook's
    # inline backend off for every later plot
    from matplotlib.figure import Figure  # lazy: heavy dependency (matplotlib)

    val_keys = sorted({k for r in rows for k in r if k.startswith("val_")})
    fig = Figure(figsize=(10 if val_keys else 6, 4))
    axes = fig.subplots(1, 2 if val_keys else 1, squeeze=False)[0]
    steps = [r["step"] for r in rows]
    axes[0].plot(steps, [r["loss"] for r in rows], label="loss", alpha=0.5)
    axes[0].plot(steps, [r.get("loss_avg", r["loss"]) for r in rows], label="loss (window mean)")
    axes[0].set_xlabel("step")
    axes[0].set_yscale("log" if all(r["loss"] > 0 for r in rows) else "linear")
    axes[0].legend()
    for key in val_keys:
        pts = [(r["step"], r[key]) for r in rows if key in r]
        axes[1].plot([p[0] for p in pts], [p[1] for p in pts], marker="o", label=key)
    if val_keys:
        axes[1].set_xlabel("step")
        axes[1].legend(fontsize=7)
    fig.tight_layout()
    with atomic_path(Path(path)) as tmp:
        fig.savefig(tmp, format="png", dpi=90)
    return Path(path)
