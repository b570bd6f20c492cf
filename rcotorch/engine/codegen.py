"""Python source written for numba: the one place where rcotorch makes code as text and runs it.

numba compiles Python functions, and most of what the native engine calls is plain Python
(``rcotorch.engine.compiled``: the NumPy and torch stand-ins, their reductions and joins, the call of a
components-form map). Three things depend on sizes and names known only when a user's function is compiled,
and Python has no way to write them but as text:

* Tuples of a length known at run time. A tuple's length is part of its numba type, so a loop cannot build one,
  and a list or an array would be allocated on the heap for every member at every step. The C wrapper that
  calls a components-form function member by member (n_in floats in, n_out out), the step of such a function
  (its state and inputs as tuples, the RK4 stages written out component by component) and ``tuple_map`` (the
  per-channel sums of ``ChangeDetector``) are written out for their sizes.
* Dicts of a user's ports. numba keeps a dict display with constant keys (and values of more than one type) a
  compile-time structure, so that no dict is made per call; the port names must then be literals in the source
  (the batch-form step and an estimator's features).
* A module file for each compiled function. numba keeps what it compiles beside the source file it comes from,
  keyed by that file, so the wrappers of each function are a module of their own, named by a hash of everything
  its code depends on (``module``).

``define`` and ``module`` run what is written here; ``_run`` holds the package's one ``exec``.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import sys
import types
from collections.abc import Callable
from pathlib import Path

import numpy as np

# The C wrappers: x and y hold the chunk's lanes slot by slot, (n_in, vl) and (n_out, vl), row-major; ``jfn`` is
# the function (or step) compiled by numba, bound in the module before the wrappers are compiled.
_WRAPPERS = """
SIG = types.void(types.CPointer(types.float64), types.CPointer(types.float64), types.int64)


def scalar(x, y, vl):
    for lane in range(vl):
        y[lane] = jfn(x[lane])


def array(x, y, vl):
    r = jfn(numba.carray(x, (N_IN, vl)).T)
    out = numba.carray(y, (N_OUT, vl))
    for j in range(N_OUT):
        for lane in range(vl):
            out[j, lane] = r[lane, j]
