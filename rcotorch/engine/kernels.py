"""The compiled kernels (``rcotorch.engine._engine``, built from ``csrc/`` when the package is installed).

The bottom of the import graph: this module imports only torch. It loads the extension, takes the engine's
op codes and record layouts from the names the extension exports (``csrc/engine.h`` is their one
definition), and wraps the kernels with the checks they need:

* ``run``: a lowered graph for T steps (``rcotorch.engine.lowering`` builds the program);
* ``rls_``: ``rls_update`` in place through the same RLS code as the estimator's native step;
* ``uniform_grid``: the integer hashing behind ``rcotorch.engine.rng.normal`` on a grid;
* ``health_bounds``: the member health checks' bounds (``rcotorch.verdict.health``) of every member;
* ``window_gram``: the sum of the regressors' outer products over the estimator's window;
* ``window_sums``, ``residual_sums``, ``markov_filter``: the intervals' replay, stretch by stretch (its Gram and
  scores' sums, the residual checks' sums, the regressors);

and ``empty``, the allocation of the large buffers the engine fills (recordings).

Without the extension (no C compiler when the package was installed) everything runs on PyTorch and the
first use warns once. ``RCOTORCH_ENGINE=torch`` turns the kernels off for the whole process, and
``disabled()`` for a block of code (``Graph(engine='torch')`` steps inside it, so that engine runs no C).
"""

from __future__ import annotations

import contextlib
import contextvars
import ctypes
import enum
import os
import sys
import threading
import warnings
from typing import NamedTuple

import torch

try:
    from . import _engine
    _WHY: str | None = None
except ImportError as e:  # built without a compiler, or not built at all
    _engine = None
    _WHY = (f"the compiled engine rcotorch.engine._engine is not installed ({e}); reinstall rcotorch with a C compiler "
            "(pip install .) to build it")

if _engine is not None and os.environ.get("RCOTORCH_ENGINE", "auto") == "torch":
    _WHY = "RCOTORCH_ENGINE=torch"


def _names(attr: str, start: int = 0) -> dict[str, int]:
    return {name: i + start for i, name in enumerate(getattr(_engine, attr, ()))}


OP = _names("OPS", 1)                          # op code of each instruction (engine.h: RCO_OPS)
#: The layout of each op's record (RCO_OPS), and each layout's fields in order (RCO_<LAYOUT>_FIELDS).
OP_LAYOUT: dict[str, str] = dict(zip(getattr(_engine, "OPS", ()), getattr(_engine, "OP_LAYOUTS", ())))
LAYOUT: dict[str, tuple[str, ...]] = dict(getattr(_engine, "LAYOUTS", {}))
#: The tables after a layout's fields, in order: (table, the field counting its entries, the entries' layout).
TABLES: dict[str, list[tuple[str, str, str]]] = {
    layout: [(table, count, entry) for owner, table, count, entry in getattr(_engine, "TABLES", ()) if owner == layout]
    for layout in LAYOUT}
FACTOR = _names("FACTORS")                     # kinds of feature factors (RCO_FACTORS)
BIND_FIELD = _names("BIND_FIELDS")             # fields of a binding record (RCO_BIND_FIELDS)
KIND = _names("KINDS")                         # element kinds of a binding (RCO_KINDS; its MODE: BindMode)
OBS_FIELD = _names("OBS_FIELDS")               # fields of an observer record (RCO_OBS_FIELDS)
OBSERVER = _names("OBSERVERS")                 # kinds of observers (RCO_OBSERVERS)
HEADER = getattr(_engine, "HEADER", 2)         # ints before an instruction's arguments (op, length)
NOISE_SLOTS = getattr(_engine, "NOISE_SLOTS", 1)  # slots of a noise channel's buffer (steps drawn ahead, in pairs)
LANE_WIDTHS: tuple[int, ...] = getattr(_engine, "LANE_WIDTHS", (1,))


