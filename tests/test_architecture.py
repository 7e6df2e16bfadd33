"""The layout's rules (docs/architecture.md), read from the source with `ast`: nothing here
imports the code, so a rule is checked even where importing a module would fail or be slow.

- No library function is over 80 lines (from its `def` line to the last line of its body;
  decorators not counted).
- No import, at module level or inside a function, closes a circle between modules of the six
  packages (an import under `if TYPE_CHECKING:` never runs and does not count).
- A package imports only from the packages below it: sefa_cli > sefa_pipelines > sefa_deploy,
  sefa_sim > sefa_model > sefa_data (sefa_deploy and sefa_sim are siblings and import neither
  each other). Modules are named as they install and as every import names them: the folders
  cli/ and pipelines/ are sefa_cli and sefa_pipelines.
- Inside sefa_model, a layer imports only from the layers below it (LAYERS): the root modules
  every layer uses, flow/ and nets/ (no sefa import at all), methods/, policy/, data/, eval/,
  train/, sefa/; and no import closes a circle even under `if TYPE_CHECKING:`.
- An earlier SeFA stage never reaches a later one: training < reflow < alignment, directly or
  through other modules.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# The packages, from the bottom up: a package may import from those of a lower rank only.
RANK = {"sefa_data": 0, "sefa_model": 1, "sefa_sim": 2, "sefa_deploy": 2, "sefa_pipelines": 3,
        "sefa_cli": 4}
# Where each installed package's source lives (pyproject.toml's package-dir).
FOLDER = {"sefa_pipelines": "pipelines", "sefa_cli": "cli"}
# sefa_model's layers, from the bottom up ("" is its root: config, distributed, progress);
# flow and nets are siblings with no sefa import at all.
LAYERS = {"": 0, "flow": 1, "nets": 1, "methods": 2, "policy": 3, "data": 4, "eval": 5,
          "train": 6, "sefa": 7}
MAX_ROOT_MODULES = 8
MAX_FUNCTION_LINES = 80
# The SeFA stages in pipeline order: train -> reflow -> align (docs/architecture.md).
STAGES = ["sefa_model.train.loop", "sefa_model.sefa.reflow", "sefa_model.sefa.alignment"]

# Import circles known and being removed elsewhere, each as the set of its modules; the test
# fails once one no longer exists, so that the set is emptied as soon as it can be.
KNOWN_CYCLES: set[frozenset[str]] = set()
# Functions allowed over MAX_FUNCTION_LINES, as "path:qualified.name". Each entry is a known
# debt being split elsewhere; the test also fails once an entry no longer applies, so that the
# set is emptied as soon as it can be.
EXCEPTIONS: set[str] = set()


def module_name(path: Path) -> str:
    """The name a file's module installs and is imported under (cli/main.py: sefa_cli.main)."""
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    parts[0] = {folder: name for name, folder in FOLDER.items()}.get(parts[0], parts[0])
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def library_files() -> dict[str, Path]:
    """Module name -> file, for every module of the six packages."""
    files = {}
    for package in RANK:
        for path in sorted((ROOT / FOLDER.get(package, package)).rglob("*.py")):
            files[module_name(path)] = path
    return files


FILES = library_files()
TREES = {name: ast.parse(path.read_text(), filename=str(path)) for name, path in FILES.items()}


def runtime_nodes(tree: ast.AST, typing_too: bool = False):
    """Every node of the file except the bodies of `if TYPE_CHECKING:`: an import there never
    runs (it is how an annotation names a type whose module imports this one). `typing_too`:
    those bodies as well."""
    for child in ast.iter_child_nodes(tree):
        yield child
        if not typing_too and isinstance(child, ast.If) and ast.unparse(child.test) in (
                "TYPE_CHECKING", "typing.TYPE_CHECKING"):
            for other in child.orelse:
                yield other
                yield from runtime_nodes(other)
        else:
            yield from runtime_nodes(child, typing_too)


