"""A user's own function compiled for the native engine.

A ``StaticMap``'s function, written with NumPy or ``math`` operations, is compiled by numba (``njit``) into a
C function ``void f(const double *in, double *out, int64 lanes)`` (a numba ``cfunc``) whose address the native
engine calls once per chunk of members and step (the ``CALL`` instruction: the chunk's inputs slot by slot,
``(n_in, lanes)``, outputs likewise): no Python runs per step, and an array-form function's arrays are made
once for the chunk's lanes, not once per member. numba is the usual choice of
the field for this (an LLVM compiler of NumPy code that can hand out C function pointers); the engine's own C
code needs nothing from it but the address.

Two forms are tried, the faster first: with one input and one output, the function applied to a float (a
scalar map such as ``lambda v: -(2 * np.sign(v) + 0.5 * v)``, in a loop over the lanes); otherwise, or when
that fails, applied to the chunk's (lanes, n) array and returning (lanes, m), as the PyTorch engine calls it
with a batch. The compiled function
is checked against the function itself on test inputs before it is used: a function that compiles but
computes something else (an operation that treats a float and a tensor differently) stays on PyTorch.

What cannot be compiled (torch operations, Python objects, an unsupported NumPy function) runs on the PyTorch
engine, and the reason names the block, the function and numba's word on the operation. Compilations are
kept for the process: copies of a graph (a sweep's shards in one process, the intervals' replay) reuse them.
"""

from __future__ import annotations

import re
import threading
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

PROBES = 64                 # test inputs the compiled function must reproduce
RTOL = 1e-12


@dataclass
class Compiled:
    """A compiled function: its C address, the numba object that owns the code, and its form."""

    address: int
    owner: Any
    form: str               # 'scalar' or 'array'

    def __deepcopy__(self, memo) -> Compiled:
        return self         # compiled code is immutable: copies of a graph (and of its program) share it


_cache: dict[tuple, tuple[Any, Compiled | str]] = {}
_lock = threading.Lock()


def call_user(fn, *args):
    """A user function called with tensors. NumPy's functions applied to a tensor go through its
    ``__array_wrap__``, whose old signature NumPy 2 warns about at each call; that says nothing to the user."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*__array_wrap__.*", category=DeprecationWarning)
        return fn(*args)


def describe(fn) -> str:
    """A function's name for messages: its qualified name and where it is defined."""
    code = getattr(fn, "__code__", None)
    name = getattr(fn, "__qualname__", None) or type(fn).__name__
    return f"{name} ({code.co_filename}:{code.co_firstlineno})" if code is not None else name


def compile_map(fn, n_in: int, n_out: int, reference=None) -> Compiled | str:
    """``fn`` (a (B, n_in) -> (B, n_out) map) as a compiled C function, or why it cannot be compiled; it must
    reproduce ``reference`` (default ``fn``) called with tensors."""
    key = (id(fn), n_in, n_out)
    with _lock:
        hit = _cache.get(key)
        if hit is not None and hit[0] is fn:
            return hit[1]
        result = _compile(fn, n_in, n_out, reference or fn)
        _cache[key] = (fn, result)            # holds fn, so its id is not reused while cached
        return result


def step_function(f, n: int, inputs: dict[str, int], dt: float, continuous: bool, substeps: int):
    """The discrete map of a ``Nonlinear`` block, x(k+1) from [x(k), inputs(k)] stacked in one (B, n + m)
    array: ``f`` itself (discrete), or ``substeps`` RK4 steps of dt / substeps with the inputs held, as
    ``Nonlinear.step_map`` computes it. Written as Python source with the port names as literals, so numba
    builds the inputs' dict as the PyTorch engine passes it. Kept per (f, sizes, ports, dt, form)."""
    key = ("step", id(f), n, tuple(inputs.items()), float(dt), bool(continuous), int(substeps))
    with _lock:
        hit = _cache.get(key)
        if hit is not None and hit[0] is f:
            return hit[1]
    cols, start = [], n
    for port, width in inputs.items():
        cols.append(f"{port!r}: xu[:, {start}:{start + width}]")
        start += width
    # An entry of another type makes numba keep the dict a compile-time literal (no dict made per call).
    ins = "{" + ", ".join(cols + ["'_rcotorch_literal': 0"]) + "}"
    if continuous:
        h = float(dt) / int(substeps)
        body = (f"    x = xu[:, :{n}]\n    ins = {ins}\n    for _ in range({int(substeps)}):\n"
                f"        k1 = f(x, ins)\n        k2 = f(x + {0.5 * h!r} * k1, ins)\n"
                f"        k3 = f(x + {0.5 * h!r} * k2, ins)\n        k4 = f(x + {h!r} * k3, ins)\n"
                f"        x = x + {h / 6.0!r} * (k1 + 2.0 * k2 + 2.0 * k3 + k4)\n    return x\n")
    else:
        body = f"    return f(xu[:, :{n}], {ins})\n"
    source = compile("def step(xu):\n" + body, f"<rcotorch step of {describe(f)}>", "exec")
    plain: dict = {"f": f}                     # the reference the compiled form is checked against
    exec(source, plain)
    jitted: dict = {"f": _jit(f)}              # the same source calling f compiled
    exec(source, jitted)
    pair = (jitted["step"], plain["step"])
    with _lock:
        _cache[key] = (f, pair)
    return pair


def _jit(f):
    """``f`` as numba calls it from compiled code (a dispatcher), or ``f`` when numba cannot take it (the
    compilation then fails with numba's reason)."""
    try:
        import numba
        return numba.njit(_with_helpers_jitted(f))
    except Exception:
        return f


