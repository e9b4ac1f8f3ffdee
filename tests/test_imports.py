"""The import graph of nerfbot, sims and tasks, read from the source (nothing is imported).

Two ratchets: the import cycles between modules and the imports made inside functions may
only go away. A new one fails here; one that went away must leave its list too, so the lists
always describe the code. The CLI's lazy imports (``nerfbot/cli.py``) and the optional Ray
import are not counted.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("nerfbot", "sims", "tasks")
#: Modules whose imports inside functions are intended: the CLI imports each command's code
#: when the command runs, so `nerfbot --help` stays fast.
LAZY_BY_DESIGN = {"nerfbot.cli"}
#: Optional dependencies, imported where they are used.
OPTIONAL = {"ray"}

#: Module pairs importing each other (directly or through others), as strongly connected
#: groups of the graph of all imports; sorted tuples of module names.
KNOWN_CYCLES = {
    ("nerfbot.auto", "nerfbot.bench", "nerfbot.bench_exec", "nerfbot.bench_point"),
    ("nerfbot.fields.fastnerf", "nerfbot.fields.fastnerf_cache", "nerfbot.fields.kilonerf",
     "nerfbot.methods", "nerfbot.plenoctree", "nerfbot.training"),
    ("sims.articulated", "sims.capture", "sims.cli", "sims.dynamic"),
    ("tasks.grasp", "tasks.grasp_report"),
}


def _modules() -> dict[str, Path]:
    found = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            name = ".".join(path.relative_to(ROOT).with_suffix("").parts)
            found[name.removesuffix(".__init__")] = path
    return found


MODULES = _modules()


def _target(module: str, node: ast.ImportFrom | ast.Import, path: Path) -> list[str]:
    """The project modules an import statement names (``from a import b`` may name a.b)."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    base = node.module or ""
    if node.level:
        package = module.split(".")
        if path.name != "__init__.py":
            package = package[:-1]
        package = package[:len(package) - node.level + 1]
        base = ".".join(package + ([base] if base else []))
    return [base] + [f"{base}.{a.name}" for a in node.names]


def _project_module(name: str) -> str | None:
    """The project module ``name`` is, or lies in (``nerfbot.data.load_dataset`` ->
    ``nerfbot.data``); None outside the project."""
    while name:
        if name in MODULES:
            return name
        name = name.rpartition(".")[0]
    return None


def import_graph() -> tuple[dict[str, set], dict[str, set]]:
    """(module -> modules imported at module level, module -> modules imported inside
    functions), project modules only."""
    top: dict[str, set] = {m: set() for m in MODULES}
    inner: dict[str, set] = {m: set() for m in MODULES}

    def visit(module, path, node, in_function):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.Import, ast.ImportFrom)):
                for name in _target(module, child, path):
                    if name.split(".")[0] in OPTIONAL:
                        continue
                    target = _project_module(name)
                    if target and target != module:
                        (inner if in_function else top)[module].add(target)
            nested = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef))
            visit(module, path, child, nested)

    for module, path in MODULES.items():
        visit(module, path, ast.parse(path.read_text()), False)
    return top, inner


def cycles(graph: dict[str, set]) -> set[tuple]:
    """Strongly connected groups of more than one module (Tarjan's algorithm)."""
    index, low, stack, on_stack, out = {}, {}, [], set(), set()

    def connect(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                out.add(tuple(sorted(group)))

    for v in sorted(graph):
        if v not in index:
            connect(v)
    return out


def test_import_cycles_only_go_away():
    top, inner = import_graph()
    both = {m: top[m] | inner[m] for m in MODULES}
    found = cycles(both)
    new = found - KNOWN_CYCLES
    gone = KNOWN_CYCLES - found
    assert not new, f"new import cycles: {sorted(new)}"
    assert not gone, f"cycles that no longer exist, remove them from KNOWN_CYCLES: {sorted(gone)}"


def test_imports_inside_functions_only_go_away():
    _, inner = import_graph()
    counted = {m: sorted(t) for m, t in inner.items() if t and m not in LAZY_BY_DESIGN}
    total = sum(len(t) for t in counted.values())
    assert total <= KNOWN_INNER_IMPORTS, (
        f"{total} imports inside functions (at most {KNOWN_INNER_IMPORTS}); import at module "
        f"level, or break the cycle that forces it: {counted}")
    assert total >= KNOWN_INNER_IMPORTS, (
        f"only {total} imports inside functions now: lower KNOWN_INNER_IMPORTS to {total}")


#: Imports made inside functions outside the CLI (see the module docstring).
KNOWN_INNER_IMPORTS = 71


def test_the_graph_sees_known_imports():
    """The reader itself: a module-level and a function-level import it must find."""
    top, inner = import_graph()
    assert "nerfbot.data.readers" in top["nerfbot.data"]
    assert "nerfbot.training" in inner["nerfbot.cli"]
