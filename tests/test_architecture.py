"""The import graph of cadalign: no cycles and no upward imports (the layer order is :mod:`cadalign._layers`).

Every module under ``cadalign/`` is parsed with :mod:`ast`; every ``import cadalign.x`` / ``from cadalign.x import
y`` / relative import counts, wherever it stands (inside functions and ``if TYPE_CHECKING:`` blocks too): an import
hidden in a function still ties the two modules together.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

import pytest

import cadalign
from cadalign._layers import HEAVY_DEPENDENCIES, KNOWN_UPWARD_IMPORTS, LAYERS, layer_of

PACKAGE_DIR = Path(cadalign.__file__).resolve().parent


def module_files(package_dir: Path) -> dict[str, Path]:
    """Dotted module name -> file, for every ``.py`` under ``package_dir`` (a package is named by its folder)."""
    out = {}
    for path in sorted(package_dir.rglob("*.py")):
        parts = list(path.relative_to(package_dir.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _imported_names(node: ast.AST, module: str, is_package: bool) -> Iterator[tuple[str, str | None]]:
    """(module, name imported from it or None) of one import statement; relative imports made absolute."""
    if isinstance(node, ast.Import):
        for alias in node.names:
            yield alias.name, None
    elif isinstance(node, ast.ImportFrom):
        if node.level:
            base = module.split(".") if is_package else module.split(".")[:-1]
            base = base[: len(base) - (node.level - 1)]
            source = ".".join([*base, *([node.module] if node.module else [])])
        else:
            source = node.module or ""
        for alias in node.names:
            yield source, alias.name


def import_graph(package_dir: Path) -> dict[str, dict[str, int]]:
    """module -> {imported module of the same package: line of the first such import}."""
    modules = module_files(package_dir)
    root = package_dir.name

    def resolve(name: str) -> str | None:
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, dict[str, int]] = {m: {} for m in modules}
    for module, path in modules.items():
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node in ast.walk(tree):
            for source, name in _imported_names(node, module, path.name == "__init__.py"):
                if source != root and not source.startswith(root + "."):
                    continue
                full = f"{source}.{name}" if name else source
                target = resolve(full if full in modules else source)
                if target is not None and target != module:
                    graph[module].setdefault(target, node.lineno)
    return graph


def cycles(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan, iterative), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for start in graph:
        if start in index:
            continue
        work = [(start, iter(graph[start]))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(graph.get(w, {}))))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    found.append(sorted(comp))
    return found


def upward_imports(graph: dict[str, dict[str, int]]) -> dict[tuple[str, str], int]:
    """(importer, imported) -> line, for every import from a higher layer than the importer's."""
    out = {}
    for a, targets in graph.items():
        for b, line in targets.items():
            la, lb = layer_of(a), layer_of(b)
            if la is not None and lb is not None and lb > la:
                out[(a, b)] = line
    return out


@pytest.fixture(scope="module")
def graph() -> dict[str, dict[str, int]]:
    return import_graph(PACKAGE_DIR)


def test_no_import_cycles(graph: dict[str, dict[str, int]]) -> None:
    found = cycles(graph)
    detail = [" <-> ".join(c) + ": " + "; ".join(f"{a} -> {b} (line {graph[a][b]})" for a in c for b in graph[a]
                                                 if b in c) for c in found]
    assert not found, "import cycles (move the shared piece down a module):\n" + "\n".join(detail)


def test_every_module_has_a_layer(graph: dict[str, dict[str, int]]) -> None:
    assert [m for m in graph if layer_of(m) is None] == [], "add the new room to cadalign/_layers.py LAYERS"


def test_no_new_upward_imports(graph: dict[str, dict[str, int]]) -> None:
    names = [name for name, _ in LAYERS]
    new = {k: v for k, v in upward_imports(graph).items() if k not in KNOWN_UPWARD_IMPORTS}
    assert not new, "imports from a higher layer:\n" + "\n".join(
        f"{a} ({names[layer_of(a) or 0]}) -> {b} ({names[layer_of(b) or 0]}), line {line}"
        for (a, b), line in sorted(new.items()))


def test_known_upward_imports_still_exist(graph: dict[str, dict[str, int]]) -> None:
    """A fixed violation leaves the allow-list, so the list only shrinks."""
    assert sorted(KNOWN_UPWARD_IMPORTS - set(upward_imports(graph))) == []