def imported_modules(name: str, tree: ast.Module, typing_too: bool = False) -> set[str]:
    """The library modules `name` imports anywhere in its file (module level, functions,
    methods; under TYPE_CHECKING too with `typing_too`): `from a.b import c` is a.b.c when that
    is a module, else a.b."""
    package = name if FILES[name].name == "__init__.py" else name.rpartition(".")[0]
    out = set()
    for node in runtime_nodes(tree, typing_too):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: from the package, up level - 1
                anchor = package.split(".")[:len(package.split(".")) - (node.level - 1)]
                base = ".".join([*anchor, base] if base else anchor)
            targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in FILES else base
                       for alias in node.names]
        else:
            continue
        for target in targets:
            while target and target not in FILES:  # `import a.b.c` of a name inside a.b
                target = target.rpartition(".")[0]
            if target and target != name:
                out.add(target)
    return out


GRAPH = {name: imported_modules(name, tree) for name, tree in TREES.items()}
# every edge, annotations' imports included: what a reader follows
FULL_GRAPH = {name: imported_modules(name, tree, typing_too=True) for name, tree in TREES.items()}


def long_functions() -> dict[str, int]:
    """"path:qualified.name" -> lines, for every function over MAX_FUNCTION_LINES."""
    found = {}

    def visit(node: ast.AST, prefix: str, path: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                qualname = f"{prefix}{child.name}"
                if not isinstance(child, ast.ClassDef):
                    lines = child.end_lineno - child.lineno + 1  # lineno: the def, not a decorator
                    if lines > MAX_FUNCTION_LINES:
                        found[f"{path}:{qualname}"] = lines
                visit(child, qualname + ".", path)
            else:
                visit(child, prefix, path)

    for name, tree in TREES.items():
        visit(tree, "", FILES[name].relative_to(ROOT).as_posix())
    return found


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles = []

    def connect(v: str) -> None:
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
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            connect(v)
    return cycles


def reachable(graph: dict[str, set[str]], start: str) -> dict[str, str]:
    """Module -> the module it was first reached from, for everything `start` imports,
    directly or through other modules."""
    came_from, todo = {}, [start]
    while todo:
        v = todo.pop()
        for w in sorted(graph[v]):
            if w not in came_from and w != start:
                came_from[w] = v
                todo.append(w)
    return came_from


def path_to(came_from: dict[str, str], start: str, end: str) -> str:
    chain = [end]
    while chain[-1] != start:
        chain.append(came_from[chain[-1]])
    return " -> ".join(reversed(chain))


def test_no_library_function_is_over_80_lines():
    found = long_functions()
    over = {where: n for where, n in found.items() if where not in EXCEPTIONS}
    assert not over, "functions over 80 lines (split them): " + ", ".join(
        f"{where} ({n} lines)" for where, n in sorted(over.items()))
    stale = EXCEPTIONS - set(found)
    assert not stale, f"EXCEPTIONS lists functions that are no longer over 80 lines: {sorted(stale)}"


def test_no_import_cycle():
    found = import_cycles(GRAPH)
    cycles = [c for c in found if frozenset(c) not in KNOWN_CYCLES]
    assert not cycles, "modules that import each other (directly or around a circle): " + "; ".join(
        " <-> ".join(c) for c in cycles)
    stale = KNOWN_CYCLES - {frozenset(c) for c in found}
    assert not stale, f"KNOWN_CYCLES lists circles that no longer exist: {sorted(map(sorted, stale))}"


def upward_imports(graph: dict[str, set[str]]) -> list[str]:
    """Every edge from a package into one of the same rank or above."""
    return sorted(f"{name} imports {target}" for name, targets in graph.items()
                  for target in targets
                  if target.split(".")[0] != name.split(".")[0]
                  and RANK[target.split(".")[0]] >= RANK[name.split(".")[0]])


def layer_of(module: str) -> str:
    """sefa_model.policy.model -> "policy"; sefa_model.config -> "" (the root)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 2 or (len(parts) == 2 and parts[1] in LAYERS) else ""


def layer_violations(graph: dict[str, set[str]]) -> list[str]:
    """Every edge inside sefa_model from a layer into one of the same rank or above (a module
    may import its own layer)."""
    wrong = []
    for name, targets in graph.items():
        if not name.startswith("sefa_model"):
            continue
        for target in targets:
            if not target.startswith("sefa_model"):
                continue
            a, b = layer_of(name), layer_of(target)
            if a != b and LAYERS[b] >= LAYERS[a]:
                wrong.append(f"{name} ({a or 'root'}) imports {target} ({b or 'root'})")
    return sorted(wrong)


def test_packages_import_only_from_below():
    wrong = upward_imports(GRAPH)
    assert not wrong, "imports from a package at the same level or above: " + "; ".join(wrong)


def test_sefa_model_layers_import_only_from_below():
    wrong = layer_violations(FULL_GRAPH)
    assert not wrong, "sefa_model: imports from a layer at the same rank or above: " + "; ".join(wrong)


def test_sefa_model_is_layers_with_a_small_root_and_no_circle_even_in_annotations():
    root = [n for n in FILES if n.count(".") == 1 and n.startswith("sefa_model.")
            and n.split(".")[1] not in LAYERS]
    assert len(root) <= MAX_ROOT_MODULES, f"sefa_model's root holds {len(root)} modules: {root}"
    packages = {n.split(".")[1] for n in FILES if n.startswith("sefa_model.") and n.count(".") >= 1
                and FILES[n].name == "__init__.py"}
    assert packages == set(LAYERS) - {""}, f"sefa_model's sub-packages: {sorted(packages)}"
    cycles = [c for c in import_cycles(FULL_GRAPH) if any(m.startswith("sefa_model") for m in c)]
    assert not cycles, "sefa_model modules that import each other: " + "; ".join(
        " <-> ".join(c) for c in cycles)


def test_an_injected_upward_import_is_caught():
    """A test of the tests: an import from sefa_model into sefa_pipelines (by the name every
    import uses), and one from a lower sefa_model layer into a higher one, each fail a rule."""
    tree = ast.parse("def f():\n    from sefa_pipelines.stages import stage_graph\n"
                     "    from sefa_model.train.loop import train\n")
    injected = imported_modules("sefa_model.config", tree)
    assert injected == {"sefa_pipelines.stages", "sefa_model.train.loop"}
    graph = {**GRAPH, "sefa_model.config": GRAPH["sefa_model.config"] | injected}
    assert upward_imports(graph) == ["sefa_model.config imports sefa_pipelines.stages"]
    assert layer_violations(graph) == [
        "sefa_model.config (root) imports sefa_model.train.loop (train)"]
    cli = ast.parse("import sefa_pipelines.workspace\nfrom sefa_cli import console\n")
    assert imported_modules("sefa_pipelines.stages", cli) == {"sefa_pipelines.workspace",
                                                             "sefa_cli.console"}


def test_no_stage_reaches_a_later_stage():
    wrong = []
    for i, stage in enumerate(STAGES):
        came_from = reachable(GRAPH, stage)
        wrong += [path_to(came_from, stage, later) for later in STAGES[i + 1:] if later in came_from]
    assert not wrong, "an earlier stage imports a later one: " + "; ".join(wrong)


def test_the_rules_see_the_code():
    """The checks above pass vacuously if the walk finds nothing: it must see every package,
    the stage modules, and imports of both kinds (module level and inside functions)."""
    assert {name.split(".")[0] for name in FILES} == set(RANK)
    assert set(STAGES) <= set(FILES)
    assert "sefa_data.errors" in GRAPH["sefa_model.sefa.alignment"]  # a module-level import
    assert "sefa_pipelines.runner" in GRAPH["sefa_pipelines.stages"]  # by its installed name
    assert "sefa_pipelines.workspace" in GRAPH["sefa_cli.workspace"]
    assert "sefa_data.readers.ros" in GRAPH["sefa_data.ingest"]  # one inside a function
    assert import_cycles({"a": {"b"}, "b": {"a"}, "c": {"a"}}) == [["a", "b"]]
