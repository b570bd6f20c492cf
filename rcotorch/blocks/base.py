"""The block protocol and the simple static blocks (gain, sum).

A block is an ``nn.Module`` with named input and output ports of fixed widths. Signals are batch-first
``(B, width)`` tensors. A step at time k runs in two phases so that a graph can order blocks by their
direct-feedthrough paths:

* ``output(port, inputs)`` returns the value of one output port at time k. ``inputs`` holds at least the
  input ports listed in ``feedthrough()[port]``.
* ``update(inputs)`` advances the block's state from k to k+1, given all of its inputs at time k.

``step(**inputs)`` does both for a block used on its own. State lives in registered buffers, created for a
batch size by ``reset(batch_size)``, so ``state_dict()`` checkpoints a block and ``.to()`` moves it.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch
from torch import nn

from ..engine.compiled import call_user
from ..errors import ConfigError, DimensionError, PortError

DEFAULT_DTYPE = torch.float64


def as_batched_matrix(value, name: str, block: str, dtype=DEFAULT_DTYPE, rows: int | None = None,
                      cols: int | None = None) -> torch.Tensor:
    """Return ``value`` as a ``(Bp, rows, cols)`` tensor: a matrix shared by the batch (Bp = 1) or one per member.

    A scalar becomes (1, 1, 1); a vector a row (1, 1, n), or a column (1, n, 1) where ``cols`` is 1 and ``rows``
    is not.

    Parameters
    ----------
    value : array_like
        A scalar, a vector, a matrix (rows, cols) or a batch of matrices (Bp, rows, cols).
    name : str
        The matrix's name, for error messages.
    block : str
        The block's name, for error messages.
    dtype : torch.dtype, optional
        Floating-point type of the result (float64 by default).
    rows, cols : int, optional
        The expected number of rows and columns; None accepts any.

    Returns
    -------
    torch.Tensor
        (Bp, rows, cols), on the CPU.

    Raises
    ------
    DimensionError
        If ``value`` has more than 3 dimensions or the wrong number of rows or columns.
    """
    t = torch.as_tensor(value, dtype=dtype, device="cpu")     # blocks are built on the CPU; the graph moves them
    if t.dim() == 0:
        t = t.reshape(1, 1, 1)
    elif t.dim() == 1:
        t = t.reshape(1, 1, -1) if rows == 1 else t.reshape(1, -1, 1) if cols == 1 else t.reshape(1, 1, -1)
    elif t.dim() == 2:
        t = t.unsqueeze(0)
    elif t.dim() != 3:
        raise DimensionError(f"block '{block}': {name} must be a matrix or a batch of matrices, got shape "
                             f"{tuple(t.shape)}")
    if (rows is not None and t.shape[1] != rows) or (cols is not None and t.shape[2] != cols):
        raise DimensionError(f"block '{block}': {name} has shape {tuple(t.shape[1:])}, expected "
                             f"({rows if rows is not None else '*'}, {cols if cols is not None else '*'})")
    return t


def first_bad(values: torch.Tensor, ok: torch.Tensor) -> str | None:
    """The first value of a setting that fails its check, for a message: ``'nan'`` for a setting of one value,
    ``'nan (member 2)'`` for one value per member; None where every value passes.

    Parameters
    ----------
    values : torch.Tensor
        The setting: one value, or one per member along the first axis.
    ok : torch.Tensor
        bool, of the shape of ``values``: which values pass.

    Returns
    -------
    str or None
    """
    bad = (~ok).reshape(values.shape[0] if values.dim() else 1, -1).any(1)
    if not bool(bad.any()):
        return None
    b = int(bad.nonzero()[0, 0])
    row = values.reshape(bad.shape[0], -1)[b]
    shown = float(row[~ok.reshape(bad.shape[0], -1)[b]][0])
    return f"{shown}" if bad.shape[0] == 1 else f"{shown} (member {b})"


def matvec(M: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``M x`` for a batch of vectors and a matrix shared by the batch or given per member.

    Parameters
    ----------
    M : torch.Tensor
        (1, m, n) shared by the batch, or (B, m, n) one per member.
    x : torch.Tensor
        (B, n).

    Returns
    -------
    torch.Tensor
        (B, m): row b is ``M[b] @ x[b]`` (``M[0] @ x[b]`` for a shared M).
    """
    if M.shape[0] == 1:
        return x @ M[0].mT
    return torch.bmm(M, x.unsqueeze(-1)).squeeze(-1)