class BindMode(enum.IntEnum):
    """The MODE field of a binding record (RCO_BIND_FIELDS): which way its tensor moves between PyTorch and the
    slots. The C code tests its bits (engine.h's RCO_BIND_MODE_BITS, exported as ``_engine.BIND_LOAD`` 1,
    ``BIND_STORE`` 2 and ``BIND_FIRST_LANE`` 4; lanes.h's ``load`` before the steps and ``store`` after them);
    these are the combinations lowering writes."""

    #: A parameter: copied into its slots before the steps, never back.
    LOAD = 1
    #: A signal: copied out of its slots after the steps (the graph's last outputs), never in.
    STORE = 2
    #: A state buffer: copied in before the steps and back after them.
    LOAD_AND_STORE = 3
    #: A parameter the operations read in the first lane only (their SHARED field): where the members share it
    #: (MSTRIDE 0), copied into that lane alone; else as LOAD.
    LOAD_FIRST_LANE = 5


_ALLOWED = contextvars.ContextVar("rcotorch_kernels_allowed", default=True)
_WARNED = threading.Event()


def available() -> bool:
    """Whether the compiled kernels can be used here (the first call without them warns once)."""
    if _WHY is not None and _WHY != "RCOTORCH_ENGINE=torch" and not _WARNED.is_set():
        _WARNED.set()
        warnings.warn(f"rcotorch: native engine unavailable, running on PyTorch only ({_WHY})", stacklevel=2)
    return _WHY is None


def why_unavailable() -> str | None:
    """Why the compiled kernels cannot be used, or None."""
    return _WHY


def allowed() -> bool:
    """Whether code running now may call the kernels: available and not inside ``disabled()``."""
    return _ALLOWED.get() and available()


@contextlib.contextmanager
def disabled():
    """Run a block of code without the compiled kernels (PyTorch operations only)."""
    token = _ALLOWED.set(False)
    try:
        yield
    finally:
        _ALLOWED.reset(token)


#: Work (members times steps of one call) below which a call runs on one thread: starting and joining the other
#: threads costs more than they give, most of all on a busy machine.
PARALLEL_WORK = 1 << 16


def threads(batch: int | None = None, steps: int = 1) -> int:
    """Threads for a call on ``batch`` members for ``steps`` steps: torch's thread count where the work is
    large enough to share (two members or more and ``PARALLEL_WORK`` member-steps), else one."""
    if batch is not None and (batch < 2 or batch * steps < PARALLEL_WORK):
        return 1
    return max(1, torch.get_num_threads())


