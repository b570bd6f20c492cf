"""Held-out validation: the refined model, its parameters frozen, simulated on data the refinement did not use.

In a refinement the known model with the identified subsystem in feedback is a free-run simulation driven by
the exogenous input w alone; the measurements only move theta. Validation freezes theta (a zero RLS gain) and
runs that simulation on other data:

* a later window of the graph's recording (``rows=(start, stop)``),
* another recording (``data=``, a block with the same output ports as the graph's data block), or
* for a simulated physical system, a fresh stretch of its sources: the excitation and noise streams continue
  from the step the refinement stopped at (samples it never drew), the physical system starting at rest.

The model starts from an initial state fitted to the first ``fit_steps`` samples (least squares in the known
model's state ``x``, by the outputs' sensitivity to each state entry; two Gauss-Newton passes, exact when the
loop is linear in the state), and the error is measured on the samples after them:

    rmse = sqrt(mean_k |y(k) - y_hat(k)|^2),     fit = 100 (1 - ||y - y_hat|| / ||y - mean(y)||)   [%],

for the refined model and, in the same way, for the initial model (theta at its initial value).
"""

from __future__ import annotations

import copy
import functools
from collections.abc import Mapping
from dataclasses import dataclass, field

import torch

from ..errors import ConfigError
from . import joined
from .intervals import snapshot

FIT_STEPS = 50           # samples that fix the initial state (excluded from the scores)


@dataclass
class Validation:
    """Scores of a refined model on held-out data, per member ((B,) tensors), and the traces they come from.

    ``validate`` makes it.

    Parameters
    ----------
    source : str
        What the held-out data are.
    steps : int
        T, the samples simulated, the first ``fit_steps`` included.
    fit_steps : int
        The leading samples that fix the initial state (not scored).
    rmse : torch.Tensor
        (B,), sqrt(mean_k |y(k) - y_hat(k)|^2) of the refined model.
    rmse_initial : torch.Tensor
        (B,), the same for the initial model.
    fit_percent : torch.Tensor
        (B,), 100 (1 - ||y - y_hat|| / ||y - mean(y)||) of the refined model.
    fit_percent_initial : torch.Tensor
        (B,), the same for the initial model.
    state_fitted : bool
        False when the known model has no state ``x`` to fit (it starts as reset).
    x0 : torch.Tensor or None
        (B, n), the refined model's fitted initial state.
    x0_initial : torch.Tensor or None
        (B, n), the initial model's.
    measured : torch.Tensor
        (T, M, width), y.
    refined : torch.Tensor
        (T, M, width), y_hat of the refined model.
    initial : torch.Tensor
        (T, M, width), y_hat of the initial model.

    Shape
    -----
    ``measured``, ``refined``, ``initial`` are (T, M, width), T = ``steps`` (the first ``fit_steps`` samples fix
    the initial state and are not scored), M the members ``validate`` kept (all of them unless ``keep``); the
    scores are (B,).
    """

    source: str              # what the held-out data are
    steps: int
    fit_steps: int
    rmse: torch.Tensor
    rmse_initial: torch.Tensor
    fit_percent: torch.Tensor
    fit_percent_initial: torch.Tensor
    state_fitted: bool       # False when the known model has no state ``x`` to fit (it starts as reset)
    x0: torch.Tensor | None = field(repr=False)           # the refined model's fitted initial state (B, n)
    x0_initial: torch.Tensor | None = field(repr=False)   # the initial model's
    measured: torch.Tensor = field(repr=False)
    refined: torch.Tensor = field(repr=False)
    initial: torch.Tensor = field(repr=False)

    def summary(self) -> dict:
        """The scores as plain numbers (B = 1) or lists, for ``summary.json``.

        Returns
        -------
        dict
            'source', 'steps', 'fit_steps', 'state_fitted', 'rmse', 'rmse_initial', 'fit_percent',
            'fit_percent_initial'.
        """
        def plain(t: torch.Tensor):
            values = [float(v) for v in t.cpu()]
            return values[0] if len(values) == 1 else values
        return {"source": self.source, "steps": self.steps, "fit_steps": self.fit_steps,
                "state_fitted": self.state_fitted, "rmse": plain(self.rmse),
                "rmse_initial": plain(self.rmse_initial), "fit_percent": plain(self.fit_percent),
                "fit_percent_initial": plain(self.fit_percent_initial)}


