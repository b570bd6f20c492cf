"""Nonlinear state-space blocks and their Markov parameters by linearization.

    x(k+1) = f(x(k), inputs(k))               (discrete map), or
    x'(t)  = f(x(t), inputs(k)),  t in [k dt, (k+1) dt)   (continuous, fixed-step RK4, inputs held)
    y(k)   = h(x(k))

``f(x, inputs)`` takes the state (B, n) and a dict of input-port tensors (B, width) and returns (B, n);
``h(x)`` returns the outputs stacked in port order, (B, sum of output widths). Both must treat batch
members independently (row b of the result depends on row b of the arguments only). They are probed with
batches of 1 and 2 when the block is built.

A ``Nonlinear`` block can stand wherever an ``LTI`` known model does: ``markov`` linearizes it (forward-mode
autograd, Jacobian-vector products through the step, or central finite differences) at its current state or
along the trajectory from it, so ``refinement`` derives the estimator's Markov parameters from it, and
``MarkovRefresh`` recomputes them during a run. Functions written with NumPy (which autograd cannot follow) are
linearized by central differences.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import torch
from torch.autograd.functional import jvp

from .blocks import DEFAULT_DTYPE, Block, tensor_result
from .compiled import call_user
from .errors import ConfigError, DimensionError


class Nonlinear(Block):
    """Batched nonlinear state-space block (see the module docstring).

    Args:
        f, h: the state map (or vector field) and output map.
        n_states: state dimension n.
        inputs, outputs: port name -> width (or lists of width-1 names).
        dt: sample time; with ``continuous=True`` each step integrates ``substeps`` RK4 steps of dt/substeps.
        x0: initial state (n,) or (B, n).
    """

    def __init__(self, f: Callable, h: Callable, n_states: int, inputs, outputs, dt: float,
                 continuous: bool = False, substeps: int = 1, x0=None, name: str = "nonlinear",
                 dtype=DEFAULT_DTYPE):
        if not callable(f) or not callable(h):
            raise ConfigError(f"block '{name}': f and h must be callable")
        super().__init__(name, _widths(inputs), _widths(outputs))
        if not dt or dt <= 0:
            raise ConfigError(f"block '{name}': dt must be a positive sample time, got {dt!r}")
        if substeps < 1:
            raise ConfigError(f"block '{name}': substeps must be at least 1, got {substeps}")
        self.f, self.h, self.n_states = f, h, int(n_states)
        self.dt, self.continuous, self.substeps = float(dt), bool(continuous), int(substeps)
        x0 = torch.zeros(1, self.n_states, dtype=dtype) if x0 is None else \
            torch.as_tensor(x0, dtype=dtype, device="cpu").reshape(-1, self.n_states)
        self.register_buffer("x0", x0)
        self.register_buffer("x", torch.zeros(0, self.n_states, dtype=dtype))
        self._out_slices, start = {}, 0
        for p, w in self.outputs.items():
            self._out_slices[p] = slice(start, start + w)
            start += w
        self._probe(dtype)

    def _probe(self, dtype) -> None:
        n_out = sum(self.outputs.values())
        for B in (1, 2):
            x = self.x0[:1].expand(B, -1).clone().to(dtype)
            ins = {p: torch.zeros(B, w, dtype=dtype) for p, w in self.inputs.items()}
            try:
                fx, hx = self._f(x, ins), self._h(x)
            except Exception as e:
                raise ConfigError(f"block '{self.name}': f or h failed on a state ({B}, {self.n_states}) and inputs "
                                  f"{ {p: (B, w) for p, w in self.inputs.items()} }: {e!r}") from e
            for what, value, want in (("f", fx, (B, self.n_states)), ("h", hx, (B, n_out))):
                got = tuple(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__
                if got != want:
                    raise DimensionError(f"block '{self.name}': {what} must return shape {want} for batch {B}, "
                                         f"got {got}")

    # --- block protocol ---------------------------------------------------------------------------------
    def feedthrough(self):
        return {p: () for p in self.outputs}

    def reset(self, batch_size: int) -> None:
        super().reset(batch_size)
        self.check_batch(self.x0, "x0")
        self.x = self.x0.expand(batch_size, -1).clone()

    def _f(self, x: torch.Tensor, inputs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        return tensor_result(call_user(self.f, x, inputs), x.dtype, x.device)

    def _h(self, x: torch.Tensor) -> torch.Tensor:
        return tensor_result(call_user(self.h, x), x.dtype, x.device)

    def output(self, port, inputs):
        return self._h(self.x)[:, self._out_slices[port]]

    def step_map(self, x: torch.Tensor, inputs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """The discrete map x(k) -> x(k+1) for given inputs (RK4 substeps for a continuous block)."""
        if not self.continuous:
            return self._f(x, inputs)
        h = self.dt / self.substeps
        for _ in range(self.substeps):
            k1 = self._f(x, inputs)
            k2 = self._f(x + 0.5 * h * k1, inputs)
            k3 = self._f(x + 0.5 * h * k2, inputs)
            k4 = self._f(x + h * k3, inputs)
            x = x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        return x

    def update(self, inputs):
        self.set_state(x=self.step_map(self.x, inputs))

    def lower(self, b) -> None:
        """The native form: ``h`` and the step map (``f``, or its RK4 substeps) compiled by numba
        (``rcotorch.compiled``), each called once per chunk of members and step; a function that does not
        compile keeps the graph on PyTorch, and the reason names it."""
        from .compiled import compile_map, compile_step, describe
        n, n_out = self.n_states, sum(self.outputs.values())
        x = b.state("x")
        h = compile_map(self.h, n, n_out)
        if isinstance(h, str):
            b.refuse(f"output function h {describe(self.h)} is not compiled: {h}")
        m = sum(self.inputs.values())
        c = compile_step(self.f, n, self.inputs, self.dt, self.continuous, self.substeps)
        if isinstance(c, str):
            b.refuse(f"state function f {describe(self.f)} is not compiled: {c}")
        for port, sl in self._out_slices.items():
            y = b.scratch(n_out)
            b.emit("CALL", [n, x, n_out, y, b.function(h.address, h)], port=port)
            b.emit("COPY", [sl.stop - sl.start, y + sl.start, b.output(port)], port=port)
        xu, nxt = b.scratch(n + m), b.scratch(n)
        b.emit("COPY", [n, x, xu])
        at = xu + n
        for port, width in self.inputs.items():
            src = b.input(port)
            if src is None:
                b.refuse(f"input '{port}' is not connected")
            b.emit("COPY", [width, src, at])
            at += width
        b.emit("CALL", [n + m, xu, n, nxt, b.function(c.address, c)])
        b.emit("COPY", [n, nxt, x])

    # --- linearization ------------------------------------------------------------------------------------
    def differentiable(self) -> bool:
        """Whether autograd follows f and h (torch operations); NumPy functions are not followed."""
        if getattr(self, "_differentiable", None) is None:
            x = self.x0[:1].detach().clone().requires_grad_(True)
            ins = {p: torch.zeros(1, w, dtype=x.dtype) for p, w in self.inputs.items()}
            try:
                with torch.enable_grad():
                    self._differentiable = all(v.requires_grad for v in (self._f(x, ins), self._h(x)))
            except Exception:              # NumPy refuses a tensor that requires grad
                self._differentiable = False
        return self._differentiable

    def markov(self, input: str, output: str, n: int, x: torch.Tensor | None = None,
               inputs: Mapping[str, torch.Tensor] | None = None, method: str = "auto",
               along: str = "trajectory", eps: float = 1e-6) -> torch.Tensor:
        """Markov parameters H_0..H_(n-1) of ``input -> output`` linearized at state ``x`` (default: the current
        state, or x0 before a reset) with the other inputs held at ``inputs`` (default zero): (B, n, out, in).

        ``along='trajectory'`` linearizes along the free motion from x (H_i = C_i A_(i-1) .. A_1 B_0);
        ``along='point'`` at the fixed point x (H_i = C A^(i-1) B). ``method`` is 'autograd' (forward-mode
        Jacobian-vector products through ``step_map`` and ``h``), 'fd' (central differences, step eps
        relative to the size of x and u) or 'auto' (autograd where f and h are torch functions, else 'fd')."""
        if input not in self.inputs or output not in self.outputs:
            raise ConfigError(f"block '{self.name}': no input '{input}' or output '{output}'; inputs are "
                              f"{list(self.inputs)}, outputs {list(self.outputs)}")
        if method not in ("auto", "autograd", "fd") or along not in ("trajectory", "point"):
            raise ConfigError(f"block '{self.name}': method must be 'auto', 'autograd' or 'fd' and along "
                              f"'trajectory' or 'point', got {method!r}, {along!r}")
        x = ((self.x if self.x.shape[0] else self.x0) if x is None else x).detach()
        if method == "auto":
            method = "autograd" if self.differentiable() else "fd"
        B, W = x.shape[0], self.inputs[input]
        ins = {p: x.new_zeros(B, w) for p, w in self.inputs.items()}
        ins.update({p: v.detach().to(x).expand(B, -1) for p, v in dict(inputs or {}).items()})
        rows = self._out_slices[output]
        # All W input directions at once: direction j of member b is row j * B + b (members are independent).
        xs = x.repeat(W, 1)
        stacked = {p: v.repeat(W, 1) for p, v in ins.items()}
        direction = torch.eye(W, dtype=x.dtype, device=x.device).repeat_interleave(B, 0)

        def tangent(fun, at, v):
            if method == "autograd":
                # Forward-mode product through reverse mode (double backward): in torch 2.x this is much faster
                # than torch.func.jvp for models built of many elementwise operations.
                value, jv = jvp(fun, at, v)
                return value.detach(), jv.detach()
            with torch.no_grad():
                scale = eps * max(1.0, float(at.abs().max()))
                return fun(at), (fun(at + scale * v) - fun(at - scale * v)) / (2 * scale)

        H = x.new_zeros(B, n, rows.stop - rows.start, W)
        xi, dx = tangent(lambda uu: self.step_map(xs, {**stacked, input: uu}), stacked[input], direction)
        for i in range(1, n):
            base = xi if along == "trajectory" else xs
            H[:, i] = tangent(lambda xx: self._h(xx)[:, rows], base, dx)[1].reshape(W, B, -1).permute(1, 2, 0)
            if i + 1 < n:
                xn, dx = tangent(lambda xx: self.step_map(xx, stacked), base, dx)
                if along == "trajectory":
                    xi = xn
        return H


class MarkovRefresh:
    """Recompute an estimator's Markov parameters from a nonlinear known model every ``every`` steps, per
    member at its current state and with its inputs held at the values it received in the last step
    (linearization along the trajectory). Attach it to the graph, ``graph.add_hook(MarkovRefresh(graph, 500))``,
    so it runs after every step (also inside ``Run``), or call it after ``graph.step()`` yourself."""

    def __init__(self, graph, every: int, known: str | None = None, identified: str | None = None,
                 actuation: str = "u", measured: str = "y", method: str = "auto"):
        """``known``, ``identified``: block names; by default the graph's ``known`` and ``estimator`` roles.
        ``method``: how ``Nonlinear.markov`` linearizes the known model. The hook acts only at steps that are
        multiples of ``every``, so the native engine runs the steps in between without Python."""
        if every < 1:
            raise ConfigError(f"MarkovRefresh: every must be at least 1, got {every}")
        self.graph, self.every, self.method = graph, every, method
        self.known = graph.blocks[known] if known else graph.role("known")
        self.ident = graph.blocks[identified] if identified else graph.role("estimator")
        self.known_name, self.actuation, self.measured = self.known.name, actuation, measured

    def __call__(self, graph=None) -> bool:
        if int(self.graph.k) % self.every:
            return False
        d, nu = self.ident.first_delay, self.ident.nu
        g = self.graph
        held = {p: g.last[g.sources[(self.known_name, p)]] for p in self.known.inputs
                if (self.known_name, p) in g.sources and g.last}
        H = self.known.markov(self.actuation, self.measured, d + nu, inputs=held, method=self.method)
        self.ident.set_markov(-H[:, d:d + nu], d)
        return True


def _widths(spec) -> dict[str, int]:
    """Port widths from a mapping name -> width, or a name / list of names of width 1."""
    if isinstance(spec, str):
        return {spec: 1}
    return dict(spec) if isinstance(spec, Mapping) else {p: 1 for p in spec}
