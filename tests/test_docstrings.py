"""The public API's docstrings follow numpydoc, and their Parameters sections match the signatures.

The public API: every name in ``rcotorch.__all__``; the public functions and classes of the modules listed there
(``rcotorch.blocks.features``, ``rcotorch.data.datasets``, ``rcotorch.models`` and its submodules,
``rcotorch.engine.rng``); the public methods and properties of each public class, and its ``__call__``, its own
and those it inherits from a class of the library. A class documents its constructor's parameters in its own
docstring. A method that overrides a documented one without a docstring of its own inherits that docstring
(``inspect.getdoc``), which must then fit its signature.

For each callable the test checks that

* it has a docstring with a one-line summary;
* every parameter of its signature (but ``self`` and ``cls``) is named in the ``Parameters`` section
  (``*args`` and ``**kwargs`` as ``*args`` / ``**kwargs``), and every name there is a parameter;
* a function that returns or yields a value has a ``Returns`` or ``Yields`` section;
* every library error (``rcotorch.errors``) its body raises itself is named in a ``Raises`` section;
* a block (a ``Block`` subclass) has a ``Shape`` section: its ports and their widths, batch-first.
"""

from __future__ import annotations

import ast
import functools
import inspect
import textwrap
import types

import pytest
import torch

import rcotorch as rt
from rcotorch import errors

SECTIONS = ("Parameters", "Attributes", "Returns", "Yields", "Raises", "Shape", "See Also", "Notes", "Examples",
            "Other Parameters", "Warns", "References")
LIBRARY_ERRORS = {name for name, value in vars(errors).items()
                  if inspect.isclass(value) and issubclass(value, errors.RcoError)}
# Methods a class inherits or overrides from torch's Module or from Exception keep torch's and Python's
# documentation; of the special methods only ``__call__`` (a hook's or a term's) is the library's own API.
MODULE_NAMES, EXCEPTION_NAMES = set(dir(torch.nn.Module)), set(dir(Exception))
PROPERTIES = (property, functools.cached_property)

def _in_library(obj) -> bool:
    return (getattr(obj, "__module__", None) or "").split(".")[0] == "rcotorch"


def _module_names(module: types.ModuleType) -> list[str]:
    names = getattr(module, "__all__", None)
    if names is None:
        names = [n for n, v in vars(module).items()
                 if not n.startswith("_") and (inspect.isfunction(v) or inspect.isclass(v))
                 and v.__module__ == module.__name__]
    return list(names)


def _members(cls: type):
    """(defining class, name, attribute as looked up on ``cls``) for the public methods and properties of
    ``cls`` and of its library base classes."""
    foreign = MODULE_NAMES if issubclass(cls, torch.nn.Module) else \
        EXCEPTION_NAMES if issubclass(cls, BaseException) else set()
    seen = set()
    for base in cls.__mro__:
        if not _in_library(base):
            continue
        for name, raw in vars(base).items():
            if (name.startswith("_") and name != "__call__") or name in seen or name in foreign:
                continue
            seen.add(name)
            if isinstance(raw, PROPERTIES + (staticmethod, classmethod)) or inspect.isfunction(raw):
                yield base, name, raw if isinstance(raw, PROPERTIES) else getattr(cls, name)


def _public_api() -> dict[str, object]:
    """Qualified name -> public callable, each object once: a method under the public class that defines it."""
    found: dict[str, object] = {}
    ids: set[int] = set()
    modules: set[str] = set()
    classes: dict[type, str] = {}

    def visit_module(qual: str, module: types.ModuleType) -> None:
        if module.__name__ in modules:
            return
        modules.add(module.__name__)
        for name in _module_names(module):
            visit(f"{qual}.{name}", getattr(module, name))

    def visit(qual: str, obj) -> None:
        if inspect.ismodule(obj):
            if obj.__name__.split(".")[0] == "rcotorch":
                visit_module(qual, obj)
            return
        if not callable(obj) or not _in_library(obj) or id(obj) in ids:
            return
        ids.add(id(obj))
        found[qual] = obj
        if inspect.isclass(obj):
            classes[obj] = qual

    visit_module("rcotorch", rt)
    for cls, qual in list(classes.items()):
        for owner, name, member in _members(cls):
            key = _function(member) or member
            if id(key) not in ids:
                ids.add(id(key))
                found[f"{classes.get(owner, qual)}.{name}"] = member
    return found



