"""Nonlinear state-space blocks and their Markov parameters by linearization.

    x(k+1) = f(x(k), inputs(k))               (discrete map), or
    x'(t)  = f(x(t), inputs(k)),  t in [k dt, (k+1) dt)   (continuous, fixed-step RK4, inputs held)
    y(k)   = h(x(k))

Two ways to write f and h (``form``):

* ``'batch'`` (the default): ``f(x, inputs)`` takes the state (B, n) and a dict of input-port tensors
  (B, width) and returns (B, n); ``h(x)`` returns the outputs stacked in port order, (B, sum of output widths).
* ``'components'``, the convention of ``scipy.integrate.solve_ivp(vectorized=True)``: ``x[i]`` is state
  component i and ``inputs[port][j]`` component j of a port, and f returns the n components of x' (or of
  x(k+1)) as a sequence, h the outputs' components (one output may be returned as it is)::

      def duffing(x, inputs):
          q, v = x
          return v, -k * q - c * v - a * q ** 3 + inputs["w"][0]

  The PyTorch engine calls it with the whole batch, each component a (B,) tensor; the native engine calls it
  for one member at a time with floats, so its compiled form makes no array in a step (the batch form makes
  its temporary arrays at every call), so a user's equations compile to a loop without temporary arrays.

Both must treat batch members independently (member b of the result depends on member b of the arguments
only). They are probed with batches of 1 and 2 when the block is built.

A ``Nonlinear`` block can stand wherever an ``LTI`` known model does: ``markov`` linearizes it (forward-mode
autograd, Jacobian-vector products through the step, or central finite differences) at its current state or
along the trajectory from it, so ``refinement`` derives the estimator's Markov parameters from it, and
``MarkovRefresh`` recomputes them during a run. Functions written with NumPy (which autograd cannot follow) are
linearized by central differences.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Mapping

import torch
from torch.autograd.functional import jvp

from ..engine import kernels
from ..engine.compiled import Compiled, call_user, components
from ..errors import ConfigError, DimensionError
from .base import DEFAULT_DTYPE, Block, tensor_result


class Nonlinear(Block):
    """Batched nonlinear state-space block (see the module docstring).

    x(k+1) = f(x(k), inputs(k)) (or x' = f(x, inputs) integrated by RK4 with the inputs held over the step),
    y(k) = h(x(k)). No output reads an input at the same step (no feedthrough).

    Parameters
    ----------
    f : callable
        The state map (or, with ``continuous=True``, the vector field), ``f(x, inputs)``.
    h : callable
        The output map ``h(x)``: the outputs stacked in port order.
    n_states : int
        The state dimension n.
    inputs : Mapping[str, int] or list of str
        Input port name -> width (or a list of width-1 names).
    outputs : Mapping[str, int] or list of str
        Output port name -> width (or a list of width-1 names), in the order h stacks them.
    dt : float
        Sample time [s], > 0.
    continuous : bool, optional
        f is a vector field: each step integrates ``substeps`` RK4 steps of dt / substeps.
    substeps : int, optional
        RK4 steps per sample, >= 1.
    x0 : array_like, optional
        Initial state (n,) or (B, n); zero by default.
    name : str, optional
        The block's name.
    dtype : torch.dtype, optional
        Floating-point type (float64 by default).
    form : {'batch', 'components'}, optional
        How f and h take and return their values (module docstring).

    Raises
    ------
    ConfigError
        If f or h is not callable or fails on the probes, ``form`` is unknown, ``dt`` is not positive, or
        ``substeps`` < 1.
    DimensionError
        If f or h returns the wrong shape on the probes.

    Shape
    -----
    - Inputs: one per entry of ``inputs``, (B, width).
    - Outputs: one per entry of ``outputs``, (B, width); together h(x), (B, sum of output widths).
    - State ``x``: (B, n_states).
    """

    def __init__(self, f: Callable, h: Callable, n_states: int, inputs, outputs, dt: float,
                 continuous: bool = False, substeps: int = 1, x0=None, name: str = "nonlinear",
                 dtype=DEFAULT_DTYPE, form: str = "batch"):
        if not callable(f) or not callable(h):
            raise ConfigError(f"block '{name}': f and h must be callable")
        if form not in ("batch", "components"):
            raise ConfigError(f"block '{name}': form must be 'batch' or 'components', got {form!r}")
        self.form = form
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
            except DimensionError:
                raise
            except Exception as e:
                call = "f(x, inputs) with x the state and inputs a dict of the input ports, and h(x)" \
                    if isinstance(e, TypeError) and "argument" in str(e) else ""
                raise ConfigError(f"block '{self.name}': f or h failed on a state ({B}, {self.n_states}) and inputs "
                                  f"{ {p: (B, w) for p, w in self.inputs.items()} }: {e!r}"
                                  + (f"; they are called as {call}" if call else "")) from e
            for what, value, want in (("f", fx, (B, self.n_states)), ("h", hx, (B, n_out))):
                got = tuple(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__
                if got != want:
                    raise DimensionError(f"block '{self.name}': {what} must return shape {want} for batch {B}, "
                                         f"got {got}{self._shape_hint(got, want)}")

    def _shape_hint(self, got, want) -> str:
        """What a batch-form result of the wrong shape most likely means, and how to write it."""
        if self.form != "batch" or not isinstance(got, tuple):
            return ""
        if len(got) >= 2 and got[:2] == want[::-1] and all(d == 1 for d in got[2:]):
            return (": the components along the first axis, as np.array([a, b]) makes them; stack them as "
                    "columns, np.stack([a, b], axis=1), or write the function in form='components'")
        if got == want[:1]:
            return ": one value per member as a 1-d array; return it as a column, x[:, 0:1] rather than x[:, 0]"
        return ""

    # --- block protocol ---------------------------------------------------------------------------------
    def feedthrough(self):
        return {p: () for p in self.outputs}

    def _user_functions(self) -> dict:
        return {"f": self.f, "h": self.h}

    def reset(self, batch_size: int) -> None:
        super().reset(batch_size)
        self.check_batch(self.x0, "x0")
        self.x = self.x0.expand(batch_size, -1).clone()

    def _f(self, x: torch.Tensor, inputs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        if self.form == "components":
            out = call_user(self.f, x.T, {p: v.T for p, v in inputs.items()})
            return self._components(out, self.n_states, x, "f")
        return tensor_result(call_user(self.f, x, inputs), x.dtype, x.device)

    def _h(self, x: torch.Tensor) -> torch.Tensor:
        if self.form == "components":
            return self._components(call_user(self.h, x.T), sum(self.outputs.values()), x, "h")
        return tensor_result(call_user(self.h, x), x.dtype, x.device)

    def _components(self, out, n: int, x: torch.Tensor, what: str) -> torch.Tensor:
        try:
            return components(out, n, x.shape[0], x.dtype, x.device)
        except DimensionError as e:
            raise DimensionError(f"block '{self.name}': {what} (form 'components') {e}") from None

    def output(self, port, inputs):
        return self._h(self.x)[:, self._out_slices[port]]

    def step_map(self, x: torch.Tensor, inputs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """The discrete map x(k) -> x(k+1) for given inputs (RK4 substeps for a continuous block).

        Parameters
        ----------
        x : torch.Tensor
            (B, n_states), the state x(k).
        inputs : Mapping[str, torch.Tensor]
            Input port -> (B, width), held over the step.

        Returns
        -------
        torch.Tensor
            (B, n_states), x(k+1).
        """
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
        """Describe the block to the native engine: ``h`` and the step map compiled by numba.

        ``h`` and the step map (``f``, or its RK4 substeps) are compiled by ``rcotorch.engine.compiled`` and each
        called once per chunk of members and step; a function that does not compile keeps the graph on
        PyTorch, and the reason names it.

        Parameters
        ----------
        b : rcotorch.engine.lowering.Builder
            Receives the compiled functions, the state, the ports and the instructions; refuses the block where
            a function does not compile or an input is not connected.
        """
        from ..engine.compiled import compile_map, compile_step, describe
        from ..engine.lowering import NotLowerable
        n, n_out = self.n_states, sum(self.outputs.values())
        x = b.state("x")
        m = sum(self.inputs.values())
        # In the components form the step reads each member's state and inputs before it writes its next state,
        # so it may read them where they are: the inputs' slots right after the state's.
        beside = b.scratch(m) if self.form == "components" else None
        try:
            h = compile_map(self.h, n, n_out, self.form)
        except NotLowerable as e:
            b.refuse(f"output function h {describe(self.h)} is not compiled: {e}")
        try:
            c = compile_step(self.f, n, self.inputs, self.dt, self.continuous, self.substeps, self.form)
        except NotLowerable as e:
            b.refuse(f"state function f {describe(self.f)} is not compiled: {e}")
        for port, sl in self._out_slices.items():
            if len(self._out_slices) == 1:           # h writes the port itself
                b.emit("CALL", port=port, NIN=n, IN=x, NOUT=n_out, OUT=b.output(port),
                       FUNCTION=b.function(h.address, h))
                continue
            y = b.scratch(n_out)
            b.emit("CALL", port=port, NIN=n, IN=x, NOUT=n_out, OUT=y, FUNCTION=b.function(h.address, h))
            b.emit("COPY", port=port, WIDTH=sl.stop - sl.start, IN=y + sl.start, OUT=b.output(port))
        if beside == x + n:
            xu = x
        else:
            xu = b.scratch(n + m)
            b.emit("COPY", WIDTH=n, IN=x, OUT=xu)
        at = xu + n
        for port, width in self.inputs.items():
            src = b.input(port)
            if src is None:
                b.refuse(f"input '{port}' is not connected")
            b.emit("COPY", WIDTH=width, IN=src, OUT=at)
            at += width
        # x(k + 1) is written over x(k), read from xu (a copy, or x itself in the components form)
        b.emit("CALL", NIN=n + m, IN=xu, NOUT=n, OUT=x, FUNCTION=b.function(c.address, c))

    # --- linearization ------------------------------------------------------------------------------------
    def differentiable(self) -> bool:
        """Whether autograd follows f and h (torch operations); NumPy functions are not followed.

        The answer comes from one probe at x0 and is kept.

        Returns
        -------
        bool
        """
        if getattr(self, "_differentiable", None) is None:
            x = self.x0[:1].detach().clone().requires_grad_(True)
            ins = {p: torch.zeros(1, w, dtype=x.dtype) for p, w in self.inputs.items()}
            try:
                with torch.enable_grad():
                    self._differentiable = all(v.requires_grad for v in (self._f(x, ins), self._h(x)))
            except Exception:              # NumPy refuses a tensor that requires grad
                self._differentiable = False
        return self._differentiable

    def compiled_maps(self) -> tuple[Compiled, Compiled] | None:
        """The step map and h compiled as the native engine runs them (``rcotorch.engine.compiled``), or None
        where either does not compile (the reason is the native engine's to give).

        Returns
        -------
        tuple of (Compiled, Compiled) or None
            The step map, [x, inputs in port order] -> x(k+1), and h.
        """
        from ..engine.compiled import compile_map, compile_step
        from ..engine.lowering import NotLowerable
        n, n_out = self.n_states, sum(self.outputs.values())
        try:
            return (compile_step(self.f, n, self.inputs, self.dt, self.continuous, self.substeps, self.form),
                    compile_map(self.h, n, n_out, self.form))
        except NotLowerable:
            return None

    def markov(self, input: str, output: str, n: int, x: torch.Tensor | None = None,
               inputs: Mapping[str, torch.Tensor] | None = None, method: str = "auto",
               along: str = "trajectory", eps: float = 1e-6, compiled: bool = False) -> torch.Tensor:
        """Markov parameters H_0..H_(n-1) of ``input -> output``, linearized at a state.

        ``along='trajectory'`` linearizes along the free motion from x (H_i = C_i A_(i-1) .. A_1 B_0);
        ``along='point'`` at the fixed point x (H_i = C A^(i-1) B). H_0 is zero: h reads no input.

        Parameters
        ----------
        input : str
            The input port.
        output : str
            The output port.
        n : int
            The number of Markov parameters.
        x : torch.Tensor, optional
            (B, n_states), the state to linearize at; by default the current state, or x0 before a reset.
        inputs : Mapping[str, torch.Tensor], optional
            Input port -> its value, (B, width) or (1, width), held during the linearization; zero by default.
        method : {'auto', 'autograd', 'fd'}, optional
            'autograd' (forward-mode Jacobian-vector products through ``step_map`` and ``h``), 'fd' (central
            differences, step eps relative to the size of x and u) or 'auto' (with ``compiled``, the native
            central differences where f and h compile; otherwise autograd where f and h are torch functions,
            else 'fd').
        along : {'trajectory', 'point'}, optional
            Linearize along the free motion from x, or at the fixed point x.
        eps : float, optional
            The relative step of the central differences.
        compiled : bool, optional
            With 'fd' or 'auto' on float64 CPU tensors and the native engine at hand, the central differences in
            the native engine, of f and h compiled as it runs them (``compiled_maps``), without Python in the
            loop: those of 'fd' to rounding, and within about 1e-9 of autograd's derivatives. Where f or h do not
            compile, the method as without it.

        Returns
        -------
        torch.Tensor
            (B, n, width(output), width(input)).

        Raises
        ------
        ConfigError
            If the block has no such input or output port, or ``method`` or ``along`` is unknown.
        """
        if input not in self.inputs or output not in self.outputs:
            raise ConfigError(f"block '{self.name}': no input '{input}' or output '{output}'; inputs are "
                              f"{list(self.inputs)}, outputs {list(self.outputs)}")
        if method not in ("auto", "autograd", "fd") or along not in ("trajectory", "point"):
            raise ConfigError(f"block '{self.name}': method must be 'auto', 'autograd' or 'fd' and along "
                              f"'trajectory' or 'point', got {method!r}, {along!r}")
        x = ((self.x if self.x.shape[0] else self.x0) if x is None else x).detach()
        B, W = x.shape[0], self.inputs[input]
        ins = {p: x.new_zeros(B, w) for p, w in self.inputs.items()}
        ins.update({p: v.detach().to(x).expand(B, -1) for p, v in dict(inputs or {}).items()})
        rows = self._out_slices[output]
        if compiled and method in ("auto", "fd") and x.device.type == "cpu" and x.dtype == torch.float64 and \
                kernels.allowed():
            maps = self.compiled_maps()
            if maps is not None:
                col = sum(w for p, w in itertools.takewhile(lambda pw: pw[0] != input, self.inputs.items()))
                u = torch.cat([ins[p] for p in self.inputs], 1)
                return kernels.markov_fd(maps[0].address, maps[1].address, x, u, col, W,
                                         sum(self.outputs.values()), rows, n, eps, along == "trajectory")
        if method == "auto":
            method = "autograd" if self.differentiable() else "fd"
        # All W input directions at once: direction j of member b is row j * B + b (members are independent).
        xs = x.repeat(W, 1)
        stacked = {p: v.repeat(W, 1) for p, v in ins.items()}
        direction = torch.eye(W, dtype=x.dtype, device=x.device).repeat_interleave(B, 0)
        # Central differences evaluate a function at the point and on both sides of it in one call: the rows
        # three times over (each row's value does not depend on the others).
        copies = 1 if method == "autograd" else 3
        xs_c, stacked_c = xs.repeat(copies, 1), {p: v.repeat(copies, 1) for p, v in stacked.items()}

        def tangent(fun, at, v):
            if method == "autograd":
                # Forward-mode product through reverse mode (double backward), chosen over torch.func.jvp for
                # models built of many elementwise operations (docs/engine.md).
                value, jv = jvp(fun, at, v)
                return value.detach(), jv.detach()
            with torch.no_grad():
                scale, N = eps * max(1.0, float(at.abs().max())), at.shape[0]
                y = fun(torch.cat([at, at + scale * v, at - scale * v]))
                return y[:N], (y[N:2 * N] - y[2 * N:]) / (2 * scale)

        H = x.new_zeros(B, n, rows.stop - rows.start, W)
        xi, dx = tangent(lambda uu: self.step_map(xs_c, {**stacked_c, input: uu}), stacked[input], direction)
        for i in range(1, n):
            base = xi if along == "trajectory" else xs
            H[:, i] = tangent(lambda xx: self._h(xx)[:, rows], base, dx)[1].reshape(W, B, -1).permute(1, 2, 0)
            if i + 1 < n:
                xn, dx = tangent(lambda xx: self.step_map(xx, stacked_c), base, dx)
                if along == "trajectory":
                    xi = xn
        return H


class MarkovRefresh:
    """Recompute an estimator's Markov parameters from a nonlinear known model every ``every`` steps.

    Per member, the known model is linearized at its current state with its inputs held at the values it
    received in the last step (linearization along the trajectory), and the estimator gets
    beta_i = -H_i, i = d..d+nu-1 (its own relative degree d and count nu). Attach it to the graph,
    ``graph.add_hook(MarkovRefresh(graph, 500))``, so it runs after every step (also inside ``Run``), or call it
    after ``graph.step()`` yourself. The hook acts only at steps that are multiples of ``every``, so the native
    engine runs the steps in between without Python.

    Parameters
    ----------
    graph : Graph
        The refinement.
    every : int
        Act after the steps k with k % every == 0, >= 1.
    known : str, optional
        The known model's block name; by default the graph's 'known' role.
    identified : str, optional
        The estimator's block name; by default the graph's 'estimator' role.
    actuation : str, optional
        The known model's input port for u.
    measured : str, optional
        The known model's output port y.
    method : {'auto', 'autograd', 'fd'}, optional
        How ``Nonlinear.markov`` linearizes the known model; on a graph that runs natively, 'auto' and 'fd'
        linearize in the native engine where the model's functions compile (``compiled=True``).

    Raises
    ------
    ConfigError
        If ``every`` < 1, or the graph lacks a role it needs.
    """

    def __init__(self, graph, every: int, known: str | None = None, identified: str | None = None,
                 actuation: str = "u", measured: str = "y", method: str = "auto"):
        if every < 1:
            raise ConfigError(f"MarkovRefresh: every must be at least 1, got {every}")
        self.graph, self.every, self.method = graph, every, method
        self.known = graph.blocks[known] if known else graph.role("known")
        self.ident = graph.blocks[identified] if identified else graph.role("estimator")
        self.known_name, self.actuation, self.measured = self.known.name, actuation, measured

    keeps_theta = True      # it sets the estimator's Markov parameters, never theta (``Graph.add_hook``)

    @property
    def acts_on(self) -> frozenset[str]:
        """The blocks it changes (``Graph.add_hook``): the estimator."""
        return frozenset({self.ident.name})

    def __call__(self, graph=None) -> bool:
        """Set new Markov parameters if the graph is at a multiple of ``every`` steps.

        Parameters
        ----------
        graph : Graph, optional
            Ignored (the hook acts on the graph it was made for); given by ``Graph`` when it calls hooks.

        Returns
        -------
        bool
            Whether it set new Markov parameters.
        """
        if int(self.graph.k) % self.every:
            return False
        d, nu = self.ident.first_delay, self.ident.nu
        g = self.graph
        held = {p: g.last[g.sources[(self.known_name, p)]] for p in self.known.inputs
                if (self.known_name, p) in g.sources and g.last}
        H = self.known.markov(self.actuation, self.measured, d + nu, inputs=held, method=self.method,
                              compiled=g.native_status() is None)
        self.ident.set_markov(-H[:, d:d + nu], d)
        return True


def _widths(spec) -> dict[str, int]:
    """Port widths from a mapping name -> width, or a name / list of names of width 1."""
    if isinstance(spec, str):
        return {spec: 1}
    return dict(spec) if isinstance(spec, Mapping) else {p: 1 for p in spec}