def validate(graph, steps: int | None = None, *, rows: tuple[int, int] | None = None, data=None,
             fit_steps: int = FIT_STEPS, keep: int | None = None) -> Validation:
    """Simulate ``graph``'s refined model (its present theta, frozen) and its initial model on held-out data.

    Parameters
    ----------
    graph : Graph
        A refinement (roles ``estimator``, ``known``, ``physical``, ``measured``, ``prediction``), e.g. made
        by ``rcotorch.refinement``, after its run. It is not changed.
    steps : int, optional
        Samples to simulate, the first ``fit_steps`` included. Default: the window's length for ``rows``,
        the recording's for ``data``, and as many steps as the refinement ran for a simulated system.
    rows : (int, int), optional
        A window [start, stop) of the graph's own recording (sample indices of its data block); it must not
        overlap the samples the refinement read.
    data : Block, optional
        Another recording: a source block with the data block's output ports (e.g. ``rcotorch.Recorded``).
    fit_steps : int
        Leading samples that fix the initial state and are left out of the scores.
    keep : int, optional
        Keep the traces of the first ``keep`` members only (default: all); the scores are every member's.

    Returns
    -------
    Validation

    Raises
    ------
    ConfigError
        If the graph lacks one of the roles, ``rows`` or ``data`` does not fit the kind of refinement (both
        given, a recording without either, a window outside the recording or overlapping the samples the
        refinement read, a data block with other ports), or ``steps`` <= ``fit_steps``.
    """
    for role in ("estimator", "known", "physical", "measured", "prediction"):
        if role not in graph.roles:
            raise ConfigError(f"validate: the graph has no '{role}' role; build it with rcotorch.refinement or "
                              f"declare roles= (it has {sorted(graph.roles)})")
    recorded = graph.roles["physical"] in graph.blocks and not graph.blocks[graph.roles["physical"]].inputs
    blocks = {name: copy.deepcopy(blk) for name, blk in graph.blocks.items()}
    phys = graph.roles["physical"]
    offset = None
    if rows is not None or data is not None:
        if not recorded:
            raise ConfigError("validate: rows= and data= are for a refinement of recorded data; this graph "
                              "simulates its physical system (validate it on a fresh excitation: no rows= or data=)")
        if data is not None and rows is not None:
            raise ConfigError("validate: give rows= or data=, not both")
        old = graph.blocks[phys]
        if data is not None:
            missing = [p for p in old.outputs if p not in data.outputs or data.outputs[p] != old.outputs[p]]
            if missing:
                raise ConfigError(f"validate: data block '{data.name}' must have the output ports of '{phys}' "
                                  f"{dict(old.outputs)}; it has {dict(data.outputs)}")
            new = copy.deepcopy(data)
            new.name = phys
            source = f"block '{data.name}'" + (f" ({data.source})" if getattr(data, "source", None) else "")
        else:
            start, stop = (int(r) for r in rows)
            used = int(old.k)
            if not 0 <= start < stop <= old.length:
                raise ConfigError(f"validate: rows=({start}, {stop}) must lie within the recording's {old.length} "
                                  "samples")
            if start < used:
                raise ConfigError(f"validate: rows=({start}, {stop}) overlap the {used} samples the refinement "
                                  "read; held-out rows start at or after them")
            new = old.window(start, stop)
            source = f"rows {start}-{stop} of block '{phys}'" + (f" ({old.source})" if old.source else "")
        blocks[phys] = new
        steps = new.max_steps if steps is None else int(steps)
    else:
        if recorded:
            raise ConfigError("validate: this refinement reads recorded data; give rows=(start, stop) of a "
                              "window it did not read, or data= another recording")
        offset = int(graph.k)
        steps = offset if steps is None else int(steps)
        source = f"fresh excitation: the sources' steps {offset}-{offset + steps}, the physical system from rest"
    if steps <= fit_steps:
        raise ConfigError(f"validate: steps ({steps}) must exceed fit_steps ({fit_steps})")
    conns = [(f"{s[0]}.{s[1]}", f"{d[0]}.{d[1]}") for d, s in graph.sources.items()]
    base = type(graph)(list(blocks.values()), conns, batch_size=graph.batch_size, dtype=_dtype(graph),
                       device=graph.k.device, engine=graph.engine, roles=graph.roles)
    est = base.role("estimator")
    refined_eta = graph.role("estimator").theta_free().detach().clone()
    initial_eta = est.theta_free().detach().clone()        # after the reset: the initial parameters
    if offset is not None:
        _continue_sources(base, offset)
    etas = {"refined": refined_eta, "initial": initial_eta}
    states = {}
    fitted_both = True
    start = snapshot(base)
    for which, eta in etas.items():                   # each fitted in one graph, from one state
        _restore(base, start)
        _freeze(base, eta)
        x0, fitted = _fit_state(base, fit_steps)
        fitted_both = fitted_both and fitted
        states[which] = x0
    scores = {which: _Scores(fit_steps, keep) for which in etas}
    measured = base.role_signal("measured")
    for predictions in _simulations(base, start, etas, states):
        _stream(base, steps, {"y": measured, **predictions}, functools.partial(_score, scores, list(predictions)))
    traces = {which: s.kept["y_hat"] for which, s in scores.items()}
    traces["measured"] = scores["refined"].kept["y"]
    scored = {which: s.result() for which, s in scores.items()}
    return Validation(source=source, steps=steps, fit_steps=fit_steps, rmse=scored["refined"][0],
                      rmse_initial=scored["initial"][0], fit_percent=scored["refined"][1],
                      fit_percent_initial=scored["initial"][1], state_fitted=fitted_both, x0=states["refined"],
                      x0_initial=states["initial"], measured=traces["measured"],
                      refined=traces["refined"], initial=traces["initial"])


