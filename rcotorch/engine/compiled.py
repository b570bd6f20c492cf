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

torch's elementwise functions (``torch.tanh``, ``torch.clamp``, ``torch.where``, ``torch.cat``, ...) compile
through NumPy stand-ins (``_torch_stand_in``). What cannot be compiled (tensor methods, Python objects, an
unsupported NumPy function) runs on the PyTorch engine, and the reason names the block, the function and
numba's word on the operation. Compilations are kept for the process (copies of a graph, a sweep's shards in
one process, the intervals' replay reuse them) and on disk for later processes (``cache_folder``): each
function's wrappers are a small module file named by a hash of everything its code depends on, which numba
caches beside it; a function whose globals have no stable description (an arbitrary object) is compiled in
every process. What is loaded from the disk is checked like a fresh compilation, and compiled afresh if it
does not reproduce the function.
"""

from __future__ import annotations

import contextlib
import dis
import functools
import hashlib
import os
import re
import stat
import sys
import threading
import types
import warnings
import weakref
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..errors import DimensionError
from . import codegen
from .lowering import NotLowerable

PROBES = 64                 # test inputs the compiled function must reproduce
RTOL = 1e-12


@dataclass
class Compiled:
    """A compiled function: its C address, the numba object that owns the code, and its form."""

    address: int
    owner: Any
    form: str               # 'scalar', 'array' or 'member'

    def __deepcopy__(self, memo) -> Compiled:
        return self         # compiled code is immutable: copies of a graph (and of its program) share it


# key -> (the function, its fingerprint, its compilation or the refusal, kept without a traceback)
_cache: dict[tuple, tuple[Any, str | None, Compiled | NotLowerable]] = {}
_lock = threading.Lock()


_host_only: weakref.WeakSet = weakref.WeakSet()     # functions that refused GPU tensors (NumPy ones)
_arrays_only: weakref.WeakSet = weakref.WeakSet()   # functions that refused tensors and took NumPy arrays


def _to_host(a):
    """Tensors in ``a`` (a tensor, or a dict, tuple or list of them) as CPU tensors."""
    if isinstance(a, torch.Tensor):
        return a.cpu()
    if isinstance(a, dict):
        return {k: _to_host(v) for k, v in a.items()}
    if isinstance(a, (tuple, list)):
        return type(a)(_to_host(v) for v in a)
    return a


def _on_device(args) -> bool:
    """Whether any tensor in ``args`` is off the CPU."""
    if isinstance(args, torch.Tensor):
        return args.device.type != "cpu"
    if isinstance(args, dict):
        return any(_on_device(v) for v in args.values())
    if isinstance(args, (tuple, list)):
        return any(_on_device(v) for v in args)
    return False


def _to_numpy(a):
    """Tensors in ``a`` (a tensor, or a dict, tuple or list of them) as NumPy arrays."""
    if isinstance(a, torch.Tensor):
        return a.detach().cpu().numpy()
    if isinstance(a, dict):
        return {k: _to_numpy(v) for k, v in a.items()}
    if isinstance(a, (tuple, list)):
        return type(a)(_to_numpy(v) for v in a)
    return a


def call_user(fn, *args):
    """A user function called with tensors.

    NumPy's functions applied to a tensor go through its ``__array_wrap__``, whose old signature NumPy 2 warns
    about at each call; that says nothing to the user. A function written with NumPy cannot take a GPU tensor
    (NumPy reads host memory only): called with GPU tensors it raises ``TypeError``, and from then on it is
    called with CPU copies of its arguments (the caller moves the result to its device). Some NumPy functions
    do not take a tensor even on the CPU (``np.sum(x, axis=1, keepdims=True)`` calls ``x.sum`` with NumPy's
    argument names, which torch's does not know): a function that raises ``TypeError`` on tensors and not on
    arrays is called with NumPy arrays from then on (its callers take an array result as a tensor). A function
    of torch operations runs on the GPU as it is."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*__array_wrap__.*", category=DeprecationWarning)
        if fn in _arrays_only:
            return fn(*_to_numpy(args))
        if fn in _host_only:
            return fn(*_to_host(args))
        try:
            return fn(*args)
        except TypeError as e:
            first = e
        tries = ((_to_host, _host_only),) if _on_device(args) else ()
        for convert, kind in (*tries, (_to_numpy, _arrays_only)):
            try:
                out = fn(*convert(args))
            except TypeError:
                continue
            kind.add(fn)
            return out
        raise first


def describe(fn) -> str:
    """A function's name for messages: its qualified name and where it is defined."""
    code = getattr(fn, "__code__", None)
    name = getattr(fn, "__qualname__", None) or type(fn).__name__
    return f"{name} ({code.co_filename}:{code.co_firstlineno})" if code is not None else name


