"""The package layout keeps its architecture: imports only point down the layers, no cycles.

Layers (docs/ARCHITECTURE.md), lowest first. A module may import modules of its own package
and of any lower layer; importing a higher layer (an upward arrow) or closing a cycle fails
here with the offending edge. Function-level imports count too: they hide the same coupling.
"""
from __future__ import annotations

import ast
from pathlib import Path

import fastneus

PKG = Path(fastneus.__file__).resolve().parent
LAYERS = [
    {"fastneus.errors", "fastneus.io", "fastneus.timing", "fastneus.plugins", "fastneus.kernels", "fastneus.configs"},
    {"fastneus.config", "fastneus.geometry"},
    {"fastneus.data", "fastneus.light"},
    {"fastneus.formats", "fastneus.field", "fastneus.classical"},
    {"fastneus.train", "fastneus.synth"},
    {"fastneus.export", "fastneus.eval", "fastneus.baselines"},
    {"fastneus.pipeline"},
    {"fastneus.batch"},
    {"fastneus.cli", "fastneus.__main__"},
]


def _unit(mod: str) -> str:
    """The layer unit of a module: its top-level subpackage or module under fastneus."""
    parts = mod.split(".")
    return ".".join(parts[:2])


def _rank(mod: str) -> int:
    for i, layer in enumerate(LAYERS):
        if _unit(mod) in layer:
            return i
    raise AssertionError(f"{mod}: not in any layer of tests/test_layout.py (add it to LAYERS and ARCHITECTURE.md)")


def _modules() -> dict[str, Path]:
    out = {}
    for f in PKG.rglob("*.py"):
        rel = f.relative_to(PKG).with_suffix("")
        parts = ["fastneus", *rel.parts]
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = f
    return out


def _imports(mod: str, path: Path, known: set[str]) -> set[str]:
    """fastneus modules imported anywhere in ``path`` (resolved to the most specific known module)."""
    tree = ast.parse(path.read_text())
    pkg = mod if path.name == "__init__.py" else mod.rsplit(".", 1)[0]
    found = set()
    for node in ast.walk(tree):
        names = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = pkg.split(".")
                up = up[: len(up) - (node.level - 1)]
                base = ".".join(up + ([base] if base else []))
            names = [f"{base}.{a.name}" for a in node.names] + [base]
        for n in names:
            while n and n not in known:
                n = n.rsplit(".", 1)[0] if "." in n else ""
            if n and n.startswith("fastneus") and n != mod:
                found.add(n)
    # importing a.b.c also runs a and a.b; only the most specific target is the arrow
    return {n for n in found if not any(o != n and o.startswith(n + ".") for o in found) or n == "fastneus"} - {"fastneus"}


def _graph():
    mods = _modules()
    return {m: _imports(m, p, set(mods)) for m, p in mods.items()}


def test_every_module_is_in_a_layer():
    for m in _graph():
        if m != "fastneus":
            _rank(m)


def test_no_upward_imports():
    bad = []
    for m, deps in _graph().items():
        if m == "fastneus":  # the facade re-exports from every layer, lazily
            continue
        for d in deps:
            if _unit(d) != _unit(m) and _rank(d) > _rank(m):
                bad.append(f"{m} -> {d}")
    assert not bad, "upward imports:\n" + "\n".join(sorted(bad))


def _with_package_inits(mod: str, deps: set[str], known: set[str]) -> set[str]:
    """Importing ``a.b.c`` runs ``a/b/__init__`` first: an edge to every such package that is not
    one of ``mod``'s own (a cycle through a package's __init__ breaks imports in some orders)."""
    out = set(deps)
    for d in deps:
        parts = d.split(".")
        for k in range(2, len(parts)):
            pkg = ".".join(parts[:k])
            if pkg in known and not (mod == pkg or mod.startswith(pkg + ".")):
                out.add(pkg)
    return out


def test_no_import_cycles():
    graph = _graph()
    known = set(graph)
    g = {m: _with_package_inits(m, {d for d in deps if d != "fastneus"}, known)
         for m, deps in graph.items() if m != "fastneus"}
    state: dict[str, int] = {}
    stack: list[str] = []
    cycles = []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for d in sorted(g.get(m, ())):
            if state.get(d) == 1:
                cycles.append(" -> ".join(stack[stack.index(d):] + [d]))
            elif d not in state:
                visit(d)
        stack.pop()
        state[m] = 2

    for m in sorted(g):
        if m not in state:
            visit(m)
    assert not cycles, "import cycles:\n" + "\n".join(cycles)


def test_no_private_names_across_modules():
    """``from fastneus.x import _name`` from another module couples to an implementation detail."""
    bad = []
    roots = [PKG, PKG.parent / "scripts"]
    for root in roots:
        for f in root.rglob("*.py"):
            for node in ast.walk(ast.parse(f.read_text())):
                if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("fastneus"):
                    bad += [f"{f.name}: {node.module}.{a.name}" for a in node.names
                            if a.name.startswith("_") and not a.name.startswith("__")]
    assert not bad, "private names imported across modules:\n" + "\n".join(sorted(bad))