"""


def define(source: str, name: str, namespace: dict, label: str) -> Callable:
    """The function that ``source`` defines as ``name``.

    Parameters
    ----------
    source : str
        Python source that defines ``name``.
    name : str
        The function's name.
    namespace : dict
        Its globals (copied; ``__name__`` is this module's unless given).
    label : str
        What the source is, for tracebacks (``<rcotorch label>``).

    Returns
    -------
    Callable
        The function.
    """
    space = {"__name__": __name__, **namespace}
    _run(source, space, f"<rcotorch {label}>")
    return space[name]


def _run(source: str, space: dict, filename: str) -> None:
    exec(compile(source, filename, "exec"), space)


def tuple_map(fn: Callable, n: int) -> Callable:
    """``fn`` over 0..n-1 as one tuple: a function of ``*args`` returning ``(fn(0, *args), .., fn(n - 1, *args))``.

    numba compiles it (and ``fn``, a plain function) with no tuple, list or array made per call; called with
    tensors, it is plain Python.

    Parameters
    ----------
    fn : Callable
        ``fn(i, *args)``, entry i of the tuple.
    n : int
        The tuple's length.

    Returns
    -------
    Callable
        The function of ``*args``.
    """
    entries = "".join(f"fn({i}, *args), " for i in range(n))
    return define(f"def each(*args):\n    return ({entries})\n", "each", {"fn": fn}, f"tuple_map of {n}")


def _ports(array: str, ports: dict[str, int], start: int) -> tuple[str, int]:
    """Source of the dict of ports that a batch-form function takes, each the columns of ``array`` from
    ``start`` on, in order; and the column after the last. An entry of another type makes numba keep the dict a
    compile-time literal (no dict made per call)."""
    cols = []
    for port, width in ports.items():
        cols.append(f"{port!r}: {array}[:, {start}:{start + width}]")
        start += width
    return "{" + ", ".join(cols + ["'_rcotorch_literal': 0"]) + "}", start


def step_source(n: int, inputs: dict[str, int], dt: float, continuous: bool, substeps: int) -> str:
    """Source of ``step(xu)``: a batch-form ``f``'s discrete map, x(k+1) from [x(k), inputs(k)] stacked in one
    (B, n + m) array, ``f`` itself or ``substeps`` RK4 steps of dt / substeps with the inputs held.

    Parameters
    ----------
    n : int
        The state's width.
    inputs : dict[str, int]
        Input port -> width, in the order of the columns after the state.
    dt : float
        The step [s].
    continuous : bool
        Whether ``f`` is a vector field (RK4) rather than the map itself.
    substeps : int
        RK4 steps per step.

    Returns
    -------
    str
        The source; it calls the global ``f``.
    """
    ins, _ = _ports("xu", inputs, n)
    if continuous:
        h = float(dt) / int(substeps)
        body = (f"    x = xu[:, :{n}]\n    ins = {ins}\n    for _ in range({int(substeps)}):\n"
                f"        k1 = f(x, ins)\n        k2 = f(x + {0.5 * h!r} * k1, ins)\n"
                f"        k3 = f(x + {0.5 * h!r} * k2, ins)\n        k4 = f(x + {h!r} * k3, ins)\n"
                f"        x = x + {h / 6.0!r} * (k1 + 2.0 * k2 + 2.0 * k3 + k4)\n    return x\n")
    else:
        body = f"    return f(xu[:, :{n}], {ins})\n"
    return "def step(xu):\n" + body


def features_source(ports: dict[str, int]) -> tuple[str, int]:
    """Source of ``features(s)``: a feature function called with its ports stacked in one (B, sum w) array.

    Parameters
    ----------
    ports : dict[str, int]
        Port -> width, in the order of the columns.

    Returns
    -------
    tuple of (str, int)
        The source (it calls the global ``f`` with the dict of ports) and the number of columns.
    """
    ins, width = _ports("s", ports, 0)
    return f"def features(s):\n    return f({ins})\n", width


def member_step_source(n: int, inputs: dict[str, int], dt: float, continuous: bool, substeps: int) -> str:
    """Source of ``step(x0, .., u0, ..)``: a components-form ``f``'s discrete map for one member, its state and
    inputs as floats, the RK4 stages written out component by component, so that no array is made in a step.
    The parameters are ``step_source``'s (``inputs`` in the order of the arguments after the state); the source
    calls the globals ``f`` and ``item`` (component i of what ``f`` returns).
    """
    xs = [f"x{i}" for i in range(n)]
    cols, start = [], 0
    for port, width in inputs.items():
        cols.append(f"{port!r}: ({''.join(f'u{start + j}, ' for j in range(width))})")
        start += width
    ins = "{" + ", ".join(cols + ["'_rcotorch_literal': 0"]) + "}"
    args = ", ".join(xs + [f"u{j}" for j in range(start)])

    def state(values) -> str:
        return "(" + "".join(f"{v}, " for v in values) + ")"

    lines = [f"def step({args}):", f"    ins = {ins}"]
    if continuous:
        h = float(dt) / int(substeps)

        def stage(k: str, c: float) -> list[str]:
            return [f"{x} + {c!r} * item({k}, {i})" for i, x in enumerate(xs)]

        lines += [f"    for _ in range({int(substeps)}):",
                  f"        k1 = f({state(xs)}, ins)",
                  f"        k2 = f({state(stage('k1', 0.5 * h))}, ins)",
                  f"        k3 = f({state(stage('k2', 0.5 * h))}, ins)",
                  f"        k4 = f({state(stage('k3', h))}, ins)"]
        lines += [f"        {x} = {x} + {h / 6.0!r} * (item(k1, {i}) + 2.0 * item(k2, {i}) + 2.0 * item(k3, {i})"
                  f" + item(k4, {i}))" for i, x in enumerate(xs)]
        lines.append(f"    return {state(xs)}")
    else:
        lines.append(f"    r = f({state(xs)}, ins)")
        lines.append(f"    return ({''.join(f'item(r, {i}), ' for i in range(n))})")
    return "\n".join(lines) + "\n"


def _member_wrapper(n_in: int, n_out: int) -> str:
    """The C wrapper of a components-form function: member by member, its inputs as separate floats."""
    args = ", ".join(f"x[{i} * vl + lane]" for i in range(n_in))
    body = "".join(f"        y[{j} * vl + lane] = item(r, {j})\n" for j in range(n_out))
    return f"\n\ndef member(x, y, vl):\n    for lane in range(vl):\n        r = jfn({args})\n{body}"


def module(source: str, n_in: int, n_out: int, member: bool, key: str | None,
           folder: Path | None) -> types.ModuleType:
    """A module of ``source`` and the C wrappers ``scalar``, ``array`` (and, with ``member``, ``member``) of a
    function of n_in inputs and n_out outputs, each ``void f(const double *x, double *y, int64 vl)`` once
    ``SIG`` is given to ``numba.cfunc`` and ``jfn`` (the function they call) is bound in the module.

    Parameters
    ----------
    source : str
        Source of the module's own functions (may be empty).
    n_in, n_out : int
        The widths of the wrappers' input and output.
    member : bool
        Add the member-by-member wrapper (a components-form function).
    key : str, optional
        Everything the compiled code depends on; None keeps the module in memory only.
    folder : Path, optional
        Where the module file is written when ``key`` is given (numba caches beside it): a file named by a hash
        of ``key``, the module's text and the versions of numba, NumPy and Python.

    Returns
    -------
    types.ModuleType
        The module.
    """
    text = (f"import numba\nfrom numba import types\n\nN_IN, N_OUT = {n_in}, {n_out}\n\n\n{source}"
            f"{_member_wrapper(n_in, n_out) if member else ''}{_WRAPPERS}")
    if key is None or folder is None:
        mod = types.ModuleType("rcotorch_compiled")
        _run(text, mod.__dict__, "<rcotorch compiled>")
        return mod
    import numba
    digest = hashlib.sha256("\n".join([key, text, numba.__version__, np.__version__, sys.version]).encode())
    name = f"rcotorch_compiled_{digest.hexdigest()[:32]}"
    if name in sys.modules:
        return sys.modules[name]
    path = folder / f"{name}.py"
    if not path.exists() or path.read_text() != text:
        tmp = path.with_name(f".{name}.{os.getpid()}.tmp")
        tmp.write_text(text)
        os.replace(tmp, path)
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod                 # numba finds the module by name when it loads its cached code
    spec.loader.exec_module(mod)
    return mod
