"""The layers of nerfbot, sims and tasks, read from docs/ARCHITECTURE.md and checked against the
import graph of the source (nothing is imported).

- every module belongs to one layer of the document's table, and every path there exists;
- a module imports only its own layer and the layers its row allows, directly or through theirs;
- no import cycle;
- no import inside a function, except the command line's lazy imports (``nerfbot/app/cli.py``
  and the ``pixelnerf`` command's ``nerfbot/app/pixelnerf_cli.py``, so ``nerfbot --help``
  stays fast), the optional Ray, and MuJoCo in ``sims/gl.py`` (imported after the GL backend
  is chosen).
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ARCHITECTURE = ROOT / "docs" / "ARCHITECTURE.md"
PACKAGES = ("nerfbot", "sims", "tasks")
#: Modules whose imports inside functions are intended: the CLI imports each command's code
#: when the command runs.
LAZY_BY_DESIGN = {"nerfbot.app.cli", "nerfbot.app.pixelnerf_cli"}
#: Optional dependencies, imported where they are used.
OPTIONAL = {"ray"}
#: (module, import) pairs that must run inside a function: MuJoCo reads MUJOCO_GL once, at
#: import, so sims.gl imports it after choosing the backend.
ORDERED_BY_DESIGN = {("sims.gl", "mujoco")}


def _modules() -> dict[str, Path]:
    found = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            name = ".".join(path.relative_to(ROOT).with_suffix("").parts)
            found[name.removesuffix(".__init__")] = path
    return found


MODULES = _modules()


def _target(module: str, node: ast.ImportFrom | ast.Import, path: Path) -> list[str]:
    """The modules an import statement names (``from a import b`` may name a.b)."""
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


def import_graph() -> tuple[dict[str, set], dict[str, set], dict[str, set]]:
    """(module -> project modules imported at module level, module -> project modules imported
    inside functions, module -> other top-level packages imported inside functions)."""
    top: dict[str, set] = {m: set() for m in MODULES}
    inner: dict[str, set] = {m: set() for m in MODULES}
    inner_external: dict[str, set] = {m: set() for m in MODULES}

    def visit(module, path, node, in_function):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.Import, ast.ImportFrom)):
                for name in _target(module, child, path):
                    target = _project_module(name)
                    if target is None:
                        if in_function and name and name.split(".")[0] not in OPTIONAL:
                            inner_external[module].add(name.split(".")[0])
                    elif target != module:
                        (inner if in_function else top)[module].add(target)
            nested = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef))
            visit(module, path, child, nested)

    for module, path in MODULES.items():
        visit(module, path, ast.parse(path.read_text()), False)
    return top, inner, inner_external


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


# -- the layers of docs/ARCHITECTURE.md ---------------------------------------------------------
def read_layers(text: str) -> dict[str, tuple[list[str], list[str]]]:
    """Layer name -> (module prefixes, layers it may import) from the "## Layers" table."""
    section = text.split("## Layers", 1)[1].split("\n## ", 1)[0]
    layers = {}
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) < 3 or cells[0] in ("layer", "") or set(cells[0]) <= {"-"}:
            continue
        paths = re.findall(r"`([^`]+)`", cells[1])
        prefixes = [p.rstrip("/").removesuffix(".py").replace("/", ".") for p in paths]
        allowed = [] if cells[2] in ("-", "") else [a.strip() for a in cells[2].split(",")]
        layers[cells[0]] = (prefixes, allowed)
    return layers


LAYERS = read_layers(ARCHITECTURE.read_text())
#: Package roots that belong to no layer: they must import nothing.
ROOTS = {"nerfbot", "tasks"}


def layer_of(module: str) -> str | None:
    """The layer whose longest prefix holds ``module``."""
    best, length = None, -1
    for name, (prefixes, _) in LAYERS.items():
        for prefix in prefixes:
            if (module == prefix or module.startswith(prefix + ".")) and len(prefix) > length:
                best, length = name, len(prefix)
    return best


def reachable(layer: str) -> set[str]:
    """The layers ``layer`` may import: its own, those its row lists, and theirs."""
    seen, todo = {layer}, [layer]
    while todo:
        for below in LAYERS[todo.pop()][1]:
            if below not in seen:
                seen.add(below)
                todo.append(below)
    return seen


def test_the_table_is_read():
    assert len(LAYERS) >= 10
    for name, (prefixes, allowed) in LAYERS.items():
        assert prefixes, f"layer {name} names no path"
        unknown = set(allowed) - set(LAYERS)
        assert not unknown, f"layer {name} may import unknown layer(s) {sorted(unknown)}"


def test_every_path_of_the_table_exists():
    for name, (prefixes, _) in LAYERS.items():
        for prefix in prefixes:
            path = ROOT / prefix.replace(".", "/")
            assert path.is_dir() or path.with_suffix(".py").is_file(), (
                f"docs/ARCHITECTURE.md: layer {name} names {prefix}, which does not exist")


def test_every_module_has_a_layer():
    homeless = [m for m in MODULES if m not in ROOTS and layer_of(m) is None]
    assert not homeless, f"modules in no layer of docs/ARCHITECTURE.md: {homeless}"


def test_imports_go_down_the_layers():
    top, inner, _ = import_graph()
    wrong = []
    for module in MODULES:
        for target in sorted(top[module] | inner[module]):
            if module in ROOTS or target in ROOTS:
                wrong.append(f"{module} -> {target} (a package root)")
                continue
            source_layer, target_layer = layer_of(module), layer_of(target)
            if target_layer not in reachable(source_layer):
                wrong.append(f"{module} ({source_layer}) -> {target} ({target_layer})")
    assert not wrong, "imports outside the layers of docs/ARCHITECTURE.md:\n" + "\n".join(wrong)


def test_no_import_cycles():
    top, inner, _ = import_graph()
    found = cycles({m: top[m] | inner[m] for m in MODULES})
    assert not found, f"import cycles: {sorted(found)}"


def test_no_imports_inside_functions():
    _, inner, inner_external = import_graph()
    found = {}
    for module in MODULES:
        if module in LAZY_BY_DESIGN:
            continue
        names = inner[module] | {e for e in inner_external[module]
                                 if (module, e) not in ORDERED_BY_DESIGN}
        if names:
            found[module] = sorted(names)
    assert not found, f"imports inside functions (import at module level): {found}"


def test_the_graph_sees_known_imports():
    """The reader itself: module-level, function-level and external imports it must find."""
    top, inner, inner_external = import_graph()
    assert "nerfbot.data.readers" in top["nerfbot.data"]
    assert "nerfbot.train.trainer" in inner["nerfbot.app.cli"]
    assert "mujoco" in inner_external["sims.gl"]


def test_the_rules_catch_an_upward_import():
    """A field importing the trainer, and sims importing a field, break the table."""
    assert "train" not in reachable("fields")
    assert "fields" not in reachable("sims")
    assert "sims" not in reachable("eval")
    assert layer_of("nerfbot.fields.ngp") == "fields"
    assert layer_of("nerfbot.methods") == "registry"
    assert cycles({"a": {"b"}, "b": {"a"}, "c": set()}) == {("a", "b")}