def _with_helpers_jitted(fn, depth: int = 4):
    """A copy of ``fn`` whose plain Python helpers (functions it names as globals or closes over) are numba
    dispatchers, compiled the same way, so that a user's function may call functions of its own."""
    import types

    import numba
    if not isinstance(fn, types.FunctionType) or depth == 0:
        return fn

    def ready(v):
        if isinstance(v, types.FunctionType) and v is not fn and v.__module__ != "numpy" and \
                not v.__module__.startswith(("numpy.", "math")):
            return numba.njit(_with_helpers_jitted(v, depth - 1))
        return v
    names = set(fn.__code__.co_names)
    glob = {**fn.__globals__, **{k: ready(v) for k, v in fn.__globals__.items() if k in names}}
    def cell(c):
        try:
            return types.CellType(ready(c.cell_contents))
        except ValueError:                     # an empty cell (a name not yet bound)
            return c
    cells = tuple(cell(c) for c in fn.__closure__ or ())
    out = types.FunctionType(fn.__code__, glob, fn.__name__, fn.__defaults__, cells or None)
    out.__kwdefaults__, out.__qualname__ = fn.__kwdefaults__, fn.__qualname__
    return out


def _compile(fn, n_in: int, n_out: int, reference) -> Compiled | str:
    try:
        import numba
        from numba import types
    except ImportError:
        return "numba is not installed (pip install numba)"
    sig = types.void(types.CPointer(types.float64), types.CPointer(types.float64), types.int64)
    try:
        jfn = numba.njit(_with_helpers_jitted(fn))
    except Exception as e:                    # not a Python function numba can take
        return f"numba cannot take it: {_first_line(e)}"
    reasons = []
    forms = (["scalar"] if n_in == 1 and n_out == 1 else []) + ["array"]
    for form in forms:
        # x and y hold the chunk's lanes slot by slot: (n_in, vl) and (n_out, vl), row-major
        if form == "scalar":
            def body(x, y, vl):
                for lane in range(vl):
                    y[lane] = jfn(x[lane])
        else:
            def body(x, y, vl):
                r = jfn(numba.carray(x, (n_in, vl)).T)
                out = numba.carray(y, (n_out, vl))
                for j in range(n_out):
                    for lane in range(vl):
                        out[j, lane] = r[lane, j]
        try:
            cf = numba.cfunc(sig, nopython=True)(body)
        except Exception as e:
            reasons.append(_first_line(e))
            continue
        mismatch = _check(reference, cf, n_in, n_out)
        if mismatch:
            reasons.append(mismatch)
            continue
        return Compiled(address=cf.address, owner=cf, form=form)
    return reasons[-1] if reasons else "no form compiled"


def _check(fn, cf, n_in: int, n_out: int) -> str | None:
    """None when the compiled function gives the function's own values on test inputs (called for one member
    and for all of them at once), else what differs."""
    import ctypes

    rng = np.random.default_rng(12345)
    x = np.concatenate([rng.standard_normal((PROBES - 8, n_in)) * 10.0 ** rng.integers(-3, 4, (PROBES - 8, 1)),
                        np.zeros((1, n_in)), np.full((1, n_in), 1.5), np.full((1, n_in), -1.5),
                        rng.uniform(-1, 1, (5, n_in))])
    with torch.no_grad(), np.errstate(all="ignore"):
        want = call_user(fn, torch.from_numpy(x))
    want = want.detach().cpu().numpy() if isinstance(want, torch.Tensor) else np.asarray(want, dtype=float)
    if want.shape != (len(x), n_out):
        return f"it returns shape {want.shape} for a batch of {len(x)}, expected ({len(x)}, {n_out})"
    pd = ctypes.POINTER(ctypes.c_double)
    one = np.empty((len(x), n_out))
    for i in range(len(x)):
        xi, yi = np.ascontiguousarray(x[i]), np.empty(n_out)
        cf.ctypes(xi.ctypes.data_as(pd), yi.ctypes.data_as(pd), 1)
        one[i] = yi
    xs, ys = np.ascontiguousarray(x.T), np.empty((n_out, len(x)))
    cf.ctypes(xs.ctypes.data_as(pd), ys.ctypes.data_as(pd), len(x))
    with np.errstate(all="ignore"):
        return _compare(x, one, want) or _compare(x, ys.T, want)


def _compare(x: np.ndarray, got: np.ndarray, want: np.ndarray) -> str | None:
    same = np.isclose(got, want, rtol=RTOL, atol=RTOL * max(1.0, float(np.nanmax(np.abs(want), initial=0.0))),
                      equal_nan=True)
    if same.all():
        return None
    i = int(np.argwhere(~same)[0][0])
    return (f"the compiled function differs from the function itself at input {x[i].tolist()}: "
            f"{got[i].tolist()} against {want[i].tolist()}")


_ANSI = re.compile(r"\x1b\[[0-9;]*m")


def _first_line(e: BaseException) -> str:
    """numba's reason in one line: the line that names the operation where it says so."""
    lines = [ln.strip() for ln in _ANSI.sub("", str(e)).splitlines() if ln.strip()]
    for pattern in ("Unknown attribute", "Untyped global name", "No implementation of function",
                    "Use of unsupported", "Cannot determine Numba type", "unsupported", "Invalid use"):
        for ln in lines:
            if pattern in ln:
                return ln
    return lines[0] if lines else type(e).__name__