@dataclass
class Raised:
    """What compiled functions raised while ``raised_in_compiled`` watched: the first exception, the names of the
    functions on its traceback (innermost last) and how many were raised."""

    first: BaseException | None = None
    functions: tuple[str, ...] = ()
    count: int = 0

    def __bool__(self) -> bool:
        return self.count > 0


_watch_lock = threading.Lock()
_watching: list[Raised] = []             # one per native run in progress
_hook_before: list = []                  # the unraisable hook in place when the first run began


def _from_compiled(info) -> bool:
    """Whether an unraisable exception comes from numba's compiled code (a C function cannot pass it on)."""
    return "numba" in str(info.object)


def _unraisable(info) -> None:
    """``sys.unraisablehook`` while native runs are in progress: an exception raised in compiled code goes to each
    run in progress; anything else to the hook that was in place before."""
    if _from_compiled(info):
        with _watch_lock:
            if _watching:
                names, tb = [], info.exc_traceback
                while tb is not None:
                    names.append(tb.tb_frame.f_code.co_name)
                    tb = tb.tb_next
                for found in _watching:
                    if found.first is None:
                        found.first, found.functions = info.exc_value, tuple(names)
                    found.count += 1
                return
    (_hook_before[0] if _hook_before else sys.__unraisablehook__)(info)


@contextlib.contextmanager
def raised_in_compiled():
    """Collect what compiled user functions raise while the ``with`` block runs, in a ``Raised``.

    An exception inside a compiled function cannot propagate through the native engine's C code: numba reports it
    as unraisable and the call returns without writing its outputs. Inside this block such reports are collected
    (not printed), so that the caller can raise an error that names the block whose function raised."""
    found = Raised()
    with _watch_lock:
        if not _watching:
            _hook_before[:] = [sys.unraisablehook]
            sys.unraisablehook = _unraisable
        _watching.append(found)
    try:
        yield found
    finally:
        with _watch_lock:
            _watching.remove(found)
            if not _watching:
                if sys.unraisablehook is _unraisable:
                    sys.unraisablehook = _hook_before[0]
                _hook_before.clear()


def components(out, n: int, batch: int, dtype, device=None) -> torch.Tensor:
    """A components-form function's result as a batch (B, n): a sequence of n components (each a (B,) tensor
    or array, or a number shared by every member), an (n, B) tensor or array, or, for n = 1, one component."""
    if isinstance(out, (torch.Tensor, np.ndarray)) and out.ndim == 2:
        parts = list(out)
    elif isinstance(out, (tuple, list)):
        parts = list(out)
    elif n == 1:
        parts = [out]
    else:
        raise DimensionError(f"returned {type(out).__name__}, not a sequence of {n} components")
    if len(parts) != n:
        raise DimensionError(f"returned {len(parts)} components, expected {n}")
    cols = []
    for c in parts:
        c = torch.as_tensor(c, dtype=dtype, device=device)
        if c.dim() > 1 or (c.dim() == 1 and c.shape[0] not in (1, batch)):
            raise DimensionError(f"returned a component of shape {tuple(c.shape)}, expected ({batch},) or a number")
        cols.append(c.reshape(-1).expand(batch))
    return torch.stack(cols, dim=1)


def _lookup(key: tuple, fn) -> tuple[Compiled | None, str | None]:
    """The compilation kept for ``key`` if it was made of ``fn`` reading the same values as now (its fingerprint:
    a global or a closure variable changed since is compiled afresh, as numba bakes them in), and ``fn``'s
    fingerprint. A refusal kept for it is raised again, as a new ``NotLowerable`` with the same reason."""
    fp = _fingerprint(fn)
    hit = _cache.get(key)
    if hit is not None and hit[0] is fn and hit[1] == fp:
        if isinstance(hit[2], NotLowerable):
            raise NotLowerable(*hit[2].args)
        return hit[2], fp
    return None, fp


def _keep(key: tuple, fn, fp: str | None, compile_) -> Compiled:
    """``compile_()``, kept for ``key`` with ``fn`` (so that its id is not reused while kept) and its fingerprint;
    a ``NotLowerable`` it raises is kept too, and raised."""
    try:
        result = compile_()
    except NotLowerable as e:
        _cache[key] = (fn, fp, NotLowerable(*e.args))
        raise
    _cache[key] = (fn, fp, result)
    return result


def compile_map(fn, n_in: int, n_out: int, form: str = "batch") -> Compiled:
    """``fn`` (a (B, n_in) -> (B, n_out) map; in the ``components`` form, a function of the sequence of n_in
    components returning n_out components, ``rcotorch.blocks.nonlinear``) as a compiled C function; it must
    reproduce ``fn`` called with tensors. Raises ``NotLowerable`` (why it cannot be compiled)."""
    key = (id(fn), n_in, n_out, form)
    with _lock:
        found, fp = _lookup(key, fn)
        if found is not None:
            return found
        if form == "components":
            return _keep(key, fn, fp, lambda: _compile_member(
                lambda module: _numba().njit(_spread(module.f)), _batch_reference(_spread(fn), n_out), n_in, n_out,
                "", fn, None if fp is None else f"components map {n_in} {n_out} {fp}"))
        return _keep(key, fn, fp, lambda: _compile(lambda module: _jit(fn), fn, n_in, n_out, "", {},
                                                   None if fp is None else f"map {n_in} {n_out} {fp}"))