class _Scores:
    """The scores' sums over the samples after the first ``fit_steps``, added stretch by stretch, and the traces
    of the first ``keep`` members (all where None)."""

    def __init__(self, fit_steps: int, keep: int | None):
        self.fit, self.keep, self.at = fit_steps, keep, 0
        self.sums: dict[str, torch.Tensor] = {}
        self.parts: dict[str, list] = {"y": [], "y_hat": []}
        self.squares: torch.Tensor | None = None       # y^2 of a stretch, kept from stretch to stretch

    def add(self, y: torch.Tensor, y_hat: torch.Tensor) -> None:
        """The next stretch's y and y_hat, (C, B, width) float64. ``y_hat`` is overwritten (z, then z^2, in its
        place): a stretch is megabytes at a large batch, and a new array for each product costs its pages."""
        kept = slice(None) if self.keep is None else slice(0, self.keep)
        self.parts["y"].append(y[:, kept].clone())
        self.parts["y_hat"].append(y_hat[:, kept].clone())
        lo = max(0, self.fit - self.at)
        self.at += y.shape[0]
        y, z = y[lo:], torch.sub(y, y_hat, out=y_hat)[lo:]
        if self.squares is None or self.squares.shape != y.shape:
            self.squares = torch.empty_like(y)
        for key, value in (("zz", torch.mul(z, z, out=z).sum((0, 2))), ("y", y.sum(0)),
                           ("yy", torch.mul(y, y, out=self.squares).sum(0)), ("n", torch.tensor(y.shape[0]))):
            self.sums[key] = value if key not in self.sums else self.sums[key] + value

    @property
    def kept(self) -> dict[str, torch.Tensor]:
        return {k: torch.cat(v) for k, v in self.parts.items()}

    def result(self) -> tuple[torch.Tensor, torch.Tensor]:
        """rmse and fit in percent, (B,) each."""
        s = self.sums
        n = s["n"].to(s["zz"].dtype)
        spread = torch.sqrt((s["yy"] - s["y"] ** 2 / n).sum(1).clamp_min(0)).clamp_min(1e-300)
        return torch.sqrt(s["zz"] / n), 100 * (1 - torch.sqrt(s["zz"]) / spread)


