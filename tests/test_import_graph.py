"""The import graph of the package: no cycles between modules and no import from a lower layer into a higher one
(module level or inside a function: a function-local import is still a dependency); and only the CLI prints.
An exception would have to be listed below with where it goes; the lists may only shrink."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1] / "vslam"

# Lower layers never import higher ones. Packages (or root modules) of one layer may import each other.
LAYERS = [
    ["errors", "paths", "resources", "outputs", "progress", "quantize", "childproc", "config", "ddp", "runtime"],
    ["geometry", "data", "nn"],
    ["features", "inertial", "viz"],
    ["backend"],
    ["mapping", "dynamic"],
    ["loop"],
    ["tracking"],
    ["pipeline", "profiling", "fusion", "eval", "train"],
    ["bench", "cli", "__main__"],
]
LAYER = {p: i for i, names in enumerate(LAYERS) for p in names}

# (importer, imported) that break the rules today; the list may only shrink.
KNOWN_UPWARD: set[tuple[str, str]] = set()
KNOWN_CYCLES: list[set[str]] = []


def _modules() -> dict[str, Path]:
    out = {}
    for f in ROOT.rglob("*.py"):
        name = ".".join(("vslam", *f.relative_to(ROOT).with_suffix("").parts))
        out[name.removesuffix(".__init__")] = f
    return out


def _type_checking(node: ast.AST) -> bool:
    return isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)


def _imports(tree: ast.AST, mods: dict[str, Path]) -> set[str]:
    """Modules of the package imported anywhere in ``tree`` except under ``if TYPE_CHECKING`` (types only)."""
    found: set[str] = set()

    def visit(node: ast.AST) -> None:
        if _type_checking(node):
            return
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name in mods)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if node.module in mods:
                found.add(node.module)
            found.update(f"{node.module}.{a.name}" for a in node.names if f"{node.module}.{a.name}" in mods)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    return found


def _graph() -> dict[str, set[str]]:
    mods = _modules()
    g = {}
    for name, path in mods.items():
        deps = _imports(ast.parse(path.read_text()), mods) - {name}
        # a package's __init__ re-exporting its own submodules is a facade, not a dependency of theirs
        g[name] = {d for d in deps if not (path.name == "__init__.py" and d.startswith(name + "."))}
    return g


def _package(mod: str) -> str:
    return mod.split(".")[1] if mod.count(".") >= 1 else mod


def _cycles(g: dict[str, set[str]]) -> list[set[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def strong(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in g.get(v, ()):
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = set()
            while True:
                w = stack.pop()
                on.discard(w)
                comp.add(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(comp)

    for v in sorted(g):
        if v not in index:
            strong(v)
    return out


def test_every_package_has_a_layer():
    missing = sorted({_package(m) for m in _modules() if m != "vslam"} - set(LAYER))
    assert not missing, f"add these to LAYERS: {missing}"


def test_no_upward_imports():
    g = _graph()
    bad = sorted((a, b) for a, deps in g.items() for b in deps
                 if a != "vslam" and b != "vslam" and LAYER[_package(a)] < LAYER[_package(b)])
    new = [e for e in bad if e not in KNOWN_UPWARD]
    assert not new, "imports from a lower layer into a higher one:\n" + "\n".join(f"{a} -> {b}" for a, b in new)
    gone = KNOWN_UPWARD - set(bad)
    assert not gone, f"fixed, remove from KNOWN_UPWARD: {sorted(gone)}"


def test_no_import_cycles():
    cycles = _cycles(_graph())
    new = [c for c in cycles if c not in KNOWN_CYCLES]
    assert not new, "import cycles:\n" + "\n".join(" <-> ".join(sorted(c)) for c in new)
    gone = [c for c in KNOWN_CYCLES if c not in cycles]
    assert not gone, f"fixed, remove from KNOWN_CYCLES: {gone}"


def test_library_modules_never_print():
    """Output to the user is the CLI's (vslam/cli/); a library function returns what it found, logs, or raises.
    A module's own ``if __name__ == "__main__":`` block is a command of its own and may print."""
    bad = []
    for name, path in _modules().items():
        if name.startswith("vslam.cli"):
            continue
        tree = ast.parse(path.read_text())
        main_blocks = [n for n in tree.body if isinstance(n, ast.If) and "__main__" in ast.unparse(n.test)]
        skip = {id(x) for b in main_blocks for x in ast.walk(b)}
        bad += [f"{path.relative_to(ROOT.parent)}:{n.lineno}" for n in ast.walk(tree)
                if isinstance(n, ast.Call) and isinstance(n.func, ast.Name) and n.func.id == "print" and id(n) not in skip]
    assert not bad, "print() outside vslam/cli: " + ", ".join(bad)