def _spread(f):
    """``f``, a function of one tuple (a components-form map), as a function of the tuple's entries: as the
    member-by-member wrapper calls it, one float per component."""
    def call(*xs):
        return f(xs)
    return call


def _batch_reference(member, n_out: int):
    """A components-form function of n_in arguments as a batch map (B, n_in) -> (B, n_out), called with the
    batch's columns: what its compiled form must reproduce."""
    def batch(xu: torch.Tensor) -> torch.Tensor:
        return components(call_user(member, *xu.T), n_out, xu.shape[0], xu.dtype, xu.device)
    return batch


def compile_step(f, n: int, inputs: dict[str, int], dt: float, continuous: bool, substeps: int,
                 form: str = "batch") -> Compiled:
    """The discrete map of a ``Nonlinear`` block compiled, x(k+1) from [x(k), inputs(k)] stacked in one
    (B, n + m) array: ``f`` itself (discrete), or ``substeps`` RK4 steps of dt / substeps with the inputs held,
    as ``Nonlinear.step_map`` computes it. Written as Python source with the port names as literals
    (``codegen.step_source``), so numba builds the inputs' dict as the PyTorch engine passes it. Raises
    ``NotLowerable`` (why it cannot be compiled)."""
    if form == "components":
        return _compile_member_step(f, n, inputs, dt, continuous, substeps)
    key = ("step", id(f), n, tuple(inputs.items()), float(dt), bool(continuous), int(substeps))
    with _lock:
        found, fp = _lookup(key, f)
        if found is not None:
            return found
        source = codegen.step_source(n, inputs, dt, continuous, substeps)
        # the same source calling f itself: what the compiled code is checked against
        reference = codegen.define(source, "step", {"f": f}, f"step of {describe(f)}")
        return _keep(key, f, fp, lambda: _compile(lambda module: _numba().njit(module.step), reference,
                                                  n + sum(inputs.values()), n, source, {"f": _jit(f)},
                                                  None if fp is None else f"step {fp}"))


def compile_features(fn, ports: dict[str, int], width: int) -> Compiled:
    """An estimator's feature function compiled: ``fn`` takes the dict of its ports, each (B, w), and returns
    the (B, width) feature signals; compiled, it takes the ports stacked in one (B, sum w) array, in the order of
    ``ports``, and is called once per chunk of members. Written as Python source with the port names as
    literals (``codegen.features_source``), as ``compile_step`` does, so numba builds the dict as the PyTorch
    engine passes it. Raises ``NotLowerable`` (why it cannot be compiled)."""
    key = ("features", id(fn), tuple(ports.items()), int(width))
    with _lock:
        found, fp = _lookup(key, fn)
        if found is not None:
            return found
        source, start = codegen.features_source(ports)
        reference = codegen.define(source, "features", {"f": fn}, f"features of {describe(fn)}")
        return _keep(key, fn, fp, lambda: _compile(lambda module: _numba().njit(module.features),
                                                   reference, start, width, source, {"f": _jit(fn)},
                                                   None if fp is None else f"features {ports} {width} {fp}",
                                                   ("array",)))


def _compile_member_step(f, n: int, inputs: dict[str, int], dt: float, continuous: bool,
                         substeps: int) -> Compiled:
    """``compile_step`` for a components-form ``f``: one member at a time, the state and the inputs as tuples
    of floats, the RK4 stages written out component by component (``codegen.member_step_source``), so that no
    array is made in a step."""
    key = ("member step", id(f), n, tuple(inputs.items()), float(dt), bool(continuous), int(substeps))
    with _lock:
        found, fp = _lookup(key, f)
        if found is not None:
            return found
        m = sum(inputs.values())
        source = codegen.member_step_source(n, inputs, dt, continuous, substeps)
        reference = codegen.define(source, "step", {"f": f, "item": _item}, f"step of {describe(f)}")
        return _keep(key, f, fp, lambda: _compile_member(lambda module: _numba().njit(module.step),
                                                         _batch_reference(reference, n), n + m, n, source, f,
                                                         None if fp is None else f"member step {fp}"))


def _item(r, i: int):
    """Component i of a components-form result: r[i] of a sequence, r itself when it is one number (or one
    (B,) component)."""
    if isinstance(r, (tuple, list)) or (isinstance(r, (torch.Tensor, np.ndarray)) and r.ndim == 2):
        return r[i]
    return r