def _dtype(graph) -> torch.dtype:
    return graph.role("estimator").theta.dtype


def _continue_sources(graph, offset: int) -> None:
    """Sources that draw from a counter (the excitation, measurement noise) continue from ``offset``."""
    for blk in graph.blocks.values():
        if not blk.inputs and "k" in dict(blk.named_buffers()) and hasattr(blk, "stream"):
            blk.k.fill_(offset)


def _freeze(graph, eta: torch.Tensor) -> None:
    graph.role("estimator").hold(eta)


STRETCH_BYTES = 1 << 23   # the simulation records y and y_hat in stretches of about this many bytes each


def _simulations(base, start: Mapping[str, torch.Tensor], etas: Mapping[str, torch.Tensor],
                 states: Mapping[str, torch.Tensor | None]):
    """Set ``base`` up for the simulations of the models held at ``etas`` ({which: eta}), each from ``start`` and
    its known model's state ``states[which]`` (None: as in ``start``), and yield for each simulation {which: the
    signal of its prediction}. Where the graph's step hooks allow it (``joined.hooks_leave``), one simulation
    runs them all: the first in ``base`` itself, each other as a copy of the blocks it changes (its estimator and
    the model it feeds back through) joined to ``base`` (``joined.join``), reading the physical system, the
    excitation and the noise from ``base``'s blocks, which compute the same numbers; else one after another."""
    est, known = base.role("estimator"), base.roles["known"]
    prediction = base.role_signal("prediction")
    structure = (list(base.blocks), dict(base.sources))
    own = joined.own_blocks(structure, {est.name}, [prediction])
    together = joined.hooks_leave(base.hooks, own, est.name)
    first, *rest = etas
    for which in etas if not together else [first]:
        _restore(base, start)
        _freeze(base, etas[which])
        if states[which] is not None:
            base.role("known").x.copy_(states[which])
        if not together:
            yield {which: prediction}
    if not together:
        return
    signals = {first: prediction}
    for which in rest:
        block = functools.partial(joined.held_block, base, est.name, etas[which])
        # the copy's known model (joined under a name of its own; the signal names it) starts from its own state
        at = joined.join(base, structure, own, [prediction, (known, "x")], which, block)
        signals[which] = at[prediction]
        if states[which] is not None and known in own:
            base.blocks[at[(known, "x")][0]].x.copy_(states[which])
    yield signals


def _score(scores: Mapping[str, _Scores], names: list, rec: Mapping[str, torch.Tensor]) -> None:
    """Add a stretch's record (``_stream``) to the scores of each of ``names``: y against its prediction."""
    for which in names:
        scores[which].add(rec["y"], rec[which])


