"""The package's layering, read from its source with ``ast`` (nothing is imported).

``hartrao_jax/`` is a pipeline of subpackages; each may import only those before it:

    campaign -> geometry -> physics -> model -> solver -> preprocess -> fit -> surface
    -> diagnose -> simulate -> {prove, sensitivity} -> report -> cli

``_files`` (files written whole), ``_programs`` (compiled programs kept on disk) and ``_config``
are base modules every layer may import; the top-level ``__init__`` gathers the public API and
may import anything. Checked here: no upward import, no import between two subpackages of the
same rank, no cycle between subpackages or between modules, and no function-local import of a
package module (those hid cycles; optional heavy third-party dependencies such as dask,
matplotlib and pyarrow may stay lazy, they are not package modules).
"""

from __future__ import annotations

import ast
import pathlib

PKG = pathlib.Path(__file__).resolve().parents[1] / "hartrao_jax"

LAYERS: list[tuple[str, ...]] = [
    ("_files",),
    ("_programs",),
    ("_config",),
    ("campaign",),
    ("geometry",),
    ("physics",),
    ("model",),
    ("solver",),
    ("preprocess",),
    ("fit",),
    ("surface",),
    ("diagnose",),
    ("simulate",),
    ("prove", "sensitivity"),
    ("report",),
    ("cli",),
]
RANK = {name: i for i, names in enumerate(LAYERS) for name in names}

# Function-local imports of package modules that remain, as "module -> imported module".
# This list may only shrink: every entry is a cycle not yet broken by moving code.
ALLOWED_LOCAL: set[str] = set()


def _modules() -> dict[str, pathlib.Path]:
    out = {}
    for p in PKG.rglob("*.py"):
        rel = p.relative_to(PKG.parent).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = p
    return out


MODULES = _modules()


def _is_package(mod: str) -> bool:
    return MODULES[mod].name == "__init__.py"


def _resolve(mod: str, node: ast.ImportFrom) -> list[str]:
    """The package modules a ``from ... import ...`` statement in ``mod`` loads."""
    if node.level == 0:
        if not (node.module or "").startswith("hartrao_jax"):
            return []
        base = node.module
    else:
        parts = mod.split(".")
        if not _is_package(mod):
            parts = parts[:-1]
        parts = parts[: len(parts) - (node.level - 1)]
        base = ".".join(parts + ([node.module] if node.module else []))
    out = [base]
    for a in node.names:  # ``from . import _x`` loads the module ``_x``
        if f"{base}.{a.name}" in MODULES:
            out.append(f"{base}.{a.name}")
    return [m for m in out if m in MODULES]


def _imports() -> list[tuple[str, str, bool, int]]:
    """(importer, imported, at module level, line) for every package import."""
    rows = []
    for mod, path in MODULES.items():
        tree = ast.parse(path.read_text(), filename=str(path))
        top = set(map(id, tree.body))
        for node in ast.walk(tree):
            targets: list[str] = []
            if isinstance(node, ast.ImportFrom):
                targets = _resolve(mod, node)
            elif isinstance(node, ast.Import):
                targets = [a.name for a in node.names if a.name in MODULES]
            for t in targets:
                if t != mod:
                    rows.append((mod, t, id(node) in top, node.lineno))
    return rows


IMPORTS = _imports()


def _layer(mod: str) -> str | None:
    parts = mod.split(".")
    return parts[1] if len(parts) > 1 else None  # None: the top-level __init__


def test_every_subpackage_has_a_layer():
    layers = {_layer(m) for m in MODULES} - {None}
    assert layers <= set(RANK), sorted(layers - set(RANK))


def test_no_function_local_package_imports():
    local = {f"{a} -> {b}" for a, b, top, _ in IMPORTS if not top}
    assert local <= ALLOWED_LOCAL, sorted(local - ALLOWED_LOCAL)
    assert ALLOWED_LOCAL <= local, f"remove from ALLOWED_LOCAL: {sorted(ALLOWED_LOCAL - local)}"


def test_no_upward_or_sideways_imports():
    bad = []
    for a, b, _, line in IMPORTS:
        la, lb = _layer(a), _layer(b)
        if la is None or lb is None or la == lb:
            continue
        if RANK[lb] >= RANK[la]:
            bad.append(f"{a}:{line} imports {b} ({lb} is not before {la})")
    assert not bad, "\n".join(bad)


def _cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one node (Tarjan)."""
    index, low, stack, on, out, n = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = n[0]
        n[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in list(edges):
        if v not in index:
            visit(v)
    return out


def test_no_cycles_between_subpackages():
    edges: dict[str, set[str]] = {}
    for a, b, _, _ in IMPORTS:
        la, lb = _layer(a), _layer(b)
        if la and lb and la != lb:
            edges.setdefault(la, set()).add(lb)
    assert not _cycles(edges)


def test_no_cycles_between_modules():
    edges: dict[str, set[str]] = {}
    for a, b, _, _ in IMPORTS:
        if b.startswith(a + "."):
            continue  # a package's __init__ gathering its own modules
        edges.setdefault(a, set()).add(b)
    assert not _cycles(edges)


def test_the_checker_sees_a_violation():
    tree = ast.parse("def f():\n    from ..cli import main\n")
    node = tree.body[0].body[0]
    assert _resolve("hartrao_jax.fit._fit", node) == ["hartrao_jax.cli"]
    assert RANK["cli"] > RANK["fit"]