def _doc(obj) -> str | None:
    if inspect.isclass(obj):
        doc = vars(obj).get("__doc__")                      # a class's own, not a base class's
        if doc and doc.startswith(f"{obj.__name__}("):      # the signature a dataclass writes by itself
            doc = None
        return inspect.cleandoc(doc) if doc else None
    return inspect.getdoc(obj)


def _sections(doc: str) -> dict[str, list[str]]:
    """numpydoc sections: heading -> its lines ('' -> the summary and extended description)."""
    out: dict[str, list[str]] = {"": []}
    lines = doc.splitlines()
    current, i = "", 0
    while i < len(lines):
        line = lines[i]
        if (line.strip() in SECTIONS and i + 1 < len(lines) and set(lines[i + 1].strip()) == {"-"}
                and len(lines[i + 1].strip()) == len(line.strip())):
            current = line.strip()
            out.setdefault(current, [])
            i += 2
            continue
        out[current].append(line)
        i += 1
    return out


def _names(lines: list[str]) -> list[str]:
    """Names of the entries ``name : type`` (or ``a, b : type``) of a Parameters-like section."""
    found = []
    for line in lines:
        if not line.strip() or line[0].isspace():
            continue
        head = line.split(" : ")[0].strip()
        found += [n.strip() for n in head.split(",") if n.strip()]
    return found


def _signature(obj) -> list[str] | None:
    """Parameter names as a docstring writes them, or None where there is no Python signature."""
    target = obj
    if inspect.isclass(obj):
        owner = next((c for c in obj.__mro__ if "__init__" in vars(c)), object)
        if not _in_library(owner):
            return None                                      # an exception's or a plain object's constructor
        target = vars(owner)["__init__"]
    if isinstance(obj, PROPERTIES):
        return None
    try:
        sig = inspect.signature(target)
    except (TypeError, ValueError):
        return None
    names = []
    for i, p in enumerate(sig.parameters.values()):
        if i == 0 and p.name in ("self", "cls") and not isinstance(obj, types.MethodType):
            continue
        names.append({p.VAR_POSITIONAL: f"*{p.name}", p.VAR_KEYWORD: f"**{p.name}"}.get(p.kind, p.name))
    return names


def _function(obj):
    """The plain function behind a method, classmethod or property (None for a class)."""
    if isinstance(obj, property):
        return obj.fget
    if isinstance(obj, functools.cached_property):
        return obj.func
    if inspect.isclass(obj):
        return None
    return inspect.unwrap(getattr(obj, "__func__", obj))


def _body(fn) -> ast.AST | None:
    try:
        source = textwrap.dedent(inspect.getsource(fn))
    except (OSError, TypeError):
        return None
    tree = ast.parse(source)
    return tree.body[0] if tree.body and isinstance(tree.body[0], ast.FunctionDef | ast.AsyncFunctionDef) \
        else None


def _own_nodes(node: ast.AST):
    """The nodes of a function body, not those of the functions, lambdas and classes nested in it."""
    for child in ast.iter_child_nodes(node):
        if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda | ast.ClassDef):
            continue
        yield child
        yield from _own_nodes(child)


def _returns_value(fn) -> bool:
    node = _body(fn)
    if node is None:
        return False
    for child in _own_nodes(node):
        if isinstance(child, ast.Yield | ast.YieldFrom):
            return True
        if isinstance(child, ast.Return) and child.value is not None and not (
                isinstance(child.value, ast.Constant) and child.value.value is None):
            return True
    return False


def _raised(fn) -> set[str]:
    """The library errors a function's body raises itself (``raise ConfigError(...)``)."""
    node = _body(fn)
    if node is None:
        return set()
    out = set()
    for child in _own_nodes(node):
        if isinstance(child, ast.Raise) and child.exc is not None:
            exc = child.exc.func if isinstance(child.exc, ast.Call) else child.exc
            name = exc.attr if isinstance(exc, ast.Attribute) else getattr(exc, "id", None)
            if name in LIBRARY_ERRORS:
                out.add(name)
    return out


