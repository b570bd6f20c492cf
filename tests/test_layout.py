"""The package's import graph: no circles (also through imports inside functions), the kernels at the bottom,
the physical models apart from the library core."""

from __future__ import annotations

import ast
from pathlib import Path

import rcotorch

ROOT = Path(rcotorch.__file__).resolve().parent
# The packages and top-level modules, by level: each imports only from levels below its own (the package's
# __init__, which re-exports the public names lazily, is the facade above them all).
LAYERS = {"errors": 0, "system": 0, "engine": 1, "data": 1, "blocks": 2, "verdict": 2, "estimator": 3, "graph": 3,
          "models": 3, "wiring": 4, "run": 5, "__main__": 6,
          "scenario": 6}   # scenario: the import path of earlier releases, an alias of run.scenario
CORE_BELOW_MODELS = {"blocks.base", "blocks.lti", "blocks.nonlinear", "blocks.sources", "blocks.features",
                     "estimator.rco", "estimator.parameter_map", "estimator.transfer", "graph", "engine.kernels",
                     "engine.lowering", "engine.rls"}


def _modules() -> dict[str, Path]:
    mods = {}
    for p in ROOT.rglob("*.py"):
        parts = p.relative_to(ROOT.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        mods[name] = p
    return mods


def _imports(mods: dict[str, Path], lazy: bool) -> dict[str, set[str]]:
    """Module -> the package's modules it imports (at module level, or anywhere when ``lazy``)."""
    graph = {}
    for name, path in mods.items():
        package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
        tree = ast.parse(path.read_text(), str(path))
        nodes = ast.walk(tree) if lazy else tree.body
        targets = set()
        for node in nodes:
            if isinstance(node, ast.ImportFrom):
                base = package[:len(package) - node.level + 1] if node.level else []
                module = ".".join(base + ([node.module] if node.module else []))
                for alias in node.names:
                    sub = f"{module}.{alias.name}"
                    if sub in mods or not _is_package_path(mods, module):
                        targets.add(sub if sub in mods else module)
                    elif not _compiled(mods, module, alias.name):
                        targets.add(module)       # a name defined by the package's __init__
            elif isinstance(node, ast.Import):
                targets |= {a.name for a in node.names}
        graph[name] = {t for t in targets if t in mods and t != name}
    return graph


def _is_package_path(mods: dict[str, Path], module: str) -> bool:
    return module in mods and mods[module].name == "__init__.py"


def _compiled(mods: dict[str, Path], package: str, name: str) -> bool:
    """Whether ``from package import name`` names a submodule not written in Python (the compiled engine):
    a name the package's ``__init__`` does not bind."""
    tree = ast.parse(mods[package].read_text())
    bound = set()
    for node in tree.body:
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            bound |= {(a.asname or a.name).split(".")[0] for a in node.names}
        elif isinstance(node, (ast.FunctionDef, ast.ClassDef)):
            bound.add(node.name)
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            for t in node.targets if isinstance(node, ast.Assign) else [node.target]:
                bound |= {n.id for n in ast.walk(t) if isinstance(n, ast.Name)}
    return name not in bound


def _circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, found, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
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
                found.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    return found


def test_the_circle_finder_finds_a_planted_circle():
    assert _circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _circles({"a": {"b"}, "b": set()}) == []


def test_no_import_circle_at_module_level_or_inside_functions():
    mods = _modules()
    assert "rcotorch.engine.kernels" in mods and "rcotorch.estimator.rco" in mods
    for lazy in (False, True):
        graph = _imports(mods, lazy)
        # the package itself re-exports everything; a module importing `rcotorch` is an edge to all of it
        assert _circles(graph) == [], f"import circle ({'inside functions too' if lazy else 'module level'})"


def test_kernels_are_at_the_bottom_and_the_core_does_not_import_the_models():
    mods = _modules()
    graph = _imports(mods, lazy=True)
    assert graph["rcotorch.engine.kernels"] == set()
    for name in CORE_BELOW_MODELS:
        deps = graph[f"rcotorch.{name}"]
        assert not any(d.startswith(("rcotorch.models", "rcotorch.scenarios")) for d in deps), (name, deps)


def test_every_package_imports_only_from_the_levels_below_it():
    mods = _modules()
    graph = _imports(mods, lazy=True)

    def part(module: str) -> str:
        parts = module.split(".")
        return parts[1] if len(parts) > 1 else "rcotorch"

    found = {part(m) for m in mods} - {"rcotorch"}
    assert found == set(LAYERS), f"packages without a level: {found - set(LAYERS)}; gone: {set(LAYERS) - found}"
    upwards = sorted((m, d) for m, deps in graph.items() if part(m) != "rcotorch" for d in deps
                     if part(d) not in ("rcotorch", part(m)) and LAYERS[part(d)] >= LAYERS[part(m)])
    assert upwards == [], f"imports that do not go down a level: {upwards}"


FUNCTION_LINES = 80      # the most lines of code a function may have (its docstring and blank lines not counted)


def _code_lines(fn: ast.FunctionDef | ast.AsyncFunctionDef, source: list[str]) -> int:
    """Lines of ``fn`` holding code: its span less blank lines, comment-only lines and its docstring."""
    body = fn.body
    doc = set()
    if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) \
            and isinstance(body[0].value.value, str):
        doc = set(range(body[0].lineno, body[0].end_lineno + 1))
    lines = range(fn.lineno, fn.end_lineno + 1)
    return sum(1 for i in lines if i not in doc and source[i - 1].strip() and not source[i - 1].strip().startswith("#"))


def test_no_function_is_longer_than_80_lines_of_code():
    long = []
    for path in sorted(ROOT.rglob("*.py")):
        text = path.read_text()
        source = text.splitlines()
        for node in ast.walk(ast.parse(text, str(path))):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                n = _code_lines(node, source)
                if n > FUNCTION_LINES:
                    long.append(f"{path.relative_to(ROOT.parent)}:{node.lineno} {node.name} ({n} lines)")
    assert not long, "functions over 80 lines of code:\n" + "\n".join(long)