@functools.cache
def _numba_item():
    """``_item`` for numba: typed by what the user's function returns (a float, a tuple or an array)."""
    numba = _numba()
    from numba import types as nt
    from numba.extending import overload

    def item(r, i):
        pass

    @overload(item, inline="always")
    def _ov(r, i):
        if isinstance(r, (nt.Float, nt.Integer, nt.Boolean)):
            return lambda r, i: float(r)
        if isinstance(r, nt.Array) and r.ndim == 0:
            return lambda r, i: float(r[()])
        return lambda r, i: float(r[i])
    return numba.njit(inline="always")(lambda r, i: item(r, i))


def _numba():
    import numba
    return numba


def _jit(f):
    """``f`` as numba calls it from compiled code (a dispatcher), or ``f`` when numba cannot take it (the
    compilation then fails with numba's reason)."""
    try:
        import numba
        return numba.njit(_with_helpers_jitted(f))
    except Exception:
        return f


def _compile_member(entry, reference, n_in: int, n_out: int, source: str, f, key: str | None) -> Compiled:
    """``_compile`` of the member-by-member wrapper of a components-form ``f``, bound as ``f`` (and ``item``) in
    the module of ``source`` that ``entry`` reads: first ``f`` with the lists it returns built as tuples
    (``_returning_tuples``; its disk cache key says so), then, when that fails to compile or to reproduce ``f`` (a
    function that also returns a list made elsewhere, say), ``f`` as it is, whose ``NotLowerable`` is the one
    raised."""
    as_tuples = _returning_tuples(f)
    if as_tuples is not f:
        with contextlib.suppress(NotLowerable):
            return _compile(entry, reference, n_in, n_out, source, {"f": _jit(as_tuples), "item": _numba_item()},
                            None if key is None else key + " tuples", ("member",))
    return _compile(entry, reference, n_in, n_out, source, {"f": _jit(f), "item": _numba_item()}, key, ("member",))


_BUILD_LIST, _BUILD_TUPLE, _RETURN = (dis.opmap[name] for name in ("BUILD_LIST", "BUILD_TUPLE", "RETURN_VALUE"))


def _returning_tuples(f):
    """A copy of ``f`` in which each list display that is returned at once (``return [a, b]``) is built as a
    tuple: the same components, read the same way (``item``), without the heap allocation that numba makes for
    a list at every call, for every member and step. ``f`` itself when it returns no list display."""
    if not isinstance(f, types.FunctionType):
        return f
    code = bytearray(f.__code__.co_code)
    changed = False
    for i in range(0, len(code) - 2, 2):                 # instructions are (opcode, argument) byte pairs
        if code[i] == _BUILD_LIST and code[i + 2] == _RETURN:
            code[i], changed = _BUILD_TUPLE, True
    if not changed:
        return f
    out = types.FunctionType(f.__code__.replace(co_code=bytes(code)), f.__globals__, f.__name__, f.__defaults__,
                             f.__closure__)
    out.__kwdefaults__, out.__qualname__ = f.__kwdefaults__, f.__qualname__
    return out


# torch's functions that a compiled function may call as ``torch.NAME``: their NumPy namesakes (numba compiles
# those), or a NumPy expression of the same value (below, in _torch_stand_in).
_TORCH_AS_NUMPY = {
    "abs": "abs", "absolute": "abs", "sign": "sign", "sgn": "sign", "exp": "exp", "exp2": "exp2", "expm1": "expm1",
    "log": "log", "log2": "log2", "log10": "log10", "log1p": "log1p", "sqrt": "sqrt", "square": "square",
    "sin": "sin", "cos": "cos", "tan": "tan", "asin": "arcsin", "arcsin": "arcsin", "acos": "arccos",
    "arccos": "arccos", "atan": "arctan", "arctan": "arctan", "atan2": "arctan2", "arctan2": "arctan2",
    "sinh": "sinh", "cosh": "cosh", "tanh": "tanh", "asinh": "arcsinh", "arcsinh": "arcsinh", "acosh": "arccosh",
    "arccosh": "arccosh", "atanh": "arctanh", "arctanh": "arctanh", "floor": "floor", "ceil": "ceil",
    "trunc": "trunc", "maximum": "maximum", "minimum": "minimum", "fmax": "fmax", "fmin": "fmin",
    "hypot": "hypot", "copysign": "copysign", "pow": "power", "where": "where", "sinc": "sinc",
    "heaviside": "heaviside", "zeros_like": "zeros_like", "ones_like": "ones_like",
}