class Block(nn.Module):
    """Base class of all blocks: an ``nn.Module`` with named input and output ports of fixed widths.

    Subclasses set ``inputs``/``outputs`` (port name -> width) and override ``output``, and ``update`` and
    ``reset`` if they hold state. Input ports listed in ``optional_inputs`` may be left unconnected.

    Parameters
    ----------
    name : str
        The block's name, an identifier (letters, digits, '_'); a graph's connections and every error name the
        block by it.
    inputs : Mapping[str, int]
        Input port name -> width.
    outputs : Mapping[str, int]
        Output port name -> width.

    Raises
    ------
    ConfigError
        If ``name`` is not an identifier.
    DimensionError
        If a port's width is not a positive integer.

    Shape
    -----
    B is the batch size set by ``reset(B)``.

    - Input port ``p``: (B, inputs[p]).
    - Output port ``q``: (B, outputs[q]).
    """

    def __init__(self, name: str, inputs: Mapping[str, int], outputs: Mapping[str, int]):
        super().__init__()
        if not isinstance(name, str) or not name.isidentifier():
            raise ConfigError(f"block name {name!r} must be an identifier (letters, digits, '_')")
        self.name = name
        self.inputs = dict(inputs)
        self.outputs = dict(outputs)
        for kind, ports in (("input", self.inputs), ("output", self.outputs)):
            for port, width in ports.items():
                if not isinstance(width, int) or width < 1:
                    raise DimensionError(f"block '{name}': {kind} port '{port}' has width {width!r}, "
                                         "expected a positive integer")
        self.batch_size = 0
        self.optional_inputs: set[str] = set()

    # --- protocol -------------------------------------------------------------------------------------
    def feedthrough(self) -> dict[str, tuple[str, ...]]:
        """The input ports each output port depends on at the same time step.

        A graph orders the blocks of a step by these direct-feedthrough paths; a cycle of them is an
        algebraic loop.

        Returns
        -------
        dict[str, tuple[str, ...]]
            Output port -> the input ports its value at time k reads (by default: all of them).
        """
        return {port: tuple(self.inputs) for port in self.outputs}

    def reset(self, batch_size: int) -> None:
        """Create or zero the state for ``batch_size`` parallel members (time k = 0).

        Parameters
        ----------
        batch_size : int
            B, the number of members run side by side.

        Raises
        ------
        ConfigError
            If ``batch_size`` is not positive.
        DimensionError
            If a per-member parameter is given for another number of members (subclasses).
        """
        if batch_size < 1:
            raise ConfigError(f"block '{self.name}': batch size must be positive, got {batch_size}")
        self.batch_size = batch_size

    def output(self, port: str, inputs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """The value of one output port at time k; the state does not change.

        Parameters
        ----------
        port : str
            The output port.
        inputs : Mapping[str, torch.Tensor]
            Input port -> its value at time k, (B, width); holds at least the ports in
            ``feedthrough()[port]``.

        Returns
        -------
        torch.Tensor
            (B, outputs[port]).
        """
        raise NotImplementedError

    def update(self, inputs: Mapping[str, torch.Tensor]) -> None:
        """Advance the state from time k to k + 1 (stateless blocks do nothing).

        Parameters
        ----------
        inputs : Mapping[str, torch.Tensor]
            Every connected input port -> its value at time k, (B, width).
        """

    # The block's native form: ``lower(b)`` describes the block to the native engine through a
    # ``rcotorch.engine.lowering.Builder`` (its state buffers, parameters and ports, and the instructions that compute
    # its outputs and update it). None: no native form, and a graph holding the block runs on PyTorch.
    lower = None

    def _user_functions(self) -> dict:
        """The user's own functions the block calls, by the argument that gave each (``fn``, ``f``, ``h``): how an
        exception raised inside compiled code, which reaches Python with a function's name only, is traced to
        the block. None by default."""
        return {}

    def set_state(self, **tensors: torch.Tensor) -> None:
        """Replace registered buffers (state) without nn.Module's per-assignment bookkeeping.

        Parameters
        ----------
        **tensors : torch.Tensor
            Buffer name -> its new value.
        """
        self._buffers.update(tensors)

    # --- helpers --------------------------------------------------------------------------------------
    @property
    def dtype(self) -> torch.dtype:
        """The floating-point type of the block's buffers (float64 for a block without one)."""
        for t in self.buffers():
            if t.is_floating_point():
                return t.dtype
        return DEFAULT_DTYPE

    @property
    def device(self) -> torch.device:
        """The device of the block's buffers (the CPU for a block without one)."""
        for t in self.buffers():
            return t.device
        return torch.device("cpu")

    def check_batch(self, t: torch.Tensor, what: str) -> None:
        """Check that a per-member parameter has a leading size of 1 (shared) or the batch size.

        Parameters
        ----------
        t : torch.Tensor
            The parameter, (1, ...) or (B, ...).
        what : str
            Its name, for the error message.

        Raises
        ------
        DimensionError
            If the leading size is neither 1 nor the batch size.
        """
        if self.batch_size and t.shape[0] not in (1, self.batch_size):
            raise DimensionError(f"block '{self.name}': {what} is given for {t.shape[0]} members, but the "
                                 f"batch has {self.batch_size}")

    def check_inputs(self, inputs: Mapping[str, torch.Tensor]) -> None:
        """Check that the given inputs are ports of the block, of shape (B, width) and of the block's dtype.

        Parameters
        ----------
        inputs : Mapping[str, torch.Tensor]
            Input port -> value.

        Raises
        ------
        PortError
            If a name is not an input port of the block.
        DimensionError
            If a value has the wrong shape or floating-point type.
        """
        unknown = set(inputs) - set(self.inputs)
        if unknown:
            raise PortError(f"block '{self.name}' has no input port(s) {sorted(unknown)}; "
                            f"its inputs are {list(self.inputs)}")
        for port, value in inputs.items():
            want = (self.batch_size, self.inputs[port])
            if tuple(value.shape) != want:
                raise DimensionError(f"block '{self.name}', input '{port}': expected shape {want} "
                                     f"(batch, width), got {tuple(value.shape)}")
            own = next((t.dtype for t in self.buffers() if t.is_floating_point()), value.dtype)
            if value.is_floating_point() and value.dtype != own:
                raise DimensionError(f"block '{self.name}', input '{port}': dtype {value.dtype} differs from "
                                     f"the block's {own}")

    def step(self, **inputs: torch.Tensor) -> dict[str, torch.Tensor]:
        """Compute every output at time k, then advance to k + 1. For a block used on its own.

        Parameters
        ----------
        **inputs : torch.Tensor
            Input port -> its value at time k, (B, width); every port but the optional ones.

        Returns
        -------
        dict[str, torch.Tensor]
            Output port -> its value at time k, (B, width).

        Raises
        ------
        ConfigError
            If ``reset`` has not been called.
        PortError
            If an input is missing or names no input port.
        DimensionError
            If an input has the wrong shape or type.
        """
        if not self.batch_size:
            raise ConfigError(f"block '{self.name}': call reset(batch_size) before step()")
        self.check_inputs(inputs)
        missing = set(self.inputs) - set(inputs) - self.optional_inputs
        if missing:
            raise PortError(f"block '{self.name}': step() is missing input(s) {sorted(missing)}")
        out = {port: self.output(port, inputs) for port in self.outputs}
        self.update(inputs)
        return out

    def extra_repr(self) -> str:
        ins = ", ".join(f"{p}[{w}]" for p, w in self.inputs.items())
        outs = ", ".join(f"{p}[{w}]" for p, w in self.outputs.items())
        return f"name={self.name!r}, inputs=({ins}), outputs=({outs})"


class Gain(Block):
    """Static gain ``out = K in``.

    Parameters
    ----------
    K : array_like
        The gain, (m, n) shared by the batch or (B, m, n) one per member; a scalar is (1, 1), a vector a row
        (1, n).
    name : str, optional
        The block's name.
    dtype : torch.dtype, optional
        Floating-point type (float64 by default).

    Raises
    ------
    DimensionError
        If ``K`` has more than 3 dimensions.

    Shape
    -----
    - Input ``in``: (B, n).
    - Output ``out``: (B, m).
    """

    def __init__(self, K, name: str = "gain", dtype=DEFAULT_DTYPE):
        K = as_batched_matrix(K, "K", name, dtype)
        super().__init__(name, {"in": K.shape[2]}, {"out": K.shape[1]})
        self.register_buffer("K", K)

    def reset(self, batch_size: int) -> None:
        super().reset(batch_size)
        self.check_batch(self.K, "K")

    def output(self, port, inputs):
        return matvec(self.K, inputs["in"])

    def lower(self, b) -> None:
        """Describe the block to the native engine: one ``GAIN`` instruction computes ``out``.

        Parameters
        ----------
        b : rcotorch.engine.lowering.Builder
            Receives the block's parameters, ports and instructions.
        """
        shared = b.shared(self.K)
        b.emit("GAIN", port="out", ROWS=self.K.shape[1], COLS=self.K.shape[2],
               K=b.param(self.K, first_lane=bool(shared)), IN=b.input("in"), OUT=b.output("out"), SHARED=shared)


class Sum(Block):
    """Summing junction ``out = sum_i sign_i in_i``, e.g. ``Sum({'y': 1, 'y_hat': -1}, 1)`` for z = y - y_hat.

    Parameters
    ----------
    signs : Mapping[str, float]
        Input port name -> its sign, +1 or -1.
    width : int
        The width of every port.
    name : str, optional
        The block's name.

    Raises
    ------
    ConfigError
        If a sign is not +1 or -1.

    Shape
    -----
    - Inputs: one per key of ``signs``, each (B, width).
    - Output ``out``: (B, width).
    """

    def __init__(self, signs: Mapping[str, float], width: int, name: str = "sum"):
        super().__init__(name, {p: width for p in signs}, {"out": width})
        for port, s in signs.items():
            if s not in (1, -1):
                raise ConfigError(f"block '{name}': sign of input '{port}' must be +1 or -1, got {s!r}")
        self.signs = dict(signs)

    def output(self, port, inputs):
        total = None
        for p, s in self.signs.items():
            v = inputs[p] if s == 1 else -inputs[p]
            total = v if total is None else total + v
        return total

    def lower(self, b) -> None:
        """Describe the block to the native engine: one ``SUM`` instruction computes ``out``.

        Parameters
        ----------
        b : rcotorch.engine.lowering.Builder
            Receives the block's ports and instructions.
        """
        b.emit("SUM", port="out", WIDTH=self.outputs["out"], OUT=b.output("out"),
               terms=[dict(IN=b.input(p), SIGN=int(s)) for p, s in self.signs.items()])


class StaticMap(Block):
    """Memoryless map ``out = fn(in)`` for a user function of a (B, n) array returning (B, m), e.g. a cubic
    spring ``lambda q: -k3 * q**3``, a friction law ``lambda v: -(2 * np.sign(v) + 0.5 * v)`` or a saturation
    ``lambda x: x.clamp(-1, 1)``. The function is probed with batches of 1, 2 and 3 when the block is built, so a
    wrong shape, or a map that mixes the members of the batch, fails here, not in the middle of a run.

    Written with NumPy, ``math`` or torch's functions (``torch.tanh``, ``torch.clamp``, ...), ``fn`` runs compiled in
    the native engine (``rcotorch.engine.compiled``: numba); the PyTorch engine calls it with tensors (a NumPy
    result is taken back as a tensor, on the CPU). Written with tensor methods (``x.clamp(-1, 1)``), it runs on
    the PyTorch engine, on the CPU or a GPU.

    Parameters
    ----------
    fn : callable
        Maps a (B, in_width) array to (B, m), treating the rows (batch members) independently.
    in_width : int
        n, the width of the input port.
    name : str, optional
        The block's name.
    dtype : torch.dtype, optional
        Floating-point type of the probes and of the result (float64 by default).

    Raises
    ------
    ConfigError
        If ``fn`` is not callable, raises on the probes, or mixes the members of a batch (member b's output must
        depend on member b's input only; a function that is not reproducible, one drawing random numbers, is not
        probed for this). During a run, an exception of ``fn`` is raised as a ConfigError that names the block,
        on either engine.
    DimensionError
        If ``fn`` does not return a (B, m) array, or m changes with the batch size.

    Shape
    -----
    - Input ``in``: (B, in_width).
    - Output ``out``: (B, m), m the width ``fn`` returns.
    """

    def __init__(self, fn, in_width: int, name: str = "map", dtype=DEFAULT_DTYPE):
        if not callable(fn):
            raise ConfigError(f"block '{name}': fn must be callable")
        widths = []
        for B in (1, 2):
            try:
                with np.errstate(all="ignore"):            # random inputs: a sqrt of a negative is no fault
                    out = tensor_result(call_user(fn, torch.randn(B, in_width, dtype=dtype)), dtype)
            except Exception as e:                          # the user's function failed on well-formed inputs
                raise ConfigError(f"block '{name}': fn failed on an input ({B}, {in_width}): {e!r}") from e
            if not isinstance(out, torch.Tensor) or out.dim() != 2 or out.shape[0] != B:
                got = tuple(out.shape) if isinstance(out, torch.Tensor) else type(out).__name__
                hint = "; return one value per member as a column, v[:, 0:1] rather than v[:, 0]" \
                    if isinstance(out, torch.Tensor) and out.dim() == 1 and out.shape[0] == B else ""
                raise DimensionError(f"block '{name}': fn must map a (batch, {in_width}) tensor to (batch, m); "
                                     f"for batch {B} it returned {got}{hint}")
            widths.append(out.shape[1])
        if widths[0] != widths[1]:
            raise DimensionError(f"block '{name}': fn's output width changes with the batch size")
        _check_members_apart(fn, in_width, name, dtype)
        super().__init__(name, {"in": in_width}, {"out": widths[0]})
        self.fn = fn

    def _user_functions(self) -> dict:
        return {"fn": self.fn}

    def output(self, port, inputs):
        """``fn`` of the input at time k.

        Parameters
        ----------
        port : str
            The output port, ``'out'``.
        inputs : Mapping[str, torch.Tensor]
            ``'in'`` -> (B, in_width).

        Returns
        -------
        torch.Tensor
            (B, m).

        Raises
        ------
        ConfigError
            If ``fn`` raises (its exception is the cause).
        """
        x = inputs["in"]
        try:
            out = call_user(self.fn, x)
        except (MemoryError, torch.OutOfMemoryError):
            raise
        except Exception as e:
            raise ConfigError(f"block '{self.name}': fn raised {type(e).__name__}: {e} on an input "
                              f"{tuple(x.shape)}") from e
        return tensor_result(out, x.dtype, x.device)

    def lower(self, b) -> None:
        """The native form: ``fn`` compiled by numba (``rcotorch.engine.compiled``) and called once per chunk of
        members and step; a function that does not compile keeps the graph on PyTorch, and the reason says
        why.

        Parameters
        ----------
        b : rcotorch.engine.lowering.Builder
            Receives the compiled function, the ports and the ``CALL`` instruction.
        """
        from ..engine.compiled import compile_map, describe
        from ..engine.lowering import NotLowerable
        n_in, n_out = self.inputs["in"], self.outputs["out"]
        try:
            c = compile_map(self.fn, n_in, n_out)
        except NotLowerable as e:
            b.refuse(f"function {describe(self.fn)} is not compiled: {e}")
        b.emit("CALL", port="out", NIN=n_in, IN=b.input("in"), NOUT=n_out, OUT=b.output("out"),
               FUNCTION=b.function(c.address, c))


def _check_members_apart(fn, width: int, name: str, dtype) -> None:
    """Refuse a map that mixes the members of a batch (its mean over the batch, a running sum along it): member
    b's output must depend on member b's input only. Probed with a batch of 3 and the same batch with its middle
    member's input changed; a function that does not give the same result twice for the same input (one that
    draws random numbers) cannot be probed so, and is accepted."""
    gen = torch.Generator().manual_seed(1)
    x = torch.randn(3, width, generator=gen, dtype=dtype)
    moved = x.clone()
    moved[1] += 1.0 + torch.rand(width, generator=gen, dtype=dtype)
    outs = []
    for v in (x, x, moved):
        try:
            with np.errstate(all="ignore"):
                out = tensor_result(call_user(fn, v.clone()), dtype)
        except Exception as e:
            raise ConfigError(f"block '{name}': fn failed on an input (3, {width}): {e!r}") from e
        if not isinstance(out, torch.Tensor) or out.dim() != 2 or out.shape[0] != 3:
            got = tuple(out.shape) if isinstance(out, torch.Tensor) else type(out).__name__
            raise DimensionError(f"block '{name}': fn must map a (batch, {width}) tensor to (batch, m); for batch 3 "
                                 f"it returned {got}")
        outs.append(out.detach().to(torch.float64))
    first, again, after = outs
    finite = first[torch.isfinite(first)]
    tol = 1e-12 * max(1.0, float(finite.abs().max()) if finite.numel() else 1.0)
    if not torch.isclose(again, first, rtol=1e-9, atol=tol, equal_nan=True).all():
        return
    for j in (0, 2):
        if not torch.isclose(after[j], first[j], rtol=1e-9, atol=tol, equal_nan=True).all():
            raise ConfigError(f"block '{name}': fn must treat each member (row of the batch) on its own: changing "
                              f"member 1's input moved member {j}'s output (a function of the whole batch, such as "
                              "its mean or a sum over axis 0, mixes the members)")


def tensor_result(out, dtype, device=None):
    """A user function's result as a tensor.

    A NumPy array (a function written with NumPy, called by the PyTorch engine with CPU tensors) becomes one;
    a tensor is returned as it is, on ``device`` where one is given.

    Parameters
    ----------
    out : torch.Tensor or numpy.ndarray
        The function's result.
    dtype : torch.dtype
        Floating-point type of a converted array.
    device : torch.device, optional
        Device of the result: a converted array's (the CPU by default); a tensor is moved there.

    Returns
    -------
    torch.Tensor
    """
    if isinstance(out, np.ndarray):
        return torch.as_tensor(out, dtype=dtype, device=device)
    return out if device is None or not isinstance(out, torch.Tensor) else out.to(device)
