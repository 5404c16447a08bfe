"""Draw docs/architecture.png: cadalign's layers (cadalign/_layers.py) with their rooms, and how many imports go from
each layer to each other, counted on the actual import graph (tests/test_architecture.py's, imports inside functions
included). Run from the repository root:  .venv/bin/python tests/tools/layers_figure.py [docs/architecture.png]
"""

from __future__ import annotations

import importlib.util
import sys
from collections import Counter
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

import cadalign
from cadalign._layers import LAYERS, layer_of

ROOT = Path(__file__).resolve().parents[2]


def _architecture_test():
    spec = importlib.util.spec_from_file_location("test_architecture", ROOT / "tests" / "test_architecture.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def room_of(module: str) -> str:
    rooms = [r for _, rs in LAYERS for r in rs if module == r or module.startswith(r + ".")]
    return max(rooms, key=len)


def main(out: Path) -> None:
    arch = _architecture_test()
    package = Path(cadalign.__file__).resolve().parent
    graph = arch.import_graph(package)
    files = arch.module_files(package)
    n = len(LAYERS)
    counts = np.zeros((n, n), int)
    for a, targets in graph.items():
        for b in targets:
            counts[layer_of(a), layer_of(b)] += 1
    lines: Counter[str] = Counter()
    modules: Counter[str] = Counter()
    for m, p in files.items():
        lines[room_of(m)] += len(p.read_text(encoding="utf-8").splitlines())
        modules[room_of(m)] += 1

    fig = Figure(figsize=(13, 7.5))
    ax = fig.add_axes([0.01, 0.02, 0.56, 0.9])
    ax.set_axis_off()
    ax.set_xlim(0, 1)
    ax.set_ylim(0, n)
    colours = ["#dde8f3", "#e3efe0", "#f3ecd9", "#f0e0e0", "#e6e0f0", "#d9efef", "#eeeeee", "#f6e3d4"]
    for i, (name, rooms) in enumerate(LAYERS):
        ax.add_patch(__import__("matplotlib.patches", fromlist=["Rectangle"]).Rectangle(
            (0, i + 0.05), 1, 0.9, color=colours[i % len(colours)], ec="#888"))
        ax.text(0.01, i + 0.78, f"{i}  {name}", fontsize=10, weight="bold", va="center")
        shown = [r.removeprefix("cadalign.") or "cadalign/__init__" for r in rooms]
        text = "   ".join(f"{s} ({modules[r]}, {lines[r]} l)" for s, r in zip(shown, rooms, strict=True)
                          if modules[r])
        wrapped, line = [], ""
        for word in text.split("   "):
            if len(line) + len(word) > 80:
                wrapped.append(line)
                line = ""
            line += ("   " if line else "") + word
        wrapped.append(line)
        ax.text(0.01, i + 0.42, "\n".join(wrapped), fontsize=7.5, va="center", family="monospace")
    ax.set_title("cadalign's layers, lowest first (room: modules, lines); a module imports only from its layer and "
                 "below", fontsize=9, loc="left")

    hx = fig.add_axes([0.62, 0.12, 0.36, 0.62])
    shown = np.where(counts > 0, counts, np.nan)
    hx.imshow(np.log1p(shown), cmap="Blues", origin="lower")
    for i in range(n):
        for j in range(n):
            hx.text(j, i, str(counts[i, j]), ha="center", va="center", fontsize=8,
                    color="#b00" if j > i and counts[i, j] else "white" if counts[i, j] > 100 else "#222")
    names = [name for name, _ in LAYERS]
    hx.set_xticks(range(n), names, rotation=45, ha="right", fontsize=8)
    hx.set_yticks(range(n), names, fontsize=8)
    hx.set_xlabel("imported layer")
    hx.set_ylabel("importing layer")
    cyc = arch.cycles(graph)
    up = arch.upward_imports(graph)
    hx.set_title(f"module -> module imports between layers\n(above the diagonal: upward, {len(up)}; "
                 f"cycles: {len(cyc)}; {sum(len(t) for t in graph.values())} imports, {len(graph)} modules)",
                 fontsize=9)
    fig.savefig(out, dpi=110)
    print(f"wrote {out}: {len(graph)} modules, {int(counts.sum())} imports, {len(up)} upward, {len(cyc)} cycles")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT / "docs" / "architecture.png")