@functools.cache
def _torch_stand_in() -> types.ModuleType:
    """What a compiled function sees as ``torch``: a module of the same name whose functions compute with
    NumPy what torch's namesakes compute with tensors (``_TORCH_AS_NUMPY``; clamp / clip, sigmoid, relu,
    reciprocal, rsqrt, stack and cat written out; sum, mean, prod, amax and amin with dim and keepdim,
    ``_reduction``; the constants pi, e, inf and nan). A function that uses
    anything else of torch (a tensor method, ``torch.nn``) does not compile, and numba's reason names it."""
    numba = _numba()
    mod = types.ModuleType("torch")
    for name, np_name in _TORCH_AS_NUMPY.items():
        setattr(mod, name, getattr(np, np_name))

    def clamp(x, min=None, max=None):                      # noqa: A002  (torch's own argument names)
        if min is not None:
            x = np.maximum(x, min)
        if max is not None:
            x = np.minimum(x, max)
        return x

    joins = _numpy_stand_in()

    def stack(tensors, dim=0):
        return joins.stack(tensors, dim)

    def cat(tensors, dim=0):
        return joins.concatenate(tensors, dim)

    extra = {"clamp": clamp, "clip": clamp, "sigmoid": lambda x: 1.0 / (1.0 + np.exp(-x)),
             "relu": lambda x: np.maximum(x, 0.0), "reciprocal": lambda x: 1.0 / x,
             "rsqrt": lambda x: 1.0 / np.sqrt(x), "stack": stack, "cat": cat, "concatenate": cat, "concat": cat}
    for name, f in extra.items():
        setattr(mod, name, numba.njit(f))
    for name, op in _TORCH_REDUCTIONS.items():
        setattr(mod, name, _reduction(op, "torch"))
    for name in ("pi", "e", "inf", "nan"):
        setattr(mod, name, float(getattr(torch, name)))
    return mod


_JOINS = ("concatenate", "hstack", "vstack", "column_stack", "stack")


@functools.cache
def _joins():
    """The compiled joins of ``_numpy_stand_in``: ``join1`` (1-d arrays end to end), ``join2`` (2-d arrays along
    axis 0 or 1) and ``rows`` (1-d arrays of one length as the rows of a 2-d array), each taking a list."""
    numba = _numba()

    def join2(arrays, ax):                # 2-d arrays along axis ax (0 or 1)
        n = 0
        for a in arrays:
            n += a.shape[ax]
        first = arrays[0]
        out = np.empty((n, first.shape[1]) if ax == 0 else (first.shape[0], n), first.dtype)
        at = 0
        for a in arrays:
            if ax == 0:
                out[at:at + a.shape[0], :] = a
                at += a.shape[0]
            else:
                out[:, at:at + a.shape[1]] = a
                at += a.shape[1]
        return out

    def join1(arrays):                    # 1-d arrays end to end
        n = 0
        for a in arrays:
            n += a.shape[0]
        out = np.empty(n, arrays[0].dtype)
        at = 0
        for a in arrays:
            out[at:at + a.shape[0]] = a
            at += a.shape[0]
        return out

    def rows(arrays):                     # 1-d arrays of one length as the rows of a 2-d array
        first = arrays[0]
        out = np.empty((len(arrays), first.shape[0]), first.dtype)
        for i, a in enumerate(arrays):
            out[i, :] = a
        return out

    return tuple(numba.njit(f) for f in (join1, join2, rows))


@functools.cache
def _numpy_stand_in() -> types.ModuleType:
    """What a compiled function sees as ``np``: NumPy itself, except that its joins (``_JOINS``) also take a
    list of arrays, as NumPy does and numba's own do not (they take a tuple): ``np.concatenate([a, b], axis=1)``,
    the way a feature function or a batch-form map is usually written, compiles. The list's arrays are 1-d or
    2-d (``stack``: 1-d); a tuple goes to numba's own. Its reductions (``_REDUCTIONS``) take an axis and
    keepdims (``_reduction``)."""
    from numba import types as nt
    from numba.extending import overload

    mod = types.ModuleType("numpy")
    mod.__dict__.update({k: v for k, v in vars(np).items() if not k.startswith("__")})

    def concatenate(arrays, axis=0):
        pass

    def hstack(arrays):
        pass

    def vstack(arrays):
        pass

    def column_stack(arrays):
        pass

    def stack(arrays, axis=0):
        pass

    join1, join2, rows = _joins()

    def listed(arrays, ndim=None):
        return isinstance(arrays, nt.List) and isinstance(arrays.dtype, nt.Array) and \
            (ndim is None or arrays.dtype.ndim in ndim)

    @overload(concatenate)
    def _concatenate(arrays, axis=0):
        if not listed(arrays, (1, 2)):
            return lambda arrays, axis=0: np.concatenate(arrays, axis)
        if arrays.dtype.ndim == 1:
            return lambda arrays, axis=0: join1(arrays)
        return lambda arrays, axis=0: join2(arrays, axis + 2 if axis < 0 else axis)

    @overload(hstack)
    def _hstack(arrays):
        if not listed(arrays, (1, 2)):
            return lambda arrays: np.hstack(arrays)
        return (lambda arrays: join1(arrays)) if arrays.dtype.ndim == 1 else (lambda arrays: join2(arrays, 1))

    @overload(vstack)
    def _vstack(arrays):
        if not listed(arrays, (1, 2)):
            return lambda arrays: np.vstack(arrays)
        return (lambda arrays: rows(arrays)) if arrays.dtype.ndim == 1 else (lambda arrays: join2(arrays, 0))

    @overload(column_stack)
    def _column_stack(arrays):
        if not listed(arrays, (1, 2)):
            return lambda arrays: np.column_stack(arrays)
        return (lambda arrays: rows(arrays).T.copy()) if arrays.dtype.ndim == 1 else \
            (lambda arrays: join2(arrays, 1))

    @overload(stack)
    def _stack(arrays, axis=0):
        if not listed(arrays, (1,)):
            return lambda arrays, axis=0: np.stack(arrays, axis)
        return lambda arrays, axis=0: rows(arrays) if axis == 0 else rows(arrays).T.copy()

    for name, f in zip(_JOINS, (concatenate, hstack, vstack, column_stack, stack)):
        setattr(mod, name, f)
    for name, op in _REDUCTIONS.items():
        setattr(mod, name, _reduction(op, "numpy"))
    return mod