def lanes(batch: int, nthreads: int | None = None) -> int:
    """The lane width for a batch: members run VL at a time; small batches in narrow lanes, so one member does
    not pay for sixteen, and a second thread has chunks to take."""
    per_thread = max(1, batch // (threads() if nthreads is None else nthreads))
    return max([w for w in LANE_WIDTHS if w <= per_thread] or [1])


def estimator_scratch(n_u: int, n_z: int, n_phi: int, n_theta: int, n_rows: int) -> int:
    """Scratch slots of one native estimator update with ``n_rows`` rows in its RLS step (the C code's count)."""
    return _engine.rco_scratch(n_u, n_z, n_phi, n_theta, n_rows)


def bump(*tensors: torch.Tensor) -> None:
    """Tell PyTorch (and ``rcotorch.engine.memo``) that C code wrote these tensors."""
    for t in tensors:
        torch.autograd.graph.increment_version(t)


def run(code: torch.Tensor, consts: torch.Tensor, binds: torch.Tensor, ptrs: torch.Tensor, counters: torch.Tensor,
        obs: torch.Tensor, nslots: int, steps: int, batch: int) -> None:
    """Run a lowered program (int64 ``code``, float64 ``consts``, binding and observer records, pointer and
    counter tables, all contiguous CPU tensors) for ``steps`` steps of ``batch`` members."""
    _engine.run(code.data_ptr(), code.numel(), consts.data_ptr(), binds.data_ptr(), binds.numel() // len(BIND_FIELD),
                ptrs.data_ptr(), counters.data_ptr(), obs.data_ptr(), obs.numel() // len(OBS_FIELD), nslots, steps,
                batch, lanes(batch, threads(batch, steps)), threads(batch, steps))


def rls_(theta: torch.Tensor, P: torch.Tensor, psi: torch.Tensor, z_r: torch.Tensor, lam, r_inv,
         active: torch.Tensor | None) -> torch.Tensor | None:
    """``rls_update`` in place (theta (B, n), P (B, n, n), psi (B, n, l), z_r (B, l), lam a float or (B,) / (1,),
    r_inv a float or (l, l)); returns ok (B,) before ``active`` is applied, or None where the kernel does not
    apply (not allowed here, not the CPU or float64, not contiguous): then the caller runs PyTorch."""
    if not allowed() or theta.device.type != "cpu" or theta.dtype != torch.float64 or P.dtype != torch.float64:
        return None
    if not (theta.is_contiguous() and P.is_contiguous()):
        return None
    B, n = theta.shape
    l = psi.shape[-1]
    psi = psi.to(torch.float64).reshape(B, n, l).contiguous()
    z_r = z_r.to(torch.float64).reshape(B, l).contiguous()
    lam_one = not isinstance(lam, torch.Tensor) and float(lam) == 1.0
    lam_t = (lam.to(torch.float64).reshape(-1) if isinstance(lam, torch.Tensor) else
             torch.tensor([float(lam)], dtype=torch.float64)).contiguous()
    if lam_t.numel() not in (1, B):
        return None
    r = torch.as_tensor(r_inv, dtype=torch.float64)
    r = (r * torch.eye(l, dtype=torch.float64) if r.dim() == 0 else r.reshape(l, l)).contiguous()
    act = None if active is None else active.reshape(B).to(torch.uint8).contiguous()
    ok = torch.empty(B, dtype=torch.uint8)
    _engine.rls(theta.data_ptr(), P.data_ptr(), psi.data_ptr(), z_r.data_ptr(), lam_t.data_ptr(),
                1 if lam_t.numel() > 1 else 0, int(lam_one), r.data_ptr(), 0 if act is None else act.data_ptr(),
                ok.data_ptr(), B, n, l, lanes(B), threads())
    bump(theta, P)
    return ok.bool()


def ring_multiplier(W: int) -> int:
    """The multiplier with which the engine takes a step's row k mod W of an estimator's ring without a division
    (engine.c, ring_row): 2**64 // W + 1, as the int64 of its 64 bits.

    Parameters
    ----------
    W : int
        The ring's rows, 1 <= W < 2**32.

    Returns
    -------
    int
    """
    m = ((1 << 64) // W + 1) & ((1 << 64) - 1)
    return m - (1 << 64) if m >= 1 << 63 else m


def uniform_grid(seeds: torch.Tensor, members: torch.Tensor, start: int, length: int, width: int
                 ) -> tuple[torch.Tensor, torch.Tensor] | None:
    """The two uniforms behind ``rng.normal(seed, member, step, comp)`` on the grid (B, length, width) of pairs
    of steps (pair p: the steps 2p and 2p + 1; the pairs start..start+length-1), bit for bit, or None where the
    kernels are not allowed (or off the CPU)."""
    if not allowed() or seeds.device.type != "cpu":
        return None
    seeds = seeds.reshape(-1).long().contiguous()
    members = members.reshape(-1).long().contiguous()
    B = seeds.numel()
    u1 = torch.empty(B, length, width, dtype=torch.float64)
    u2 = torch.empty_like(u1)
    _engine.uniform_grid(B, seeds.data_ptr(), members.data_ptr(), int(start), int(length), int(width),
                         u1.data_ptr(), u2.data_ptr(), threads())
    return u1, u2


def health_bounds(P: torch.Tensor, theta: torch.Tensor, u_now: torch.Tensor, phi_rms: torch.Tensor,
                  bound: torch.Tensor, windup: torch.Tensor, alive: torch.Tensor, reasons: tuple[int, int, int, int]
                  ) -> torch.Tensor | None:
    """The codes of ``Health._bounds_exceeded`` (P (B, n, n), theta (B, n_u, n_phi), u_now (B, n_u), phi_rms
    (B, n_phi), bound and windup (B,), alive (B,); ``reasons``: the codes of P not positive definite, windup,
    u runaway, theta runaway), or None where the kernel does not apply (not allowed here, not the CPU or
    float64): then the caller runs PyTorch."""
    if not allowed() or any(t.device.type != "cpu" or t.dtype != torch.float64 for t in (P, theta, u_now)):
        return None
    B, n = P.shape[0], P.shape[-1]
    n_u, n_phi = theta.shape[1], theta.shape[2]

    def f64(t: torch.Tensor, *shape: int) -> torch.Tensor:
        return t.detach().to(torch.float64).expand(*shape).contiguous()
    args = [f64(P, B, n, n), f64(theta, B, n_u, n_phi), f64(u_now, B, n_u), f64(phi_rms, B, n_phi),
            f64(bound, B), f64(windup, B), alive.reshape(B).to(torch.uint8).contiguous()]
    args.append(torch.tensor(reasons, dtype=torch.int64))
    code = torch.empty(B, dtype=torch.int64)
    _engine.health_bounds(B, n, n_u, n_phi, *(t.data_ptr() for t in args), code.data_ptr(), threads())
    return code


def window_sums(z: torch.Tensor, moved: torch.Tensor, psi: torch.Tensor, d: torch.Tensor | None, eps: torch.Tensor,
                own: torch.Tensor, t0: int, measured: int, weight: torch.Tensor, norm: torch.Tensor | None,
                gram: torch.Tensor, ring: torch.Tensor, score_gram: torch.Tensor, moving: torch.Tensor) -> bool:
    """The intervals' replay sums over a stretch (``rcotorch.verdict.intervals._WindowSums``): from time-major
    float64 records z (C, B, n_z), moved (C, B, n_z, n), psi (C, B, n_z, n) and d (C, B, n_z) or None, with eps
    (B, n), each member's first measured step ``own`` (B,) int64, ``measured`` steps each, the stretch's first
    step ``t0``, the weight W (n_z, n_z) and ``norm`` (B,) (1 / s^2 of normalized regressors, None if not): adds
    g g^T, g = [J, z, d, psi / m, J / m, z / m], to the upper triangle of ``gram`` (B, K, K) in the blocks
    [J, z, d] x [J, z, d], psi / m x [psi / m, J / m] and z / m x z / m (the others stay 0), and takes the scores
    s = (psi / m)^T W (z / m), 0 outside a member's measured steps, into their long-run sums in place
    (``_ScoreSums``): ``score_gram`` (B, n, n) += s s^T and ``moving`` (B, n, n) += S S^T, S the sum of the last
    L + 1 scores, the L before each step in ``ring`` (B, L, n), oldest first, which the stretch's last L replace.
    Returns False where the kernel does not apply (not allowed here, not the CPU), having changed nothing."""
    if not allowed() or z.device.type != "cpu":
        return False
    C, B, nz = z.shape
    n = moved.shape[3]
    f64 = lambda t: t.to(torch.float64).contiguous()      # noqa: E731
    args = [f64(z), f64(moved), f64(psi), None if d is None else f64(d), f64(eps), own.to(torch.int64).contiguous(),
            f64(weight), None if norm is None else f64(norm.reshape(-1).expand(B))]
    K = 3 * nz * n + 3 * nz
    L = ring.shape[1]
    for name, t, shape in (("gram", gram, (B, K, K)), ("ring", ring, (B, L, n)), ("score_gram", score_gram, (B, n, n)),
                           ("moving", moving, (B, n, n))):
        if t.dtype != torch.float64 or not t.is_contiguous() or tuple(t.shape) != shape:
            raise ValueError(f"window_sums: {name} must be a contiguous float64 {shape} tensor")
    _engine.window_sums(C, B, nz, n, int(t0), int(measured), *(0 if t is None else t.data_ptr() for t in args),
                        gram.data_ptr(), L, ring.data_ptr() if L else 0, score_gram.data_ptr(), moving.data_ptr(),
                        threads(B, C))
    return True


def residual_sums(z: torch.Tensor, zi: torch.Tensor, y: torch.Tensor, w: torch.Tensor | None, own: torch.Tensor,
                  t0: int, measured: int, zlag: torch.Tensor, wlag: torch.Tensor | None, zring: torch.Tensor,
                  wring: torch.Tensor | None, sums: torch.Tensor, scratch: torch.Tensor | None = None) -> bool:
    """The residual checks' sums over a stretch (``rcotorch.verdict.intervals._ResidualSums``) from time-major
    float64 records z and zi (C, B, n_z), y (C, B, n_y) and w (C, B, n_w) or None, each member's first measured step
    ``own`` (B,) int64 and ``measured`` steps each, the stretch's first step ``t0``; every value counts 0 outside
    its member's measured steps. Adds in place, L = zlag.shape[0] - 1: to zlag (L + 1, B, n_z) z(t) z(t - lag) per
    channel, to wlag (L + 1, B, n_z, n_w) z(t) w(t - lag) per pair, the L values before the stretch in zring
    (B, L, n_z) and wring (B, L, n_w), which the stretch's last L replace, and to sums (B, n_z + 2 n_w + n_y + 3)
    [sum z, sum w, sum w^2, sum |z|^2, sum |zi|^2, sum y, sum |y|^2]. ``scratch``: a float64 tensor the kernel may
    work in, from ``residual_scratch`` (zeros when made, kept from call to call), else it allocates its own.
    Returns False where the kernel does not apply (not allowed here, not the CPU), having changed nothing."""
    if not allowed() or z.device.type != "cpu":
        return False
    C, B, nz = z.shape
    ny, nw, L = y.shape[2], 0 if w is None else w.shape[2], zlag.shape[0] - 1
    shapes = (("zlag", zlag, (L + 1, B, nz)), ("zring", zring, (B, L, nz)), ("sums", sums, (B, nz + 2 * nw + ny + 3)))
    if w is not None:
        shapes += (("wlag", wlag, (L + 1, B, nz, nw)), ("wring", wring, (B, L, nw)))
    for name, t, shape in shapes:
        if t is None or t.dtype != torch.float64 or not t.is_contiguous() or tuple(t.shape) != shape:
            raise ValueError(f"residual_sums: {name} must be a contiguous float64 {shape} tensor")
    f64 = lambda t: None if t is None else t.to(torch.float64).contiguous()      # noqa: E731
    args = [own.to(torch.int64).contiguous(), f64(z), f64(zi), f64(y), f64(w)]
    _engine.residual_sums(C, B, nz, nw, ny, int(t0), int(measured), args[0].data_ptr(), L,
                          *(0 if t is None else t.data_ptr() for t in args[1:]), zlag.data_ptr(),
                          0 if wlag is None else wlag.data_ptr(), zring.data_ptr() if L else 0,
                          wring.data_ptr() if L and w is not None else 0, sums.data_ptr(),
                          0 if scratch is None else scratch.data_ptr(), 0 if scratch is None else scratch.numel(),
                          threads(B, C))
    return True


def residual_scratch(B: int, nz: int, nw: int, lags: int, C: int) -> torch.Tensor | None:
    """A scratch for ``residual_sums`` over stretches of at most C steps (zeros, float64), or None where the kernel
    does not apply."""
    if not allowed():
        return None
    return torch.zeros(_engine.residual_scratch(B, nz, nw, lags, C), dtype=torch.float64)


def markov_filter(phi: torch.Tensor, beta: torch.Tensor, s0: int, T: int) -> torch.Tensor | None:
    """Psi(t)[b, o, j] = sum_{i=0}^{nu-1} beta[b, i, o] phi(t + s0 - i)[b, j] for t = 0 .. T - 1: the regressors of
    a stretch (``RCOEstimator.regressors_over``) from phi time-major (rows, B, n_phi) and the Markov parameters
    beta (B or 1, nu, n_out), as (T, B, n_out, n_phi) float64; None where the kernel does not apply (not allowed
    here, not the CPU, not float64), or where the rows do not reach (s0 < nu - 1 or rows < T + s0)."""
    if not allowed() or phi.device.type != "cpu" or phi.dtype != torch.float64 or beta.dtype != torch.float64:
        return None
    rows, B, n_phi = phi.shape
    nu, n_out = beta.shape[1], beta.shape[2]
    if s0 < nu - 1 or rows < T + s0 or beta.shape[0] not in (1, B):
        return None
    phi, beta = phi.contiguous(), beta.contiguous()
    psi = torch.empty(T, B, n_out, n_phi, dtype=torch.float64)
    _engine.markov_filter(T, B, n_phi, n_out, nu, s0, phi.data_ptr(), beta.data_ptr(), int(beta.shape[0] == 1),
                          psi.data_ptr(), threads(B, T))
    return psi


def window_gram(win: torch.Tensor, n: int) -> torch.Tensor | None:
    """sum_w x x^T over the rows of a time-major window (W, B, m), x = win[w, b, :n], as (B, n, n), or None where
    the kernel does not apply (not allowed here, not the CPU, float64 and contiguous)."""
    if not allowed() or win.device.type != "cpu" or win.dtype != torch.float64 or not win.is_contiguous():
        return None
    W, B, m = win.shape
    out = torch.empty(B, n, n, dtype=torch.float64)
    _engine.window_gram(W, B, m, n, win.data_ptr(), out.data_ptr(), threads())
    return out


class MarkovTarget(NamedTuple):
    """Where ``lti_markov`` writes the Markov parameters in place: value t (t = 0..nu-1) of entry e = r m + k
    (output r, input k) of the member in row ``rows[b]`` goes to the flat elements
    ``offset + rows[b] row_stride + t step_stride + e entry_stride + c copy_stride`` of ``tensor``, for
    c < ``copies`` (engine.c: ``markov_target_t``, at most ``MARKOV_TARGETS`` of them a call).
    ``RCOEstimator._refill_from_system`` writes two: beta itself and the copy of it that the estimator's lowered
    program reads (``rcotorch.estimator.rco.NativeCopy``)."""

    #: A contiguous float64 CPU tensor.
    tensor: torch.Tensor
    #: Its flat element of value 0, entry 0 of row 0.
    offset: int
    #: Elements from one row (member) to the next.
    row_stride: int
    #: Elements from one value t to the next (negative: written in reverse time).
    step_stride: int
    #: Elements from one entry e to the next.
    entry_stride: int
    #: How many times over each value is written.
    copies: int = 1
    #: Elements from one copy to the next.
    copy_stride: int = 0


def lti_markov(A: torch.Tensor, B: torch.Tensor, C: torch.Tensor, D: torch.Tensor, d: int, nu: int,
               targets: list[MarkovTarget] | None = None, rows: torch.Tensor | None = None,
               stable: bool = False) -> torch.Tensor | None:
    """beta_t = -H_(d+t), t = 0..nu-1 (H_0 = D, H_i = C A^(i-1) B) of one system per member, A (Bm, N, N), B (Bm,
    N, m), C (Bm, p, N), D (Bm, p, m); None where the kernel does not apply (not allowed here, not the CPU or
    float64): then the caller runs PyTorch.

    Without ``targets``, returns them as (Bm, nu, p, m). With ``targets`` (``MarkovTarget``), writes them in
    place into the target rows ``rows`` ((Bm,) int64, by default 0..Bm-1) and advances the targets' versions
    (``bump``), as a PyTorch write would; returns the (Bm,) bool tensor of the members written: with ``stable``,
    those whose A has a power A^(2^s), s <= 16, of infinity norm below 1 (spectral radius below 1; the others are
    left to the caller), else all. ``stable`` applies to ``targets`` only.
    """
    for tg in targets or ():
        if not isinstance(tg, MarkovTarget):
            raise TypeError(f"lti_markov: a target must be a MarkovTarget, got {type(tg).__name__}")
    tensors = (A, B, C, D) + tuple(tg.tensor for tg in targets or ())
    if not allowed() or any(t.device.type != "cpu" or t.dtype != torch.float64 for t in tensors):
        return None
    Bm, N, m, p = A.shape[0], A.shape[-1], B.shape[-1], C.shape[1]
    A, B, C, D = (t.detach().contiguous() for t in (A, B, C, D))
    out = None
    if targets is None:
        out = torch.empty(Bm, nu, p, m, dtype=torch.float64)
        targets = [MarkovTarget(out, offset=0, row_stride=nu * p * m, step_stride=p * m, entry_stride=1)]
    row_t = torch.arange(Bm) if rows is None else rows.to(device="cpu", dtype=torch.int64).contiguous()
    flat = []
    for tg in targets:
        if not tg.tensor.is_contiguous():
            raise ValueError("lti_markov: a target must be contiguous")
        # the corners of what is written must lie inside the tensor
        span = [tg.offset + r * tg.row_stride + tt * tg.step_stride + e * tg.entry_stride + c * tg.copy_stride
                for r in (int(row_t.min()), int(row_t.max())) for tt in (0, nu - 1) for e in (0, p * m - 1)
                for c in (0, tg.copies - 1)] if Bm else [0]
        if min(span) < 0 or max(span) >= tg.tensor.numel():
            raise ValueError(f"lti_markov: a target of {tg.tensor.numel()} elements is written at "
                             f"{min(span)}..{max(span)}")
        # as engine.c's markov_target_t reads it: the address of element offset, then the strides and copies
        flat += [tg.tensor.data_ptr() + 8 * tg.offset, tg.row_stride, tg.step_stride, tg.entry_stride, tg.copies,
                 tg.copy_stride]
    spec = torch.tensor(flat, dtype=torch.int64)
    ok = torch.ones(Bm, dtype=torch.bool)
    _engine.lti_markov(Bm, N, m, p, d, nu, A.data_ptr(), B.data_ptr(), C.data_ptr(), D.data_ptr(),
                       0 if rows is None else row_t.data_ptr(), ok.data_ptr() if stable and out is None else 0,
                       spec.data_ptr(), len(targets), lanes(Bm), threads())
    if out is not None:
        return out
    bump(*(tg.tensor for tg in targets))
    return ok


def markov_fd(step: int, h: int, x: torch.Tensor, u: torch.Tensor, col: int, width: int, n_out: int, rows: slice,
              n: int, eps: float, trajectory: bool) -> torch.Tensor:
    """Markov parameters (B, n, rows, width) of compiled maps at the addresses ``step`` ([x, u] -> x) and ``h``
    (x -> n_out values) by central differences (``Nonlinear.markov``): input columns col .. col + width - 1 of
    u, output rows ``rows``, at x (B, n_x) with the inputs held at u (B, m), along the free motion or at x."""
    x, u = x.detach().to(torch.float64).contiguous(), u.detach().to(torch.float64).contiguous()
    B, nx = x.shape
    H = torch.empty(B, n, rows.stop - rows.start, width, dtype=torch.float64)
    _engine.markov_fd(step, h, B, nx, u.shape[1], col, width, n_out, rows.start, rows.stop, n, float(eps),
                      int(bool(trajectory)), x.data_ptr(), u.data_ptr(), H.data_ptr())
    return H


_HUGE = 2 << 20              # the huge page size of x86-64 and arm64 Linux
_MADV_HUGEPAGE = 14


def _libc_madvise():
    try:
        fn = ctypes.CDLL(None, use_errno=True).madvise
    except (OSError, AttributeError):
        return None
    fn.argtypes, fn.restype = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int], ctypes.c_int
    return fn


_MADVISE = _libc_madvise() if sys.platform.startswith("linux") else None


def empty(shape: tuple[int, ...], dtype: torch.dtype, device: torch.device | str = "cpu") -> torch.Tensor:
    """``torch.empty``; a large CPU buffer is first advised to the kernel as huge-page memory.

    The advice (Linux ``madvise(MADV_HUGEPAGE)``, given before anything touches the buffer) lets filling it
    fault once per 2 MiB page rather than once per 4 KiB page. Elsewhere, or where the system refuses, it is a
    plain ``torch.empty``.

    Parameters
    ----------
    shape : tuple of int
        The tensor's shape.
    dtype : torch.dtype
        Its type.
    device : torch.device or str, optional
        Its device.

    Returns
    -------
    torch.Tensor
        Uninitialized.
    """
    t = torch.empty(shape, dtype=dtype, device=device)
    if _MADVISE is not None and t.device.type == "cpu":
        start = -(-t.data_ptr() // _HUGE) * _HUGE                        # the whole huge pages inside the buffer
        end = (t.data_ptr() + t.numel() * t.element_size()) // _HUGE * _HUGE
        if end > start:
            _MADVISE(start, end - start, _MADV_HUGEPAGE)                  # advice only: a refusal changes nothing
    return t