def imports_inside_functions(path: Path) -> Iterator[ast.Import | ast.ImportFrom]:
    """Every import statement inside a function (methods and nested functions included)."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    for func in ast.walk(tree):
        if isinstance(func, (ast.FunctionDef, ast.AsyncFunctionDef)):
            for node in ast.walk(func):
                if isinstance(node, (ast.Import, ast.ImportFrom)):
                    yield node


def lazy_import_problems(package_dir: Path) -> list[str]:
    """Imports inside functions without a ``# lazy:`` reason on the line or the line above, or of a third-party
    package that is not a heavy one (those belong at module top)."""
    problems = []
    root = package_dir.name
    seen: set[tuple[Path, int]] = set()
    for path in sorted(package_dir.rglob("*.py")):
        lines = path.read_text(encoding="utf-8").splitlines()
        for node in imports_inside_functions(path):
            if (path, node.lineno) in seen:  # a nested function's import is walked once per enclosing function
                continue
            seen.add((path, node.lineno))
            where = f"{path.relative_to(package_dir.parent)}:{node.lineno}"
            here, above = lines[node.lineno - 1], lines[node.lineno - 2] if node.lineno > 1 else ""
            if "# lazy:" not in here and not above.strip().startswith("# lazy:"):
                problems.append(f"{where}: an import inside a function needs a '# lazy: <reason>' comment (an "
                                "optional or heavy dependency it keeps off a light path), else move it to the top")
            if isinstance(node, ast.ImportFrom) and node.level:
                continue
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""]
            for name in names:
                top = name.split(".")[0]
                if top != root and top not in HEAVY_DEPENDENCIES:
                    problems.append(f"{where}: {name} is not a heavy dependency "
                                    "(cadalign._layers.HEAVY_DEPENDENCIES); import it at module top")
    return problems


def test_imports_inside_functions_are_lazy_for_a_reason() -> None:
    problems = lazy_import_problems(PACKAGE_DIR)
    assert not problems, "\n".join(problems)


def test_a_lazy_import_without_a_reason_is_found(tmp_path: Path) -> None:
    pkg = _write(tmp_path, {
        "pkg/__init__.py": "",
        "pkg/a.py": ("def f():\n    import torch  # lazy: heavy dependency (torch)\n    import json\n"
                     "    # lazy: pulls torch\n    from pkg import b\n    from pkg import c\n"),
    })
    found = lazy_import_problems(pkg)
    assert len(found) == 3 and "a.py:3" in found[0] and "a.py:3" in found[1] and "a.py:6" in found[2]


def _write(root: Path, files: dict[str, str]) -> Path:
    for rel, text in files.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    return root / "pkg"


def test_cycle_through_an_import_inside_a_function_is_found(tmp_path: Path) -> None:
    pkg = _write(tmp_path, {
        "pkg/__init__.py": "",
        "pkg/a.py": "from pkg.b import f\n",
        "pkg/b.py": "def f():\n    from pkg import a\n    return a\n",
        "pkg/sub/__init__.py": "",
        "pkg/sub/c.py": "from ..a import f\nfrom . import d\n",
        "pkg/sub/d.py": "import pkg.sub.c\n",
        "pkg/e.py": "import numpy\nfrom pkg.sub import c\n",
    })
    g = import_graph(pkg)
    assert g["pkg.b"] == {"pkg.a": 2} and g["pkg.sub.c"] == {"pkg.a": 1, "pkg.sub.d": 2}
    assert g["pkg.e"] == {"pkg.sub.c": 2}
    assert sorted(cycles(g)) == [["pkg.a", "pkg.b"], ["pkg.sub.c", "pkg.sub.d"]]


def test_upward_import_is_found() -> None:
    g = {"cadalign.geometry.camera": {"cadalign.infer.run": 3}, "cadalign.infer.run": {"cadalign.types": 1}}
    assert upward_imports(g) == {("cadalign.geometry.camera", "cadalign.infer.run"): 3}


MAX_MODULE_LINES = 500
MAX_FUNCTION_LINES = 80
SIZE_EXCEPTIONS: dict[str, str] = {}
"""module or ``module:function`` -> why it may be longer (issue 48: each exception justified). Empty."""


def size_problems(package_dir: Path) -> list[str]:
    """Modules over :data:`MAX_MODULE_LINES` lines and functions (decorators to last line) over
    :data:`MAX_FUNCTION_LINES`, not in :data:`SIZE_EXCEPTIONS`."""
    problems = []
    for module, path in module_files(package_dir).items():
        text = path.read_text(encoding="utf-8")
        n = len(text.splitlines())
        if n > MAX_MODULE_LINES and module not in SIZE_EXCEPTIONS:
            problems.append(f"{module}: {n} lines (split it by what its parts do)")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                start = min([node.lineno] + [d.lineno for d in node.decorator_list])
                length = (node.end_lineno or start) - start + 1
                if length > MAX_FUNCTION_LINES and f"{module}:{node.name}" not in SIZE_EXCEPTIONS:
                    problems.append(f"{module}:{node.name} (line {node.lineno}): {length} lines")
    return problems


def test_modules_and_functions_are_small() -> None:
    problems = size_problems(PACKAGE_DIR)
    assert not problems, (f"over {MAX_MODULE_LINES} lines a module or {MAX_FUNCTION_LINES} a function:\n"
                          + "\n".join(problems))


def test_an_oversized_function_is_found(tmp_path: Path) -> None:
    body = "".join(f"    x{i} = {i}\n" for i in range(MAX_FUNCTION_LINES))
    pkg = _write(tmp_path, {"pkg/__init__.py": "", "pkg/a.py": f"def f():\n{body}"})
    assert size_problems(pkg) == [f"pkg.a:f (line 1): {MAX_FUNCTION_LINES + 1} lines"]


def test_docs_architecture_lists_the_layers() -> None:
    """docs/architecture.md's table of layers is LAYERS, in order (the one place the order is written is _layers)."""
    doc = PACKAGE_DIR.parent / "docs" / "architecture.md"
    rows = [line.split("|")[1:3] for line in doc.read_text(encoding="utf-8").splitlines()
            if line.startswith("| ") and not line.startswith("| layer")]
    table = [(name.strip(), tuple(r.strip().strip("`") for r in rooms.split(","))) for name, rooms in rows]
    assert table == [(name, rooms) for name, rooms in LAYERS]