# Reductions a compiled function may call with an axis and keepdims, as NumPy (and torch, with dim and keepdim)
# take them; numba's own take no keepdims, and its max and min no axis. The value is the operation's code in
# ``_reduce``.
_REDUCTIONS = {"sum": 0, "mean": 1, "max": 2, "amax": 2, "min": 3, "amin": 3, "prod": 4}
_TORCH_REDUCTIONS = {"sum": 0, "mean": 1, "amax": 2, "amin": 3, "prod": 4}


@functools.cache
def _reduce():
    """The reductions of a float array of 1 or 2 dimensions along axis ``ax`` (0 or 1; of a 1-d array, 0),
    written out: a 1-d array of the other axis's length (of a 1-d array, length 1). NaN propagates as in NumPy."""
    numba = _numba()

    @numba.njit
    def reduce(a, ax, op):
        b = a.reshape((1, a.shape[0])) if a.ndim == 1 else a
        if ax == 0:
            b = b.T
        m, n = b.shape
        if n == 0 and (op == 2 or op == 3):
            raise ValueError("zero-size array to a max or min reduction, which has no identity")
        out = np.empty(m, np.float64)
        for i in range(m):
            acc = 0.0 if op <= 1 else 1.0 if op == 4 else b[i, 0]
            for j in range(n):
                x = b[i, j]
                if op <= 1:
                    acc += x
                elif op == 4:
                    acc *= x
                elif op == 2:
                    if np.isnan(x) or x > acc:
                        acc = x
                elif np.isnan(x) or x < acc:
                    acc = x
            out[i] = acc / n if op == 1 else acc
        return out
    return reduce


def _stub(names: str):
    """A new function that does nothing, with NumPy's reduction arguments (``a``, ``axis``, ``keepdims``) or
    torch's (``input``, ``dim``, ``keepdim``): each reduction's own, for its own numba overload."""
    if names == "torch":
        def stub(input, dim=None, keepdim=False):              # noqa: A002  (torch's own argument names)
            pass
    else:
        def stub(a, axis=None, keepdims=False):
            pass
    return stub


def _overload_of(typer, names: str):
    """The numba overload of a reduction stub: the implementation that ``typer`` gives for the argument types
    (None: numba's own), compiled, taking its arguments by the stub's names (``_stub``)."""
    njit = _numba().njit

    if names == "torch":
        def torch_overload(input, dim=None, keepdim=False):      # noqa: A002
            f = typer(input, dim, keepdim)
            if f is None:
                return None
            f = njit(f)

            def impl(input, dim=None, keepdim=False):            # noqa: A002
                return f(input, dim, keepdim)
            return impl
        return torch_overload

    def numpy_overload(a, axis=None, keepdims=False):
        f = typer(a, axis, keepdims)
        if f is None:
            return None
        f = njit(f)

        def impl(a, axis=None, keepdims=False):
            return f(a, axis, keepdims)
        return impl
    return numpy_overload