def _stream(graph, steps: int, signals: Mapping[str, tuple[str, str]], take) -> None:
    """Run ``graph`` (changed) ``steps`` steps, handing each stretch's record of ``signals`` ({name: signal}),
    {name: (C, B, width) float64}, to ``take``; the stretches are recorded into the same buffers."""
    widths = {k: graph.blocks[blk].outputs[port] for k, (blk, port) in signals.items()}
    stretch = max(1, min(steps, STRETCH_BYTES // (8 * graph.batch_size * max(widths.values()))))
    bufs = {k: torch.empty(stretch, graph.batch_size, w, dtype=_dtype(graph), device=graph.k.device)
            for k, w in widths.items()}
    for done in range(0, steps, stretch):
        C = min(stretch, steps - done)
        graph.advance(C, record={signals[k]: b[:C] for k, b in bufs.items()})
        take({k: b[:C].to(torch.float64) for k, b in bufs.items()})


def _simulate(g, steps: int, x0: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
    """y and y_hat of graph ``g`` (changed) run ``steps`` steps from the known model's state ``x0`` (None: as it
    is), (steps, B, width) float64 each."""
    if x0 is not None:
        g.role("known").x.copy_(x0)
    tr = g.run(steps, record={"y": g.roles["measured"], "y_hat": g.roles["prediction"]})
    return tr["y"].to(torch.float64), tr["y_hat"].to(torch.float64)


def _restore(graph, start: Mapping[str, torch.Tensor]) -> None:
    """Put ``graph``'s buffers back to ``start`` (its ``snapshot``), writing only those that differ:
    the parameters a simulation leaves as they were are not written, so that the native engine's program made
    for them stays valid (``rcotorch.engine.lowering.ProgramCache``)."""
    now = dict(graph.named_buffers())
    if any(k not in now or now[k].shape != v.shape for k, v in start.items()):
        graph.load_state_dict(start)
        return
    with torch.no_grad():
        for key, value in start.items():
            if not torch.equal(now[key], value):
                now[key].copy_(value)


def _fit_state(graph, steps: int, passes: int = 2) -> tuple[torch.Tensor | None, bool]:
    """The known model's initial state that best explains the first ``steps`` measured samples, per member;
    ``graph`` is left in the state it was given. A known model may name the entries of its state a fit may move
    (its attribute ``fitted_states``, indices; e.g. not a state that carries a past input); the others keep
    their value."""
    known = graph.role("known")
    x = getattr(known, "x", None)
    if not isinstance(x, torch.Tensor) or x.dim() != 2 or x.shape[1] == 0:
        return None, False
    start = snapshot(graph)                         # each simulation from it, and at the end
    try:
        return _fit_from(graph, x, start, steps, passes)
    finally:
        _restore(graph, start)


def _fit_from(graph, x: torch.Tensor, start: Mapping[str, torch.Tensor], steps: int, passes: int
              ) -> tuple[torch.Tensor | None, bool]:
    """``_fit_state``'s Gauss-Newton passes, each simulation of ``graph`` from ``start``. A pass whose first
    simulation lands where the last step's linearization predicted (to a tenth of the square root of the dtype's
    epsilon, relative to the residual it started from: the outputs are affine in the state, as with a linear known
    model in a linear loop) ends the fit there: the last step was already the least-squares one."""
    x0 = x.detach().clone().to(torch.float64)
    B, n = x0.shape
    moved = list(getattr(graph.role("known"), "fitted_states", None) or range(n))
    fitted = torch.ones(B, dtype=torch.bool, device=x0.device)

    def simulate(x0: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        _restore(graph, start)
        return _simulate(graph, steps, x0)
    predicted = before = None      # the residual the last step's linearization predicts, and the one it left
    tol = 0.1 * torch.finfo(x.dtype).eps ** 0.5
    for _ in range(passes):
        y, y_hat = simulate(x0.to(x.dtype))
        r = (y - y_hat).permute(1, 0, 2).reshape(B, -1)                       # (B, steps * width)
        if predicted is not None and bool(((r - predicted).norm(dim=1) <= tol * before).all()):
            break                  # the outputs are affine in the state: the last step was the least-squares one
        scale = 1e-6 * torch.clamp(x0.abs().amax(1, keepdim=True), min=1.0)
        S = torch.zeros(B, r.shape[1], n, dtype=torch.float64, device=x0.device)
        for i in moved:
            step = torch.zeros_like(x0)
            step[:, i:i + 1] = scale
            _, y_i = simulate((x0 + step).to(x.dtype))
            S[:, :, i] = ((y_i - y_hat).permute(1, 0, 2).reshape(B, -1)) / scale
        # A member whose outputs do not respond finitely to its state (a diverged or stiff model) keeps its
        # state; the others take their least-squares step (unobservable directions: 0).
        ok = torch.isfinite(S).flatten(1).all(1) & torch.isfinite(r).all(1)
        fitted &= ok
        S = torch.where(ok.reshape(-1, 1, 1), S, 0.0)
        delta = torch.linalg.pinv(S, rtol=1e-10) @ torch.where(ok.reshape(-1, 1), r, 0.0).unsqueeze(-1)
        x0 = x0 + delta.squeeze(-1)
        predicted = r - (S @ delta).squeeze(-1)
        before = r.norm(dim=1) + torch.finfo(x.dtype).tiny
        if not bool(torch.isfinite(x0).all()):
            return None, False
    return x0.to(x.dtype), bool(fitted.all())

