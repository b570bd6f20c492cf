"""The bias of a sampled feedback against the continuous physics it stands for.

The identified subsystem acts on the known model once per sample: u(k) = f_theta(s(k)), held over the sample.
Where the known model samples a continuous system (an ``LTI`` built from continuous matrices, discretized by
zero-order hold) and the physics the identified subsystem stands for acts continuously (a stiffness, a damping,
a friction: u(t) = f_theta(s(t)) at every instant), no sampled theta reproduces the continuous one exactly: the
theta that best fits data of the continuous system differs from its physical value by O(Ts) (Franklin, Powell
and Workman, *Digital Control of Dynamic Systems*, ch. 6, on emulating a continuous controller). That
difference is a bias no interval width covers; it shrinks with Ts, not with the data.

``ContinuousPrediction`` simulates the refined model with the feedback acting continuously, stretch by stretch
of recorded signals: the known model's continuous matrices in feedback with the identified subsystem's map, the
other inputs held over each sample as the ZOH model holds them. Where f_theta is linear in its inputs (a static gain)
the closed loop is one linear system, discretized exactly; otherwise it is integrated with ``SUBSTEPS``
exponential-midpoint steps per sample. With y_c the sampled model's prediction and y_f the continuous one's,
both at theta, the sampled fit to data of the continuous system (z = y - y_c) moves theta by the Gauss-Newton
step

    b = (sum J^T W J)^-1 sum J^T W (z_f - z_c),    z_f - z_c = -(y_f - y_c),    J = dz / d eta,

evaluated at the estimate instead of the truth (an error of second order in b): the estimate of the sampled
model minus the continuous physics' parameter. ``rcotorch.verdict.intervals.replay`` sums it over the window.

Whether the physics acts continuously is the graph's declaration ``graph.feedback``: ``'continuous'`` or
``'sampled'`` (``rcotorch.refinement`` sets ``'sampled'`` for a truth given as a block in discrete feedback,
``'continuous'`` for a physical system or recorded data).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch

SUBSTEPS = 1       # exponential-midpoint steps per sample for a feedback map that is not linear


def plan(graph) -> dict | str:
    """How to simulate ``graph``'s refined model with a continuous feedback, or why it cannot be done (a
    sentence). The plan names the known block, its input fed by the estimator, the estimator's input ports with
    their sources, and the signals to record."""
    if getattr(graph, "feedback", "sampled") != "continuous":
        return "the graph declares a sampled feedback"
    if "known" not in graph.roles or "prediction" not in graph.roles:
        return "the graph has no known model and prediction roles"
    known, est = graph.role("known"), graph.role("estimator")
    form = known.continuous_form() if hasattr(known, "continuous_form") else None
    if form is None:
        return f"the known model '{known.name}' is not a sampled continuous system"
    if est.nc or not est.proper:
        return "the identified subsystem has memory (nc > 0) or is not exactly proper"
    fed = [p for p in known.inputs if graph.sources.get((known.name, p)) == (est.name, "u")]
    if len(fed) != 1:
        return f"the known model's input from the estimator is not one port ({fed})"
    u_port = fed[0]
    if graph.role_signal("prediction")[0] != known.name:
        return "the prediction is not an output of the known model"
    sees = {}
    for p in est.ports:
        src = graph.sources.get((est.name, p))
        if src is None:
            return f"the estimator's input '{p}' has no source"
        sees[p] = src
    cu = known._in_slices[u_port]
    for blk, port in sees.values():
        if blk == known.name and bool(known.D[:, known._out_slices[port], cu].abs().amax() > 0):
            return f"the known model's output '{port}' depends on u at once (an algebraic loop)"
    record = [graph.sources[(known.name, p)] for p in known.inputs if p != u_port]
    record += [src for src in sees.values() if src[0] != known.name]
    return {"known": known.name, "u_port": u_port, "sees": sees, "record": list(dict.fromkeys(record))}


def _zoh(A: torch.Tensor, B: torch.Tensor, dt: float) -> tuple[torch.Tensor, torch.Tensor]:
    """exp([[A, B], [0, 0]] dt) = [[Ad, Bd], [0, I]], batched."""
    n, m = A.shape[-1], B.shape[-1]
    batch = np.broadcast_shapes(tuple(A.shape[:-2]), tuple(B.shape[:-2]))   # (torch's imports sympy)
    M = A.new_zeros(*batch, n + m, n + m)
    M[..., :n, :n] = A
    M[..., :n, n:] = B
    E = torch.linalg.matrix_exp(M * dt)
    return E[..., :n, :n], E[..., :n, n:]


class ContinuousPrediction:
    """The prediction (the known model's measured output) of ``graph``'s refined model with its feedback acting
    continuously, simulated stretch by stretch from the known model's state ``x0`` (B, n): ``predict`` takes the
    next stretch's recorded signals and carries the state on. theta is the estimator's as it is (nothing is
    changed)."""

    def __init__(self, graph, plan_: Mapping, x0: torch.Tensor):
        known, est = graph.blocks[plan_["known"]], graph.role("estimator")
        f64 = torch.float64
        self.graph, self.known, self.est = graph, known, est
        A, Bc = (t.to(f64) for t in known.continuous_form())
        self.C, self.D = known.C.to(f64), known.D.to(f64)
        dt = float(known.dt)
        self.u_port, self.sees = plan_["u_port"], plan_["sees"]
        ins, outs = known._in_slices, known._out_slices
        self.y_port = graph.role_signal("prediction")[1]
        self.held = [p for p in known.inputs if p != self.u_port]
        self.x = x0.to(f64)
        B = self.x.shape[0]
        Bu = Bc[:, :, ins[self.u_port]]
        self.gain = _linear_gain(est, B)
        if self.gain is not None:
            # u = sum_p K_p s_p + u0 is linear: the continuous closed loop x' = A_cl x + B_v v with v the held
            # inputs (the known model's other inputs, the estimator's other inputs, 1), discretized exactly.
            K, u0 = self.gain
            A_cl = A.expand(B, -1, -1).clone()
            cols = []
            for p, (blk, port) in self.sees.items():
                if blk == known.name:
                    A_cl = A_cl + Bu @ K[p] @ self.C[:, outs[port]]
            for q in self.held:
                term = Bc[:, :, ins[q]]
                for p, (blk, port) in self.sees.items():
                    if blk == known.name:
                        term = term + Bu @ K[p] @ self.D[:, outs[port], ins[q]]
                cols.append(term.expand(B, -1, -1))
            for p, (blk, _) in self.sees.items():
                if blk != known.name:
                    cols.append((Bu @ K[p]).expand(B, -1, -1))
            cols.append((Bu @ u0.unsqueeze(-1)).expand(B, -1, -1))
            self.Phi, self.Gamma = _zoh(A_cl, torch.cat(cols, dim=2), dt)
        else:
            # a map that is not linear: exponential-midpoint steps of h = dt / SUBSTEPS, u held over half a step
            # to predict the midpoint, then over the step from the midpoint's u
            h = dt / SUBSTEPS
            Bh = torch.cat([Bc[:, :, ins[q]] for q in self.held] + [Bu], dim=2)
            self.Ph, self.Gh = _zoh(A, Bh, h)
            self.Ph2, self.Gh2 = _zoh(A, Bh, h / 2)

    def _inputs_of(self, signals: Mapping[tuple, torch.Tensor], k: int) -> dict[str, torch.Tensor]:
        return {p: signals[self.graph.sources[(self.known.name, p)]][k].to(torch.float64) for p in self.held}

    def _seen(self, x: torch.Tensor, held_now: Mapping[str, torch.Tensor], signals, k: int) -> dict:
        ins, outs, out = self.known._in_slices, self.known._out_slices, {}
        for p, (blk, port) in self.sees.items():
            if blk == self.known.name:
                v = (self.C[:, outs[port]] @ x.unsqueeze(-1)).squeeze(-1)
                for q, cs in ins.items():
                    if q != self.u_port:
                        v = v + (self.D[:, outs[port], cs] @ held_now[q].unsqueeze(-1)).squeeze(-1)
                out[p] = v
            else:
                out[p] = signals[(blk, port)][k].to(torch.float64)
        return out

    def _u_of(self, values: Mapping[str, torch.Tensor]) -> torch.Tensor:
        dtype = self.est.theta.dtype
        return self.est.static_output({p: v.to(dtype) for p, v in values.items()}).to(torch.float64)

    def _predict(self, x: torch.Tensor, held_now: Mapping[str, torch.Tensor], u: torch.Tensor) -> torch.Tensor:
        ins, ys = self.known._in_slices, self.known._out_slices[self.y_port]
        y = (self.C[:, ys] @ x.unsqueeze(-1)).squeeze(-1)
        for q, cs in ins.items():
            v = u if q == self.u_port else held_now[q]
            y = y + (self.D[:, ys, cs] @ v.unsqueeze(-1)).squeeze(-1)
        return y

    def predict(self, signals: Mapping[tuple, torch.Tensor], steps: int) -> torch.Tensor:
        """The prediction over the next ``steps`` samples, (steps, B, n_y) float64. ``signals``: the recorded
        signals of the plan's ``record`` over those samples, each (>= steps, B, width)."""
        x = self.x
        B, ys = x.shape[0], self.known._out_slices[self.y_port]
        out = x.new_empty(steps, B, ys.stop - ys.start)
        mv = lambda M, v: (M @ v.unsqueeze(-1)).squeeze(-1)             # noqa: E731
        for k in range(steps):
            held_now = self._inputs_of(signals, k)
            now = self._seen(x, held_now, signals, k)
            u = self._u_of(now)
            out[k] = self._predict(x, held_now, u)
            if self.gain is not None:
                v = [held_now[q] for q in self.held] + [now[p] for p, (blk, _) in self.sees.items()
                                                        if blk != self.known.name]
                v.append(x.new_ones(B, 1))
                x = mv(self.Phi, x) + mv(self.Gamma, torch.cat(v, dim=1))
                continue
            hv = [held_now[q] for q in self.held]
            for _ in range(SUBSTEPS):
                mid = mv(self.Ph2, x) + mv(self.Gh2, torch.cat(hv + [u], 1))
                u_mid = self._u_of(self._seen(mid, held_now, signals, k))
                x = mv(self.Ph, x) + mv(self.Gh, torch.cat(hv + [u_mid], 1))
                u = self._u_of(self._seen(x, held_now, signals, k))
        self.x = x
        return out


def _linear_gain(est, B: int) -> tuple[dict[str, torch.Tensor], torch.Tensor] | None:
    """The estimator's map as u = sum_p K_p s_p + u0 ({port: (B, n_u, width)}, (B, n_u)) where it is affine in
    its inputs (checked on random inputs), else None."""
    f64 = torch.float64
    widths = dict(est.ports)

    def u_at(values: Mapping[str, torch.Tensor]) -> torch.Tensor:
        return est.static_output({p: v.to(est.theta.dtype) for p, v in values.items()}).to(f64)
    zero = {p: torch.zeros(B, w, dtype=f64, device=est.theta.device) for p, w in widths.items()}
    u0 = u_at(zero)
    K = {}
    for p, w in widths.items():
        cols = []
        for j in range(w):
            probe = dict(zero)
            e = torch.zeros(B, w, dtype=f64, device=est.theta.device)
            e[:, j] = 1.0
            probe[p] = e
            cols.append(u_at(probe) - u0)
        K[p] = torch.stack(cols, dim=2)
    gen = torch.Generator(device="cpu").manual_seed(0)
    for _ in range(2):
        probe = {p: 3 * torch.randn(B, w, generator=gen, dtype=f64).to(est.theta.device) for p, w in widths.items()}
        lin = u0 + sum((K[p] @ v.unsqueeze(-1)).squeeze(-1) for p, v in probe.items())
        got = u_at(probe)
        if not bool(torch.allclose(got, lin, rtol=1e-9, atol=1e-9 * float(lin.abs().amax().clamp_min(1.0)))):
            return None
    return K, u0