@functools.cache
def _reduction(op: int, names: str):
    """A reduction stub for compiled code, taking its arguments by the names NumPy's (``names='numpy'``: ``a``,
    ``axis``, ``keepdims``) or torch's (``'torch'``: ``input``, ``dim``, ``keepdim``) functions give them, with
    its numba overload: an axis and keepdims on float arrays of 1 or 2 dimensions (``_reduce``); otherwise
    numba's own."""
    from numba import types as nt
    from numba.extending import overload

    stub = _stub(names)
    plain = [np.sum, np.mean, np.max, np.min, np.prod][op]
    reduce = _reduce()

    def omitted(t) -> bool:                   # an omitted argument comes as its default (None), or as Omitted
        return t is None or isinstance(t, nt.NoneType) or isinstance(t, nt.Omitted) and t.value is None

    def literal(t, default):
        if omitted(t):
            return default
        if isinstance(t, bool):
            return t
        return t.value if isinstance(t, nt.Omitted) else getattr(t, "literal_value", None)

    def typer(arr, ax, keepdims):
        keepdims = literal(keepdims, False)
        whole = omitted(ax)
        if whole and keepdims is False:
            return lambda x, y, z: plain(x)
        if not isinstance(arr, nt.Array) or not isinstance(arr.dtype, nt.Float) or arr.ndim not in (1, 2) or \
                keepdims is not True and keepdims is not False:
            return None
        two = arr.ndim == 2
        if whole:
            return (lambda x, y, z: np.full((1, 1), plain(x))) if two else (lambda x, y, z: np.full(1, plain(x)))
        if not isinstance(ax, nt.Integer):
            return None
        if not two:
            return (lambda x, y, z: reduce(x, 0, op)) if keepdims else (lambda x, y, z: reduce(x, 0, op)[0])
        if not keepdims:
            return lambda x, y, z: reduce(x, y + 2 if y < 0 else y, op)

        def keep2(x, y, z):
            k = y + 2 if y < 0 else y
            r = reduce(x, k, op)
            return r.reshape((1, r.shape[0])) if k == 0 else r.reshape((r.shape[0], 1))
        return keep2

    overload(stub, prefer_literal=True)(_overload_of(typer, names))
    return stub


@functools.cache
def _numpy_functions() -> dict:
    """NumPy's joins by identity, with their stand-ins: ``from numpy import concatenate`` compiles too."""
    stand_in = _numpy_stand_in()
    return {getattr(np, name): getattr(stand_in, name) for name in _JOINS}


@functools.cache
def _torch_functions() -> dict:
    """torch's functions that have a stand-in, by identity: ``from torch import tanh`` compiles too."""
    stand_in = _torch_stand_in()
    return {getattr(torch, name): getattr(stand_in, name) for name in vars(stand_in)
            if not name.startswith("_") and callable(getattr(torch, name, None))}


def _with_helpers_jitted(fn, depth: int = 4):
    """A copy of ``fn`` whose plain Python helpers (functions it names as globals or closes over) are numba
    dispatchers, compiled the same way, so that a user's function may call functions of its own; ``torch`` and
    the torch functions it names are replaced by their NumPy stand-ins (``_torch_stand_in``), and NumPy's joins
    by ones that also take lists (``_numpy_stand_in``)."""

    import numba
    if not isinstance(fn, types.FunctionType) or depth == 0:
        return fn

    def ready(v):
        if v is torch:
            return _torch_stand_in()
        if v is np:
            return _numpy_stand_in()
        try:
            stand_in = _torch_functions().get(v) or _numpy_functions().get(v)
        except TypeError:                      # an unhashable value
            stand_in = None
        if stand_in is not None:
            return stand_in
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


def _compile(entry, reference, n_in: int, n_out: int, source: str, bind: dict, key: str | None,
             forms: tuple[str, ...] | None = None) -> Compiled:
    """Compile the wrappers of a module holding ``source`` with ``bind`` as globals and ``jfn = entry(module)``;
    the result must reproduce ``reference``. ``key`` names everything the code depends on (None: not known, so
    nothing is kept on disk); a module loaded from the disk cache that does not reproduce ``reference`` is
    compiled again without it. Raises ``NotLowerable`` with the last form's reason where none compiles and
    reproduces ``reference``."""
    try:
        numba = _numba()
    except ImportError:
        raise NotLowerable("numba is not installed (pip install numba)") from None
    reasons: list[str] = []
    for cached in ((True, False) if key is not None and cache_folder() is not None else (False,)):
        module = codegen.module(source, n_in, n_out, forms == ("member",), key if cached else None,
                                cache_folder() if cached else None)
        try:
            module.__dict__.update(bind)
            module.jfn = entry(module)
        except Exception as e:                # not a Python function numba can take
            raise NotLowerable(f"numba cannot take it: {_first_line(e)}") from None
        for form in forms or (["scalar"] if n_in == 1 and n_out == 1 else []) + ["array"]:
            try:
                cf = numba.cfunc(module.SIG, nopython=True, cache=cached)(getattr(module, form))
            except Exception as e:
                reasons.append(_first_line(e))
                continue
            mismatch = _check(reference, cf, n_in, n_out)
            if mismatch:
                reasons.append(mismatch)
                continue
            return Compiled(address=cf.address, owner=cf, form=form)
    raise NotLowerable(reasons[-1] if reasons else "no form compiled")


def cache_folder() -> Path | None:
    """Where compiled functions are kept between processes: ``$RCOTORCH_CACHE`` (``off``: nowhere), else
    ``$XDG_CACHE_HOME/rcotorch`` or ``~/.cache/rcotorch``; its ``compiled/`` folder, private to the user. A
    folder that others may write to is not used (its code would be loaded unchecked by numba before
    rcotorch's own check)."""
    root = os.environ.get("RCOTORCH_CACHE")
    if root == "off":
        return None
    if not root:
        root = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "rcotorch"
    folder = Path(root) / "compiled"
    try:
        folder.mkdir(parents=True, exist_ok=True, mode=0o700)
        st = folder.stat()
    except OSError:
        return None
    if st.st_uid != os.getuid() or st.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        return None
    return folder


