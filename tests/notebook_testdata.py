"""Run a notebook in a real Jupyter kernel (nbclient + ipykernel, the dev extra), as the tests do."""

from __future__ import annotations

import os
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
ALLOWED_IMPORTS = {"os", "pathlib", "dataclasses", "matplotlib", "cadalign"}
"""Notebooks only call cadalign's stage functions (and look at the results with matplotlib)."""


def execute_notebook(name: str, env: dict[str, str], timeout_s: int = 300) -> object:
    """Run ``notebooks/NAME`` in a fresh python3 kernel started in notebooks/ with ``env`` added (and this
    checkout's cadalign first on the path); returns the executed notebook. A failing cell raises
    ``nbclient.exceptions.CellExecutionError`` with its traceback."""
    import nbformat
    from nbclient import NotebookClient

    path = REPO / "notebooks" / name
    nb = nbformat.read(path, as_version=4)
    for cell in nb.cells:
        if cell.cell_type != "code":
            continue
        for line in cell.source.splitlines():
            if line.startswith(("import ", "from ")):
                assert line.split()[1].split(".")[0] in ALLOWED_IMPORTS, f"{name}: {line}"
    old = {k: os.environ.get(k) for k in (*env, "PYTHONPATH", "MPLBACKEND", "OMP_NUM_THREADS")}
    os.environ.update(env)
    os.environ["PYTHONPATH"] = os.pathsep.join([str(REPO), *filter(None, [old["PYTHONPATH"]])])
    os.environ["MPLBACKEND"] = "module://matplotlib_inline.backend_inline"
    os.environ["OMP_NUM_THREADS"] = "1"  # the suite runs two workers on two cores
    try:
        NotebookClient(nb, timeout=timeout_s, kernel_name="python3",
                       resources={"metadata": {"path": str(path.parent)}}).execute()
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    return nb