def problems(obj) -> list[str]:
    """What is wrong with the docstring of ``obj`` (empty when it is complete)."""
    doc = _doc(obj)
    if not doc or not doc.strip():
        return ["no docstring"]
    found = []
    sections = _sections(doc)
    summary = [line for line in sections[""] if line.strip()]
    if not summary or not sections[""][0].strip():
        found.append("no one-line summary on the first line")
    params = _names(sections.get("Parameters", []))
    sig = _signature(obj)
    if sig is not None:
        documented = set(params) | (set(_names(sections.get("Attributes", []))) if inspect.isclass(obj) else set())
        missing = [p for p in sig if p not in documented and p.lstrip("*") not in documented]
        stale = [p for p in params if p not in sig and f"*{p}" not in sig and f"**{p}" not in sig]
        if missing:
            found.append(f"parameters not documented: {missing}")
        if stale:
            found.append(f"documented parameters not in the signature: {stale}")
    elif params and isinstance(obj, PROPERTIES):
        found.append("a property documents no parameters")
    fn = _function(obj)
    if fn is not None and not isinstance(obj, PROPERTIES) and _returns_value(fn) \
            and not ({"Returns", "Yields"} & set(sections)):
        found.append("returns a value but has no Returns section")
    raised = _raised(fn) if fn is not None else set()
    if inspect.isclass(obj) and _signature(obj) is not None:
        owner = next(c for c in obj.__mro__ if "__init__" in vars(c))
        raised = _raised(vars(owner)["__init__"])
    if raised:
        listed = set(_names(sections.get("Raises", [])))
        if not raised <= listed:
            found.append(f"raises {sorted(raised - listed)} without naming it in a Raises section")
    if inspect.isclass(obj) and issubclass(obj, rt.Block) and "Shape" not in sections:
        found.append("a block without a Shape section (its ports and widths)")
    return found


API = _public_api()


@pytest.mark.parametrize("qual", sorted(API))
def test_docstring(qual):
    found = problems(API[qual])
    assert found == [], f"{qual}: {found}"


def test_api_is_found():
    """The walk reaches the classes, their methods and the modules' functions (a walk that finds nothing
    would pass every check above)."""
    for qual in ("rcotorch.Block", "rcotorch.Block.output", "rcotorch.Block.step", "rcotorch.RCOEstimator.update",
                 "rcotorch.Graph.run", "rcotorch.LTI.from_control", "rcotorch.load", "rcotorch.refine",
                 "rcotorch.validate", "rcotorch.at_step", "rcotorch.datasets.silverbox_files"):
        assert qual in API, qual
    assert len(API) > 150


def test_checks_catch_a_missing_and_a_stale_parameter():
    # the checks read the source, so the examples are written to a module the test can read back
    import importlib.util
    import sys
    import tempfile
    from pathlib import Path

    cases = {
        "complete": '''
            def f(a, b=1, *rest, **options):
                """Sum.

                Parameters
                ----------
                a, b : float
                    Terms.
                *rest : float
                    More terms.
                **options
                    Ignored.

                Returns
                -------
                float
                """
                return a + b
            ''',
        "missing": '''
            def f(a, b):
                """Sum.

                Parameters
                ----------
                a : float
                    A term.
                """
            ''',
        "stale": '''
            def f(a):
                """Sum.

                Parameters
                ----------
                a : float
                    A term.
                c : float
                    Gone.
                """
            ''',
        "no_returns": '''
            def f(a):
                """Twice.

                Parameters
                ----------
                a : float
                    A term.
                """
                return 2 * a
            ''',
        "unnamed_raise": '''
            def f(a):
                """Check.

                Parameters
                ----------
                a : float
                    A term.
                """
                if a < 0:
                    raise ConfigError("a < 0")
            ''',
    }
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for key, source in cases.items():
            path = Path(tmp) / f"docstring_case_{key}.py"
            path.write_text("from rcotorch.errors import ConfigError\n" + textwrap.dedent(source))
            spec = importlib.util.spec_from_file_location(path.stem, path)
            module = importlib.util.module_from_spec(spec)
            sys.modules[path.stem] = module
            try:
                spec.loader.exec_module(module)
                results[key] = problems(module.f)
            finally:
                del sys.modules[path.stem]
    assert results["complete"] == []
    assert results["missing"] == ["parameters not documented: ['b']"]
    assert results["stale"] == ["documented parameters not in the signature: ['c']"]
    assert results["no_returns"] == ["returns a value but has no Returns section"]
    assert results["unnamed_raise"] == ["raises ['ConfigError'] without naming it in a Raises section"]