def _fingerprint(fn, depth: int = 4) -> str | None:
    """A text naming everything ``fn``'s compiled code depends on (its code, constants, defaults, closure and
    the globals it reads, helper functions included), or None when a value has no stable description."""
    if not isinstance(fn, types.FunctionType) or depth == 0:
        return None
    parts = [fn.__module__ or "", fn.__qualname__, _code_text(fn.__code__), repr(fn.__defaults__)]
    values = [c.cell_contents for c in fn.__closure__ or () if _filled(c)]
    values += [fn.__globals__[k] for k in sorted(_names(fn.__code__)) if k in fn.__globals__]
    for v in values:
        if isinstance(v, types.FunctionType):
            inner = _fingerprint(v, depth - 1)
            if inner is None:
                return None
            parts.append(inner)
        elif isinstance(v, types.ModuleType):
            parts.append(f"module {v.__name__}")
        elif isinstance(v, np.ndarray):
            parts.append(f"array {v.dtype} {v.shape} {hashlib.sha256(np.ascontiguousarray(v).tobytes()).hexdigest()}")
        elif isinstance(v, (int, float, complex, str, bytes, bool, type(None))) or \
                (isinstance(v, tuple) and all(isinstance(t, (int, float, str, bool)) for t in v)):
            parts.append(f"{type(v).__name__} {v!r}")
        elif callable(v) and getattr(v, "__module__", "") and str(v.__module__).startswith(("numpy", "math")):
            parts.append(f"{v.__module__}.{getattr(v, '__qualname__', '')}")
        elif _is_torch_function(v):
            parts.append(f"torch.{v.__name__}")
        else:
            return None
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()


def _is_torch_function(v) -> bool:
    try:
        return v in _torch_functions()
    except TypeError:                          # an unhashable value
        return False


def _code_text(code) -> str:
    consts = [(_code_text(c) if isinstance(c, types.CodeType) else repr(c)) for c in code.co_consts]
    return f"{code.co_code.hex()} {consts} {code.co_names} {code.co_varnames}"


def _names(code) -> set[str]:
    """The global names a code object (and the code objects nested in it) reads."""
    names = set(code.co_names)
    for c in code.co_consts:
        if isinstance(c, types.CodeType):
            names |= _names(c)
    return names


def _filled(cell) -> bool:
    try:
        return cell.cell_contents is not _filled       # reading an empty cell raises
    except ValueError:
        return False


def _check(fn, cf, n_in: int, n_out: int) -> str | None:
    """None when the compiled function gives the function's own values on test inputs (called for one member
    and for all of them at once), else what differs."""
    import ctypes

    rng = np.random.default_rng(12345)
    x = np.concatenate([rng.standard_normal((PROBES - 8, n_in)) * 10.0 ** rng.integers(-3, 4, (PROBES - 8, 1)),
                        np.zeros((1, n_in)), np.full((1, n_in), 1.5), np.full((1, n_in), -1.5),
                        rng.uniform(-1, 1, (5, n_in))])
    try:
        with torch.no_grad(), np.errstate(all="ignore"):
            want = call_user(fn, torch.from_numpy(x))
    except Exception as e:                    # the function itself fails on these inputs
        return f"the function itself raised {type(e).__name__} on a batch of {len(x)}: {_first_line(e)}"
    want = want.detach().cpu().numpy() if isinstance(want, torch.Tensor) else np.asarray(want, dtype=float)
    if want.shape != (len(x), n_out):
        return f"it returns shape {want.shape} for a batch of {len(x)}, expected ({len(x)}, {n_out})"
    pd = ctypes.POINTER(ctypes.c_double)
    one = np.empty((len(x), n_out))
    # An exception inside a C function cannot propagate: Python reports it as unraisable and the function returns
    # what it had. Here that is a failed check (e.g. code from the disk cache that does not fit these sizes).
    raised: list[str] = []
    hook, sys.unraisablehook = sys.unraisablehook, lambda info: raised.append(f"{info.exc_type.__name__}: "
                                                                                  f"{info.exc_value}")
    try:
        for i in range(len(x)):
            xi, yi = np.ascontiguousarray(x[i]), np.empty(n_out)
            cf.ctypes(xi.ctypes.data_as(pd), yi.ctypes.data_as(pd), 1)
            one[i] = yi
        xs, ys = np.ascontiguousarray(x.T), np.empty((n_out, len(x)))
        cf.ctypes(xs.ctypes.data_as(pd), ys.ctypes.data_as(pd), len(x))
    finally:
        sys.unraisablehook = hook
    if raised:
        return f"the compiled code raised {raised[0]}"
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
