"""Linear time-invariant blocks: discrete state space, and continuous systems discretized by zero-order hold.

    x(k+1) = A x(k) + B u(k)
    y(k)   = C x(k) + D u(k)

u stacks the input ports in the order given, y the output ports. Each matrix is shared by the batch or
given per member (leading batch dimension), so a sweep over physical parameters is one batched block.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np
import torch

from ..engine import memo
from ..errors import ConfigError, DimensionError
from .base import DEFAULT_DTYPE, Block, as_batched_matrix, matvec

if TYPE_CHECKING:
    import control


def _ports(spec, total: int, what: str, name: str) -> dict[str, int]:
    """Port layout from a mapping name -> width, or a list of names of width 1."""
    if isinstance(spec, str):
        spec = [spec]
    ports = dict(spec) if isinstance(spec, Mapping) else {p: 1 for p in spec}
    if sum(ports.values()) != total:
        raise DimensionError(f"block '{name}': {what} ports {ports} have total width {sum(ports.values())}, "
                             f"but the system has {total} {what}s")
    return ports


def zoh(A, B, dt: float, dtype=DEFAULT_DTYPE) -> tuple[torch.Tensor, torch.Tensor]:
    """Zero-order-hold discretization of (A, B), batched: exp([[A, B], [0, 0]] dt) = [[Ad, Bd], [0, I]].

    Members with equal matrices share one matrix exponential.

    Parameters
    ----------
    A : array_like
        Continuous state matrix, (n, n) or batched (..., n, n).
    B : array_like
        Continuous input matrix, (n, m) or batched (..., n, m); its batch dimensions broadcast with A's.
    dt : float
        Sample time [s].
    dtype : torch.dtype, optional
        Floating-point type (float64 by default).

    Returns
    -------
    Ad : torch.Tensor
        (..., n, n), the discrete state matrix exp(A dt).
    Bd : torch.Tensor
        (..., n, m), the discrete input matrix (integral of exp(A s) ds over [0, dt]) B.
    """
    A = torch.as_tensor(A, dtype=dtype)
    B = torch.as_tensor(B, dtype=dtype)
    n, m = A.shape[-1], B.shape[-1]
    batch = np.broadcast_shapes(tuple(A.shape[:-2]), tuple(B.shape[:-2]))   # (torch's imports sympy)
    M = torch.zeros(*batch, n + m, n + m, dtype=dtype)
    M[..., :n, :n] = A
    M[..., :n, n:] = B
    M = M * dt
    if M[..., 0, 0].numel() > 1:                   # members that share their physics: one exponential each
        flat = M.reshape(-1, (n + m) ** 2)
        if bool((flat == flat[0]).all()):
            unique, index = flat[:1], torch.zeros(flat.shape[0], dtype=torch.long)
        else:
            unique, index = torch.unique(flat, dim=0, return_inverse=True)
        E = torch.linalg.matrix_exp(unique.reshape(-1, n + m, n + m))[index].reshape(M.shape)
    else:
        E = torch.linalg.matrix_exp(M)
    return E[..., :n, :n], E[..., :n, n:]


def _check_dt(dt, name: str) -> None:
    """Refuse a sample time that is not a finite positive number."""
    try:
        value = None if isinstance(dt, (str, bytes)) else float(dt)
    except (TypeError, ValueError):
        value = None
    if value is None or not np.isfinite(value) or value <= 0:
        raise ConfigError(f"block '{name}': dt must be a positive sample time, got {dt!r}")


def _check_finite(M: torch.Tensor, key: str, name: str) -> None:
    """Refuse a matrix (shared, (1, rows, cols), or one per member) or an initial state (1 or B, n) that holds a
    NaN or an infinity: the message gives the first such entry, and its member where there is one per member."""
    bad = ~torch.isfinite(M)
    if not bool(bad.any()):
        return
    at = bad.nonzero()[0].tolist()
    where = f"({', '.join(str(i) for i in at[1:])})" + (f" of member {at[0]}" if M.shape[0] > 1 else "")
    raise ConfigError(f"block '{name}': {key} must be finite; it has {float(M[tuple(at)])} at {where}")


class LTI(Block):
    """Discrete LTI block with named input and output ports.

    x(k+1) = A x(k) + B u(k), y(k) = C x(k) + D u(k), where u stacks the input ports in the order given and y
    the output ports. An output port depends on an input port at the same step only where D's block for the
    pair is nonzero (``feedthrough``).

    Parameters
    ----------
    A, B, C, D : array_like
        State-space matrices, each (rows, cols) shared by the batch or (B, rows, cols) one per member.
    inputs : Mapping[str, int] or list of str
        Port name -> width (or a list of width-1 names), in the column order of B and D.
    outputs : Mapping[str, int] or list of str
        Port name -> width (or a list of width-1 names), in the row order of C and D.
    dt : float
        Sample time in seconds (recorded; the block steps once per sample).
    name : str, optional
        The block's name.
    x0 : array_like, optional
        Initial state (n,) or (B, n); zero by default.
    dtype : torch.dtype, optional
        Floating-point type (float64 by default).

    Raises
    ------
    DimensionError
        If A is not square, the matrices do not fit together, or the ports' widths do not add up to the
        columns of B (inputs) or the rows of C (outputs).
    ConfigError
        If ``dt`` is not a positive number, or a matrix or ``x0`` holds a NaN or an infinity.

    Shape
    -----
    - Inputs: one per entry of ``inputs``, (B, width); together u, (B, m) with m the columns of B.
    - Outputs: one per entry of ``outputs``, (B, width); together y, (B, p) with p the rows of C.
    - State ``x``: (B, n).
    """

    def __init__(self, A, B, C, D, inputs, outputs, dt: float, name: str = "lti", x0=None,
                 dtype=DEFAULT_DTYPE):
        A = as_batched_matrix(A, "A", name, dtype)
        n = A.shape[-1]
        if A.shape[1] != n:
            raise DimensionError(f"block '{name}': A must be square, got shape {tuple(A.shape[1:])}")
        B = as_batched_matrix(B, "B", name, dtype, rows=n)
        C = as_batched_matrix(C, "C", name, dtype, cols=n)
        D = as_batched_matrix(D, "D", name, dtype, rows=C.shape[1], cols=B.shape[2])
        super().__init__(name, _ports(inputs, B.shape[2], "input", name),
                         _ports(outputs, C.shape[1], "output", name))
        _check_dt(dt, name)
        self.dt = float(dt)
        self.n_states = n
        for key, M in (("A", A), ("B", B), ("C", C), ("D", D)):
            _check_finite(M, key, name)
            self.register_buffer(key, M)
        x0 = torch.zeros(1, n, dtype=dtype) if x0 is None else \
            torch.as_tensor(x0, dtype=dtype, device="cpu").reshape(-1, n)
        _check_finite(x0, "x0", name)
        self.register_buffer("x0", x0)
        self.register_buffer("x", torch.zeros(0, n, dtype=dtype))
        self._in_slices = self._slices(self.inputs)
        self._out_slices = self._slices(self.outputs)
        # Structural feedthrough: input p reaches output q at once where D's (q, p) block is nonzero.
        self._feedthrough = {
            q: tuple(p for p, cs in self._in_slices.items() if bool(D[:, rs, cs].abs().amax() > 0))
            for q, rs in self._out_slices.items()}

    @staticmethod
    def _slices(ports: Mapping[str, int]) -> dict[str, slice]:
        out, start = {}, 0
        for p, w in ports.items():
            out[p] = slice(start, start + w)
            start += w
        return out

    # --- constructors ---------------------------------------------------------------------------------
    @classmethod
    def from_control(cls, sys, inputs, outputs, dt: float | None = None, name: str = "lti", x0=None,
                     dtype=DEFAULT_DTYPE) -> LTI:
        """An LTI block from a python-control ``StateSpace`` or ``TransferFunction``.

        A continuous system is discretized by zero-order hold at ``dt``; a discrete one keeps its own sample
        time (``dt`` must agree).

        Parameters
        ----------
        sys : control.StateSpace or control.TransferFunction
            The system.
        inputs, outputs : Mapping[str, int] or list of str
            Port layouts, as for ``LTI``.
        dt : float, optional
            Sample time [s]; required for a continuous system.
        name : str, optional
            The block's name.
        x0 : array_like, optional
            Initial state (n,) or (B, n); zero by default.
        dtype : torch.dtype, optional
            Floating-point type (float64 by default).

        Returns
        -------
        LTI

        Raises
        ------
        ConfigError
            If ``sys`` is of another type, a continuous system has no ``dt``, or a discrete system's sample time
            differs from ``dt``.
        """
        import control
        if isinstance(sys, control.TransferFunction):
            sys = control.tf2ss(sys)
        continuous = None
        if not isinstance(sys, control.StateSpace):
            raise ConfigError(f"block '{name}': expected a control.StateSpace or TransferFunction, "
                              f"got {type(sys).__name__}")
        if sys.isctime(strict=True):
            if dt is None:
                raise ConfigError(f"block '{name}': a continuous system needs dt for its ZOH discretization")
            continuous, sys = sys, control.sample_system(sys, dt, method="zoh")
        elif sys.dt not in (None, True) and dt is not None and not np.isclose(sys.dt, dt):
            raise ConfigError(f"block '{name}': system sample time {sys.dt} differs from dt={dt}")
        dt = dt if dt is not None else sys.dt
        block = cls(sys.A, sys.B, sys.C, sys.D, inputs, outputs, dt, name=name, x0=x0, dtype=dtype)
        if continuous is not None:
            block.set_continuous(continuous.A, continuous.B)
        return block

    @classmethod
    def continuous(cls, A, B, C, D, inputs, outputs, dt: float, name: str = "lti", x0=None,
                   dtype=DEFAULT_DTYPE) -> LTI:
        """An LTI block from continuous matrices (shared or per member), ZOH-discretized in torch at ``dt``.

        Parameters
        ----------
        A, B, C, D : array_like
            Continuous state-space matrices, each (rows, cols) or (B, rows, cols).
        inputs, outputs : Mapping[str, int] or list of str
            Port layouts, as for ``LTI``.
        dt : float
            Sample time [s].
        name : str, optional
            The block's name.
        x0 : array_like, optional
            Initial state (n,) or (B, n); zero by default.
        dtype : torch.dtype, optional
            Floating-point type (float64 by default).

        Returns
        -------
        LTI

        Raises
        ------
        ConfigError
            If ``dt`` is not a positive number, or a matrix holds a NaN or an infinity.
        """
        _check_dt(dt, name)
        A = as_batched_matrix(A, "A", name, dtype)
        B = as_batched_matrix(B, "B", name, dtype, rows=A.shape[-1])
        _check_finite(A, "A (continuous)", name)
        _check_finite(B, "B (continuous)", name)
        Ad, Bd = zoh(A, B, dt, dtype)
        block = cls(Ad, Bd, C, D, inputs, outputs, dt, name=name, x0=x0, dtype=dtype)
        block.set_continuous(A, B)
        return block

    def set_continuous(self, A, B) -> None:
        """Record that the block samples a continuous system x' = A x + B u (its A and B discretized by
        zero-order hold at ``dt``; C and D shared): a feedback that acts on it continuously can then be simulated
        between the samples (``continuous_form``). The constructors from continuous systems call this.

        Parameters
        ----------
        A, B : array_like
            Continuous state-space matrices, (n, n) and (n, m) or batched (B, ...).

        Raises
        ------
        DimensionError
            If A or B does not have the shape of the block's discrete A or B.
        """
        A = as_batched_matrix(A, "A (continuous)", self.name, self.A.dtype)
        B = as_batched_matrix(B, "B (continuous)", self.name, self.A.dtype, rows=self.n_states)
        if A.shape[1:] != self.A.shape[1:] or B.shape[1:] != self.B.shape[1:]:
            raise DimensionError(f"block '{self.name}': continuous A {tuple(A.shape[1:])} and B {tuple(B.shape[1:])} "
                                 f"must have the shapes of the discrete ones, {tuple(self.A.shape[1:])} and "
                                 f"{tuple(self.B.shape[1:])}")
        self.register_buffer("A_c", A.to(self.A.device), persistent=False)
        self.register_buffer("B_c", B.to(self.A.device), persistent=False)

    def continuous_form(self) -> tuple[torch.Tensor, torch.Tensor] | None:
        """The continuous system this block samples.

        Returns
        -------
        tuple of torch.Tensor or None
            (A, B), each (1 or B, rows, cols), or None for a block built from a discrete system.
        """
        A, B = getattr(self, "A_c", None), getattr(self, "B_c", None)
        return None if A is None else (A, B)

    # --- block protocol -------------------------------------------------------------------------------
    def feedthrough(self):
        return dict(self._feedthrough)

    def reset(self, batch_size: int) -> None:
        super().reset(batch_size)
        for key in ("A", "B", "C", "D", "x0"):
            self.check_batch(getattr(self, key), key)
        self.x = self.x0.expand(batch_size, -1).clone()

    def output(self, port, inputs):
        rows = self._out_slices[port]
        y = memo.derived(self, "Cx", (self.C, self.x), lambda: matvec(self.C, self.x))[:, rows]  # C x, all ports
        for p in self._feedthrough[port]:
            y = y + matvec(self.D[:, rows, self._in_slices[p]], inputs[p])
        return y

    def update(self, inputs):
        if self.A.shape[0] == 1 and self.B.shape[0] == 1:
            # Shared matrices: x(k+1) = [x, u_1, u_2, ...] [A B]^T in one product.
            AB_t = memo.derived(self, "AB_t", (self.A, self.B), lambda: torch.cat([self.A[0], self.B[0]], 1).mT)
            x = torch.cat([self.x] + [inputs[p] for p in self._in_slices], dim=1) @ AB_t
        else:
            x = matvec(self.A, self.x)
            for p, cs in self._in_slices.items():
                x = x + matvec(self.B[:, :, cs], inputs[p])
        self.set_state(x=x)

    def lower(self, b) -> None:
        """Describe the block to the native engine: an ``LTI_OUT`` instruction per output port (C x plus the
        feedthrough columns of D u) and one ``LTI_UPD`` (x <- A x + B u).

        Parameters
        ----------
        b : rcotorch.engine.lowering.Builder
            Receives the block's state, parameters, ports and instructions.
        """
        n, mt = self.n_states, self.B.shape[2]
        x, shared = b.state("x"), b.shared(self.A, self.B, self.C, self.D)
        C, D = b.param(self.C, first_lane=bool(shared)), None
        for port, rows in self._out_slices.items():
            ft = [p for p in self._feedthrough[port] if b.input(p) is not None]
            if ft and D is None:
                D = b.param(self.D, first_lane=bool(shared))
            cols = [(c, b.input(p) + c - self._in_slices[p].start)   # each feedthrough column and its slot
                    for p in ft for c in range(self._in_slices[p].start, self._in_slices[p].stop)]
            b.emit("LTI_OUT", port=port, NX=n, ROWS=rows.stop - rows.start, C=C + rows.start * n, STATE=x,
                   OUT=b.output(port), MT=mt, D=(0 if D is None else D) + rows.start * mt, SHARED=shared,
                   feedthrough=[dict(COLUMN=c, IN=slot) for c, slot in cols])
        inputs = [b.input(p) + i for p, cs in self._in_slices.items()   # the input columns in order: their slots
                  for i in range(cs.stop - cs.start)]
        b.emit("LTI_UPD", NX=n, MT=mt, A=b.param(self.A, first_lane=bool(shared)),
               B=b.param(self.B, first_lane=bool(shared)), STATE=x, SCRATCH=b.scratch(n),
               SHARED=shared, inputs=inputs)

    # --- analysis -------------------------------------------------------------------------------------
    def markov(self, input: str, output: str, n: int) -> torch.Tensor:
        """Markov parameters H_0 = D, H_i = C A^(i-1) B of the map ``input -> output``, i = 0..n-1.

        They are the impulse response of the discrete system from one input port to one output port.

        Parameters
        ----------
        input : str
            The input port.
        output : str
            The output port.
        n : int
            The number of Markov parameters.

        Returns
        -------
        torch.Tensor
            (Bp, n, rows, cols): Bp is 1 where the matrices are shared, else the batch; rows is the output
            port's width, cols the input port's.

        Raises
        ------
        ConfigError
            If the block has no such input or output port.
        """
        for p, ports, kind in ((input, self._in_slices, "input"), (output, self._out_slices, "output")):
            if p not in ports:
                raise ConfigError(f"block '{self.name}' has no {kind} port '{p}'; its {kind}s are {list(ports)}")
        cs, rs = self._in_slices[input], self._out_slices[output]
        A, B, C = self.A, self.B[:, :, cs], self.C[:, rs]
        Bp = max(A.shape[0], B.shape[0], C.shape[0])
        H = [self.D[:, rs, cs].expand(Bp, -1, -1)]
        AkB = B.expand(Bp, -1, -1)
        for _ in range(1, n):
            H.append(C @ AkB)
            AkB = A @ AkB
        return torch.stack(H[:n], dim=1)

    def to_control(self, member: int = 0) -> control.StateSpace:
        """The discrete system of one batch member as a python-control ``StateSpace`` with its dt.

        Parameters
        ----------
        member : int, optional
            The batch member (its matrices, or the shared ones).

        Returns
        -------
        control.StateSpace
            Its signals named after the ports (``p[i]`` for the columns of a port wider than 1).
        """
        import control
        A, B, C, D = (M[member if M.shape[0] > 1 else 0].detach().cpu().numpy()
                      for M in (self.A, self.B, self.C, self.D))
        return control.ss(A, B, C, D, self.dt,
                          inputs=[f"{p}[{i}]" if w > 1 else p for p, w in self.inputs.items() for i in range(w)],
                          outputs=[f"{p}[{i}]" if w > 1 else p for p, w in self.outputs.items() for i in range(w)])
