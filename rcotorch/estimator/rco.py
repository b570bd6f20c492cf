"""The retrospective-cost (RCO) estimator: the identified subsystem and its adaptive update.

The identified subsystem is the linear controller (seed eqs. 6-8)

    u(k) = theta(k) phi(k),
    phi(k) = [ s_1(k-l) for l in lags ; ... ; s_m(k-l) for l in lags ; u(k-1) .. u(k-nc) ]

over regressor signals s_i (input ports such as y0 or w). ``lags`` are 1..nc (strictly proper) or 0..nc
(``proper=True``; lag 0 only with nc = 0 gives the exactly proper static gain u(k) = theta s(k)).
The retrospective error (seed eq. 9) uses the Markov parameters beta_d..beta_(d+nu-1) of the map u -> z:

    z_hat(theta_hat, k) = z(k) + sum_i beta_i [theta_hat - theta(k-i)] phi(k-i)
                        = zeta(k) + Psi(k)^T Theta_hat,  zeta(k) = z(k) - sum_i beta_i u(k-i),

with Theta = theta flattened row-major (entry (i, j) at i * n_phi + j), so Psi^T has entries
sum_i beta_i[z, a] phi(k-i)[j] at column a * n_phi + j. Theta is then updated by ``rls_update`` on
z_R(k) = z_hat(theta(k), k).

Structure: theta's entries are functions of a parameter vector eta, Theta = T eta, with T a 0/1 matrix. A
mask pins entries to zero (their rows of T are zero); ``tie`` lets entries share one parameter (e.g. one
function of a temperature for every altitude node). The update runs on eta with the regressor T^T Psi, so
P is (n_theta x n_theta) over the free parameters only; for a plain estimator T is the identity. The map is
the estimator's ``parameter_map`` (``rcotorch.estimator.parameter_map.ParameterMap``); the identified subsystem as a
transfer function (frequency response, DC gain, python-control export) is computed by ``rcotorch.estimator.transfer``.

A member whose z, Psi or theta becomes non-finite, or whose P loses definiteness, is frozen (theta and P
held, u = 0) and its step recorded in ``diverged_at``; the others go on. Where the optional ``valid`` input is
0 (a skipped measurement) the update is skipped, theta and P held.

Robustness options (each off by default, each a scalar or one value per member):

* ``r_delta``: a penalty r_delta |eta_hat - eta(k)|^2 on the parameters' change, added to the retrospective
  cost at every step. It enters the update as n_theta pseudo-measurement rows sqrt(r_delta) I with residual 0
  (weight 1) next to the rows of z, so the update is the exact minimizer of
  lam^(k+1) |eta - eta_0|^2 / p0 + sum_j lam^(k-j) (|z_hat_j(eta)|^2_R + r_delta |eta - eta(j)|^2).
* ``normalize``: a scale s; the rows of z are divided by m(k) = sqrt(1 + |Psi(k)|_R^2 / s^2) before the update
  (normalized RLS), i.e. step j of the cost is weighted by 1 / m(j)^2. |Psi|_R^2 = sum_p Psi_p^T R Psi_p is the
  regressors' size in the cost's own weight R (the Frobenius norm for R = I), so channels of z in different
  units count as the cost counts them.
* ``p_max``: a bound on trace(P); after an update, a living member whose trace exceeds it has P scaled by
  p_max / trace(P) (covariance windup with lam < 1 and weak excitation).
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import torch

from ..blocks.base import DEFAULT_DTYPE, Block, first_bad, tensor_result
from ..blocks.features import Term, as_terms
from ..engine import kernels, memo
from ..engine.compiled import call_user, compile_features, describe
from ..engine.lowering import NotLowerable
from ..engine.rls import rls_update
from ..errors import ConfigError, DimensionError
from . import transfer
from .parameter_map import ParameterMap

if TYPE_CHECKING:
    import control

# The buffer that holds each robustness option (see ``RCOEstimator._options``).
_OPTION_BUFFER = {"r_delta": "rd_sqrt", "normalize": "norm_inv_s2", "p_max": "p_max"}
# ``regressors_over`` filters phi by this many Markov parameters or more as one depthwise convolution over time
# (one product and sum per parameter below it)
CONVOLVE_NU = 32


@dataclasses.dataclass(frozen=True)
class UpdateOptions:
    """The settings of the estimator's update, one record, as torch's optimizers keep theirs in ``defaults``.

    ``RCOEstimator(..., options=UpdateOptions(...))`` takes them instead of its keywords of the same names, and
    keeps the settings it was made with as ``options`` (``set_options`` replaces the robustness options there
    too). Each value is as given and checked by the estimator that takes it (a scalar, or one value per member
    where the keyword allows it); ``dataclasses.replace(est.options, lam=0.99)`` is another record.

    Parameters
    ----------
    p0 : float or array_like, optional
        Initial covariance P(0) = p0 I, scalar or one per member (B,), finite and > 0.
    lam : float or array_like, optional
        Forgetting factor in (0, 1], scalar or one per member (B,).
    R : float or array_like, optional
        Weight on z, scalar or (n_z, n_z).
    theta_bounds : tuple, optional
        (low, high) box for theta, scalars or (n_u, n_phi); theta is projected onto it after each update.
    r_delta : float or array_like, optional
        Weight of the penalty on the parameters' change (>= 0), scalar or one per member; None: none.
    normalize : float or array_like, optional
        Scale s of normalized regressors (> 0), scalar or one per member; None: not normalized.
    p_max : float or array_like, optional
        Bound on trace(P) (> 0), scalar or one per member; None: unbounded.
    """

    p0: Any = 1.0
    lam: Any = 1.0
    R: Any = 1.0
    theta_bounds: Any = None
    r_delta: Any = None
    normalize: Any = None
    p_max: Any = None


def _update_options(options: UpdateOptions | None, block: str, **keywords) -> UpdateOptions:
    """The update's settings of an estimator: ``options`` where given, else a record of ``keywords``; a keyword
    that differs from its default beside ``options`` is refused (ConfigError naming it)."""
    if options is None:
        return UpdateOptions(**keywords)
    if not isinstance(options, UpdateOptions):
        raise ConfigError(f"block '{block}': options must be an UpdateOptions, got {type(options).__name__}")
    defaults = UpdateOptions()
    given = [key for key, value in keywords.items() if not _is_default(value, getattr(defaults, key))]
    if given:
        raise ConfigError(f"block '{block}': {', '.join(given)} given both as keywords and in options=; give "
                          "each setting once")
    return options


def _is_default(value, default) -> bool:
    """Whether a keyword's value is its default (None, or the number 1.0 of p0, lam and R)."""
    if default is None:
        return value is None
    return isinstance(value, (int, float)) and not isinstance(value, bool) and value == default


class NativeCopy(NamedTuple):
    """The estimator's copy of beta that its lowered native program reads (``RCOEstimator._native_beta``), held in
    ``RCOEstimator._native_copy`` so that new Markov parameters reach a program already made: ``set_markov`` and
    ``_refill_from_system`` write them into ``ring`` in place, and the graph's program cache is told
    (``rcotorch.engine.lowering.refilled``) or made to lower again (``kernels.bump`` of ``beta``)."""

    #: (Bp, n_z * n_u, 2W): beta reversed in time with first_delay zeros after it, twice over (``_laid_out``).
    ring: torch.Tensor
    #: The buffer beta that ``ring`` was laid out from: it stands for that tensor only.
    beta: torch.Tensor


def _markov_convolution(phi: torch.Tensor, beta: torch.Tensor, B: int) -> torch.Tensor:
    """Psi(t)[o, j] = sum_i beta_i[o] phi(t + nu - 1 - i)[j] for t = 0 .. len(phi) - nu: phi (T + nu - 1, B, n_phi)
    filtered by the Markov parameters beta (1 or B, nu, n_out, 1), as one depthwise convolution over time (a
    filter per member, output and regressor), (T, B, n_out, n_phi)."""
    nu, n_out, n_phi = beta.shape[1], beta.shape[2], phi.shape[2]
    x = phi.permute(1, 2, 0).reshape(1, B * n_phi, phi.shape[0])                   # (1, B n_phi, time)
    w = beta[..., 0].flip(1).transpose(1, 2).expand(B, n_out, nu)                 # cross-correlation: flipped
    w = w.unsqueeze(1).expand(B, n_phi, n_out, nu).reshape(B * n_phi * n_out, 1, nu)
    out = torch.nn.functional.conv1d(x, w, groups=B * n_phi)                        # (1, B n_phi n_out, T)
    return out.reshape(B, n_phi, n_out, -1).permute(3, 0, 2, 1)


class RCOEstimator(Block):
    """Identified subsystem u = theta phi with the retrospective-cost RLS update.

    Parameters
    ----------
    signals : Mapping[str, int]
        Input ports and widths, e.g. ``{'y0': 1}`` (the subsystem's input) or ``{'y0': 1, 'w': 1}``. Which
        signals feed phi decides identifiability (see docs/method.md).
    n_u : int, optional
        Width of u (the identified subsystem's output).
    n_z : int, optional
        Width of z (the model error).
    nc : int, optional
        Controller order (number of past samples of each signal and of u).
    features : Term, sequence of Term, or Mapping[str, Term or callable], optional
        Basis functions of the input ports that become phi's regressor signals instead of the ports
        themselves: terms of ``rcotorch.blocks.features`` (one, or a list), e.g.
        ``features=rt.features.power('y0', 3)`` (both engines), or ``{'name': callable}`` where each callable
        maps the dict of port tensors (B, width) to a (B, m) tensor or array (probed with batches of 1 and 2
        when the block is built; compiled for the native engine where numba can, ``lower``). theta stays linear
        in them, so the update is least squares.
    proper : bool, optional
        Also use the present sample s(k) (lag 0), so u(k) depends on s(k) at once.
    feed_u : bool, optional
        Put past u into phi (the controller's poles); False gives an FIR controller.
    mask : array_like of bool, optional
        (n_u, n_phi), True where theta is free; False pins that entry to zero.
    tie : array_like of int, optional
        (n_u, n_phi): entries with the same label share one parameter (labels are any integers; a negative
        label pins the entry to zero, as does ``mask``). For example, with u_j = theta_j1 e_j + theta_j2 e_j^2
        at three nodes j, ``tie=[[0, 1], [0, 1], [0, 1]]`` makes the function the same at every node.
        ``theta_names`` lists one name per parameter.
    p0, lam, R : float or array_like, optional
        The update's initial covariance P(0) = p0 I, forgetting factor and weight on z, as ``UpdateOptions``
        describes them.
    theta0 : array_like, optional
        Initial theta (n_u, n_phi) or (B, n_u, n_phi); zero by default.
    markov : array_like, optional
        beta_d..beta_(d+nu-1) of u -> z as (nu, n_z, n_u) or (B, nu, n_z, n_u), with the relative degree
        ``first_delay`` = d. Usually left out and derived by ``refinement`` from the known model.
    first_delay : int, optional
        d, the delay of the first Markov parameter in ``markov`` (>= 0). d = 0 where u reaches z at once (an
        accelerometer's reading of a force): u(k) = Theta(k) phi(k) is made from theta(k) before z(k) is known,
        and the update then weighs beta_0 [u(k) - Theta phi(k)] like the later terms. A loop through a signal
        the identified subsystem sees at once (a proper estimator on a port that u reaches at once) is refused
        by the graph.
    dt : float, optional
        Sample time [s] (for transfer functions and frequency responses). Left out, the identified subsystem
        has the sample time that comes with its Markov parameters (``set_markov``; ``refinement`` gives the
        known model's): ``sample_time``.
    u_bounds : tuple, optional
        (low, high) saturation of u, scalars or per component (n_u,), e.g. (0, inf) where physics forbids a
        sign (a cooling that cannot heat). The retrospective cost uses the saturated u, the one actually
        applied.
    theta_bounds : tuple, optional
        (low, high) box for theta, scalars or (n_u, n_phi); theta is projected onto it after each update
        (P unchanged).
    r_delta : float or array_like, optional
        Weight of the penalty r_delta |eta - eta(k)|^2 on the parameters' change in the retrospective cost,
        scalar or one per member (>= 0); None (the default) leaves it out. Larger values slow and smooth the
        estimate (noisy data, a member that jumps).
    normalize : float or array_like, optional
        Scale s of normalized regressors, scalar or one per member (> 0): Psi and z_R enter the update divided
        by sqrt(1 + |Psi|_R^2 / s^2) (module docstring), which bounds the step for large signals. None (the
        default): not normalized.
    p_max : float or array_like, optional
        Bound on trace(P), scalar or one per member (> 0): after each update P is scaled by p_max / trace(P)
        where the trace exceeds it (covariance windup). None (the default): unbounded.
    name : str, optional
        The block's name.
    dtype : torch.dtype, optional
        Floating-point type (float64 by default).
    options : UpdateOptions, optional
        The update's settings (``p0``, ``lam``, ``R``, ``theta_bounds``, ``r_delta``, ``normalize``,
        ``p_max``) as one record, given instead of those keywords. Either way the estimator keeps them as
        ``options``; the update reads its buffers (``p0``, ``lam``, ...), which a ``ResetOnChange`` may change
        while the graph runs.

    Raises
    ------
    ConfigError
        If a port is named 'z', 'u' or 'valid', ``nc`` is not a non-negative integer, phi is empty, a setting
        is out of its range, ``tie`` does not hold integers, the mask leaves no free entry, values that
        tied entries share differ, or ``options`` comes with a keyword of its settings other than its
        default.
    DimensionError
        If ``R``, ``mask``, ``tie``, a bound or ``markov`` has the wrong shape, or a feature returns the wrong
        shape.

    Shape
    -----
    n_phi is the length of phi (``phi_names``), n_theta the number of free parameters (``theta_names``).

    - Inputs: one per entry of ``signals``, (B, width); ``z``: (B, n_z); ``valid`` (optional): (B, 1), 0 skips
      the update of that step.
    - Output ``u``: (B, n_u).
    - State: ``theta`` (B, n_u, n_phi), ``P`` (B, n_theta, n_theta).
    """

    def __init__(self, signals: Mapping[str, int], n_u: int = 1, n_z: int = 1, nc: int = 1,
                 features: Term | Sequence[Term] | Mapping[str, Term | Callable[[dict], torch.Tensor]] | None = None,
                 proper: bool = False, feed_u: bool = True, mask=None, tie=None, p0=1.0, lam=1.0, R=1.0,
                 theta0=None, markov=None, first_delay: int = 1, dt: float | None = None,
                 u_bounds=None, theta_bounds=None, r_delta=None, normalize=None, p_max=None,
                 name: str = "identified", dtype=DEFAULT_DTYPE, options: UpdateOptions | None = None):
        signals = dict(signals)
        if "z" in signals or "valid" in signals or "u" in signals:
            raise ConfigError(f"block '{name}': 'z', 'u' and 'valid' are reserved port names")
        super().__init__(name, {**signals, "z": n_z, "valid": 1}, {"u": n_u})
        self.optional_inputs = {"valid"}
        if not isinstance(nc, int) or nc < 0:
            raise ConfigError(f"block '{name}': nc must be a non-negative integer, got {nc!r}")
        self.ports, self.n_u, self.n_z, self.nc = signals, n_u, n_z, nc
        self.options = _update_options(options, name, p0=p0, lam=lam, R=R, theta_bounds=theta_bounds,
                                       r_delta=r_delta, normalize=normalize, p_max=p_max)
        # Regressor signals (name -> width, and one name per channel): the ports themselves, or the features.
        self.terms = as_terms(features) if features is not None else None   # vocabulary only: both engines
        self.features = self._feature_map(features) if features is not None else None
        self.signals = self._probe_features(dtype) if self.features else dict(signals)
        self.signal_names = self._signal_names()
        self.proper, self.feed_u = bool(proper), bool(feed_u and nc > 0)
        self.lags = list(range(0 if proper else 1, nc + 1))
        if not self.lags or not self.signals:
            raise ConfigError(f"block '{name}': phi is empty (signals={list(signals)}, nc={nc}, "
                              f"proper={proper}); use nc >= 1 or proper=True")
        self.n_sig = sum(self.signals.values())
        self.n_phi = len(self.lags) * self.n_sig + (nc * n_u if self.feed_u else 0)
        self.phi_names = self._phi_names()
        self.dt = dt
        self.markov_dt: float | None = None      # the sample time of the Markov parameters (set_markov)
        # Theta = T eta: which parameter each entry of theta holds (mask and tie)
        self.parameter_map = ParameterMap(n_u, self.phi_names, mask, tie, block=name, dtype=dtype)
        self._update_buffers(dtype)
        # the parameters' covariance the end of a run measured (``record_covariance``), None before
        self.covariance = None
        # held (``hold``): an update then only moves the window and the histories on, until ``reset``
        self.held = False
        theta0 = torch.zeros(1, n_u, self.n_phi, dtype=dtype) if theta0 is None else \
            torch.as_tensor(theta0, dtype=dtype, device="cpu").reshape(-1, n_u, self.n_phi)
        theta0 = theta0 * self.parameter_map.unpinned
        self.parameter_map.check_shared("theta0", theta0.reshape(theta0.shape[0], -1))
        self.register_buffer("theta0", theta0)
        self._bound_buffers(u_bounds, dtype)
        self.register_buffer("beta", torch.zeros(1, 0, n_z, n_u, dtype=dtype))
        self.register_buffer("delays", torch.zeros(0, dtype=torch.int64))
        self.window = 0  # first_delay + nu once Markov parameters are set
        # the copy of beta that a lowered native program reads, once the estimator was lowered (``NativeCopy``)
        self._native_copy: NativeCopy | None = None
        if markov is not None:
            self.set_markov(markov, first_delay)
        # Per-member state (created by reset).
        for key, shape in (("theta", (0, n_u, self.n_phi)), ("P", (0, self.n_theta, self.n_theta)),
                           ("past", (0, max(nc, 1), self.n_sig)), ("past_u", (0, max(nc, 1), n_u)),
                           ("win", (0, 0, self.n_phi + n_u)),    # [phi, u] history, see update()
                           ("phi_now", (0, self.n_phi)), ("u_now", (0, n_u)), ("z_r", (0, n_z))):
            self.register_buffer(key, torch.zeros(shape, dtype=dtype))
        self.register_buffer("alive", torch.zeros(0, dtype=torch.bool))
        self.register_buffer("diverged_at", torch.zeros(0, dtype=torch.int64))
        self.register_buffer("k", torch.zeros((), dtype=torch.int64))
        self.register_buffer("_gather", self._phi_gather())
        # Without lag 0, phi is a permutation of [past s | past u]; often the identity (one regressor port).
        tail = self._gather - self.n_sig
        width = max(nc, 1) * (self.n_sig + (n_u if self.feed_u else 0))
        self._phi_is_past = (not self.proper and tail.numel() == width
                             and bool(torch.equal(tail, torch.arange(width))))

    def _update_buffers(self, dtype) -> None:
        """The buffers the update reads from ``options``, each checked: p0 and lam ((1,) or one per member), the
        robustness options (``_options``), and R's inverse with R itself (n_z, n_z)."""
        o = self.options
        for key, value in (("p0", o.p0), ("lam", o.lam)):
            t = torch.as_tensor(value, dtype=dtype, device="cpu").reshape(-1)
            # one value, or one per member; NaN fails both comparisons
            bad = first_bad(t, torch.isfinite(t) & (t > 0) if key == "p0" else (t > 0) & (t <= 1))
            if bad is not None:
                need = "must be finite and positive" if key == "p0" else "must lie in (0, 1]"
                raise ConfigError(f"block '{self.name}': {key} {need}, got {bad}")
            self.register_buffer(key, t)
        self._options(dtype, r_delta=o.r_delta, normalize=o.normalize, p_max=o.p_max)
        n_z = self.n_z
        R = torch.as_tensor(o.R, dtype=dtype, device="cpu")
        R = R * torch.eye(n_z, dtype=dtype) if R.dim() == 0 else R
        if tuple(R.shape) != (n_z, n_z):
            raise DimensionError(f"block '{self.name}': R has shape {tuple(R.shape)}, expected ({n_z}, {n_z})")
        self.register_buffer("r_inv", torch.linalg.inv(R))
        self.register_buffer("r_weight", R.clone(), persistent=False)     # the cost's R (normalized regressors)

    def _bound_buffers(self, u_bounds, dtype) -> None:
        """The saturation of u (``u_bounds``) and the box of theta (``options.theta_bounds``) as buffers, (low,
        high) each, None when unbounded; values that tied entries share must agree."""
        for key, value, width in (("u", u_bounds, self.n_u), ("theta", self.options.theta_bounds,
                                                              self.n_u * self.n_phi)):
            lo, hi = self._bounds(value, f"{key}_bounds", width, dtype)
            if key == "theta" and lo is not None:
                for what, t in (("theta_bounds low", lo), ("theta_bounds high", hi)):
                    if t.dim():
                        self.parameter_map.check_shared(what, t.reshape(1, -1))
            self.register_buffer(f"{key}_low", lo)    # None when unbounded (then not in state_dict)
            self.register_buffer(f"{key}_high", hi)

    def _options(self, dtype, **values) -> None:
        """The robustness options as buffers (None when off): sqrt(r_delta), 1 / s^2 and p_max, each (1,) or (B,)."""
        for key, value in values.items():
            low, stored = {"r_delta": (0.0, torch.sqrt), "normalize": (None, lambda t: 1.0 / (t * t)),
                           "p_max": (None, lambda t: t)}[key]
            t = None if value is None else torch.as_tensor(value, dtype=dtype, device="cpu").reshape(-1)
            if t is not None and not bool(torch.isfinite(t).all() & ((t >= low) if low is not None else (t > 0)).all()):
                bound = "finite and >= 0" if low is not None else "finite and > 0"
                raise ConfigError(f"block '{self.name}': {key} must be {bound}, got {value!r}")
            self.register_buffer(_OPTION_BUFFER[key], None if t is None else stored(t))

    def set_options(self, r_delta=None, normalize=None, p_max=None) -> None:
        """Switch robustness options on after construction, before the graph runs.

        Each value given replaces that option (checked as in the constructor: a scalar or one value per
        member), in the buffers the update reads and in ``options``; None leaves it as it is.

        Parameters
        ----------
        r_delta : float or array_like, optional
            Weight of the penalty on the parameters' change (>= 0).
        normalize : float or array_like, optional
            Scale s of normalized regressors (> 0).
        p_max : float or array_like, optional
            Bound on trace(P) (> 0).

        Raises
        ------
        ConfigError
            If a value is out of its range.
        DimensionError
            If a value is given per member for another number of members than the batch's.
        """
        given = {k: v for k, v in (("r_delta", r_delta), ("normalize", normalize), ("p_max", p_max)) if v is not None}
        self._options(self.theta0.dtype, **given)
        self.options = dataclasses.replace(self.options, **given)
        for key in given:
            t = getattr(self, _OPTION_BUFFER[key])
            setattr(self, _OPTION_BUFFER[key], t.to(self.theta0.device))
            if self.batch_size:                                   # already reset for a batch
                self.check_batch(t, key)

    # --- the parameter map (``parameter_map``: Theta = T eta) ----------------------------------------------
    @property
    def n_theta(self) -> int:
        """n_theta, the number of free parameters eta (``parameter_map.n_params``)."""
        return self.parameter_map.n_params

    @property
    def theta_names(self) -> list[str]:
        """One name per free parameter, in the order of eta: the entries of theta that hold it, joined by ' = '."""
        return self.parameter_map.names

    @property
    def param_of(self) -> torch.Tensor:
        """The parameter each entry of Theta holds, -1 where it is pinned, (n_u * n_phi,)
        (``parameter_map.param_of_entry``)."""
        return self.parameter_map.param_of_entry

    @property
    def free_idx(self) -> torch.Tensor:
        """The entry of Theta (flattened) that each parameter is read from, the first entry holding it, (n_theta,)
        (``parameter_map.entry_of_param``; the native engine's table REP): eta = Theta[free_idx]."""
        return self.parameter_map.entry_of_param

    @property
    def all_free(self) -> bool:
        """Whether every entry of theta is its own parameter (T = I; ``parameter_map.identity``)."""
        return self.parameter_map.identity

    def hold(self, eta: torch.Tensor | None = None, alive: torch.Tensor | None = None) -> None:
        """Hold theta (at ``eta``, the free parameters (B, n_theta), where given) until ``reset``: u = Theta phi goes
        on, and each update only moves the window of [phi, u] and the histories on (what ``regressors_over`` reads),
        without the retrospective cost's step (P is zero, theta and z_r stay). ``alive`` (B,) bool: the members
        that go on at all (the others frozen, as diverged members are).

        Parameters
        ----------
        eta : torch.Tensor, optional
            (B, n_theta), in the order of ``theta_names``.
        alive : torch.Tensor, optional
            (B,) bool.
        """
        if eta is not None:
            self.set_theta_free(eta)
        self.set_state(P=torch.zeros_like(self.P))
        self.held = True
        if alive is not None:
            self.set_state(alive=alive.to(device=self.alive.device, dtype=torch.bool).reshape(self.alive.shape).clone())

    def record_covariance(self, covariance) -> None:
        """Keep the parameters' covariance that the end of a run measured (a
        ``rcotorch.verdict.intervals.ParameterCovariance``) as ``covariance``, for what reads the estimator
        afterwards (a scenario's figures, the verdict).

        Parameters
        ----------
        covariance : ParameterCovariance or None
        """
        self.covariance = covariance

    def theta_free(self) -> torch.Tensor:
        """The free parameters eta, in the order of ``theta_names``.

        Returns
        -------
        torch.Tensor
            (B, n_theta).
        """
        return self.parameter_map.eta_of(self.theta.reshape(self.theta.shape[0], -1))

    @classmethod
    def static_gain(cls, signals: Mapping[str, int], n_u: int = 1, n_z: int = 1, **kwargs) -> RCOEstimator:
        """An estimator of the exactly proper structure u(k) = theta s(k) (a static gain: stiffness, damping, ...).

        Parameters
        ----------
        signals : Mapping[str, int]
            Input ports and widths.
        n_u : int, optional
            Width of u.
        n_z : int, optional
            Width of z.
        **kwargs
            Further arguments of ``RCOEstimator`` (not ``nc``, ``proper`` or ``feed_u``, which this sets).

        Returns
        -------
        RCOEstimator
            With nc = 0, ``proper=True`` and ``feed_u=False``.
        """
        return cls(signals, n_u=n_u, n_z=n_z, nc=0, proper=True, feed_u=False, **kwargs)

    def _bounds(self, bounds, what: str, width: int, dtype):
        """(low, high) as tensors broadcastable to (B, width) (theta bounds flattened like Theta), or Nones."""
        if bounds is None:
            return None, None
        try:
            lo, hi = (torch.as_tensor(b, dtype=dtype, device="cpu") for b in bounds)
        except (TypeError, ValueError):
            raise ConfigError(f"block '{self.name}': {what} must be a pair (low, high), got {bounds!r}") from None
        lo, hi = (t.reshape(-1) if t.dim() else t for t in (lo, hi))
        for t in (lo, hi):
            if t.dim() and t.numel() != width:
                raise DimensionError(f"block '{self.name}': {what} entries must be scalars or have {width} "
                                     f"values, got {t.numel()}")
        if bool((lo > hi).any()):
            raise ConfigError(f"block '{self.name}': {what} has low > high")
        return lo, hi

    def _regressors(self, inputs) -> torch.Tensor:
        """The regressor signals at time k, (B, n_sig)."""
        if self.features is None:
            return torch.cat([inputs[p] for p in self.ports], dim=1)
        return torch.cat([f(inputs) if isinstance(f, Term) else self._call_feature(f, inputs)
                          for f in self.features.values()], dim=1)

    @staticmethod
    def _call_feature(f, inputs) -> torch.Tensor:
        """A feature function's (B, m) result as a tensor on its inputs' device (a NumPy function returns an
        array, computed on the CPU)."""
        x = next(iter(inputs.values()))
        return tensor_result(call_user(f, inputs), x.dtype, x.device)

    def _feature_map(self, features) -> dict[str, Callable]:
        """name -> callable for the PyTorch engine (terms are named after what they compute)."""
        if isinstance(features, Mapping):
            return dict(features)
        terms = [features] if isinstance(features, Term) else list(features)
        out = {}
        for t in terms:
            if not isinstance(t, Term):
                raise ConfigError(f"block '{self.name}': features must be rcotorch.blocks.features terms (or a dict of "
                                  f"name -> callable), got {t!r}")
            key = t.name({})
            if key in out:
                raise ConfigError(f"block '{self.name}': feature {key!r} is given twice")
            out[key] = t
        return out

    def _probe_features(self, dtype) -> dict[str, int]:
        """The width of each feature: a term's from its ports; a callable is called on random inputs of batch 1
        and 2 and must return (B, m)."""
        widths = {}
        for name, f in self.features.items():
            if isinstance(f, Term):
                widths[name] = f.width(self.ports, self.name)
                continue
            if not callable(f):
                raise ConfigError(f"block '{self.name}': feature {name!r} is not callable")
            shapes = []
            for B in (1, 2):
                probe = {p: torch.randn(B, w, dtype=dtype) for p, w in self.ports.items()}
                try:
                    with np.errstate(all="ignore"):        # random inputs: a sqrt of a negative is no fault
                        out = self._call_feature(f, probe)
                except Exception as e:  # the user's function failed on well-formed inputs
                    raise ConfigError(f"block '{self.name}': feature {name!r} failed on inputs "
                                      f"{ {p: (B, w) for p, w in self.ports.items()} }: {e!r}") from e
                if not isinstance(out, torch.Tensor) or out.dim() != 2 or out.shape[0] != B:
                    p0 = next(iter(self.ports))
                    hint = f"; return one value per member as a column, s[{p0!r}][:, 0:1] rather than " \
                        f"s[{p0!r}][:, 0]" if isinstance(out, torch.Tensor) and out.dim() == 1 and out.shape[0] == B \
                        else ""
                    raise DimensionError(f"block '{self.name}': feature {name!r} must return a (batch, m) tensor; "
                                         f"for batch {B} it returned "
                                         f"{tuple(out.shape) if isinstance(out, torch.Tensor) else type(out)}{hint}")
                shapes.append(out.shape[1])
            if shapes[0] != shapes[1]:
                raise DimensionError(f"block '{self.name}': feature {name!r} width changes with the batch size")
            widths[name] = shapes[0]
        return widths

    def _signal_names(self) -> list[str]:
        """One name per regressor channel, in order: 'y0', 'y0[1]', 'y0^3', 'sign(v)*v^2', ..."""
        names = []
        for s, w in self.signals.items():
            f = self.features.get(s) if self.features else None
            if isinstance(f, Term) and s == f.name({}):           # named after what it computes
                names += f.names(self.ports)
            else:
                names += [f"{s}[{c}]" if w > 1 else s for c in range(w)]
        return names

    # --- layout ---------------------------------------------------------------------------------------
    def _phi_names(self) -> list[str]:
        names, offset = [], 0
        for w in self.signals.values():
            for lag in self.lags:
                for c in range(w):
                    sig = self.signal_names[offset + c]
                    names.append(f"{sig}(k)" if lag == 0 else f"{sig}(k-{lag})")
            offset += w
        if self.feed_u:
            for lag in range(1, self.nc + 1):
                for c in range(self.n_u):
                    names.append(f"u[{c}](k-{lag})" if self.n_u > 1 else f"u(k-{lag})")
        return names

    def _phi_gather(self) -> torch.Tensor:
        """Index map from [s(k) | past s(k-1..k-nc) | past u(k-1..k-nc)] (flattened) to phi's order."""
        nc1 = max(self.nc, 1)
        cur, past0, upast0 = 0, self.n_sig, self.n_sig + nc1 * self.n_sig
        idx, offset = [], 0
        for _s, w in self.signals.items():
            for lag in self.lags:
                for c in range(w):
                    idx.append(cur + offset + c if lag == 0 else past0 + (lag - 1) * self.n_sig + offset + c)
            offset += w
        if self.feed_u:
            for lag in range(1, self.nc + 1):
                idx += [upast0 + (lag - 1) * self.n_u + c for c in range(self.n_u)]
        return torch.tensor(idx, dtype=torch.int64)

    def set_markov(self, markov, first_delay: int = 1, dt: float | None = None, members=None) -> bool:
        """Set the Markov parameters beta_d..beta_(d+nu-1) of the map u -> z (sign included).

        A lowered native program reads the new values where their shape stays, and is built again where it
        changes.

        Parameters
        ----------
        markov : array_like
            (nu, n_z, n_u) shared by the batch, or (B, nu, n_z, n_u) one per member; nu >= 1. With ``members``,
            (len(members), nu, n_z, n_u), the parameters of those members, with the nu and d they have.
        first_delay : int, optional
            d, the delay of the first one (>= 0; 0 where u reaches z at once).
        dt : float, optional
            The sample time [s] of the model they are taken from, the identified subsystem's ``sample_time``
            where the estimator has no ``dt`` of its own; None keeps the one given before.
        members : array_like, optional
            The indices of the members whose parameters ``markov`` holds; the others keep theirs (a shared set
            becomes one per member).

        Returns
        -------
        bool
            Whether beta was changed in place, with the native engine's copy of it (``members``
            where the parameters are already one per member and a lowered program reads them): a graph whose
            program was made with them stays valid through the change (``rcotorch.engine.lowering.refilled``).
            False where they were replaced.

        Raises
        ------
        DimensionError
            If ``markov`` has the wrong shape.
        ConfigError
            If ``first_delay`` is negative, or differs from the present one with ``members``.
        """
        beta = torch.as_tensor(markov, dtype=self.theta0.dtype, device=self.theta0.device)
        if members is not None:
            idx = torch.as_tensor(members, dtype=torch.int64, device=beta.device).reshape(-1)
            if first_delay != self.first_delay:
                raise ConfigError(f"block '{self.name}': the Markov parameters of some members must keep the "
                                  f"first delay {self.first_delay}, got {first_delay}")
            if tuple(beta.shape) != (idx.numel(), *self.beta.shape[1:]):
                raise DimensionError(f"block '{self.name}': Markov parameters of {idx.numel()} members must be "
                                     f"{(idx.numel(), *self.beta.shape[1:])}, got {tuple(beta.shape)}")
            if self.beta.shape[0] == self.theta.shape[0] and self._refill_members(idx, beta):
                return True
            full = self.beta.expand(self.theta.shape[0], -1, -1, -1).clone()
            full[idx] = beta
            beta = full
        beta = beta.unsqueeze(0) if beta.dim() == 3 else beta
        if beta.dim() != 4 or tuple(beta.shape[2:]) != (self.n_z, self.n_u) or beta.shape[1] < 1:
            raise DimensionError(f"block '{self.name}': Markov parameters must be (nu, n_z, n_u) = "
                                 f"(nu, {self.n_z}, {self.n_u}) with nu >= 1, got {tuple(beta.shape)}")
        if first_delay < 0:
            raise ConfigError(f"block '{self.name}': first_delay must be >= 0, got {first_delay}")
        same = self._buffers["beta"].shape == beta.shape and self.__dict__.get("first_delay") == first_delay
        self.beta = beta
        self.first_delay = int(first_delay)
        self.delays = torch.arange(first_delay, first_delay + beta.shape[1], device=beta.device)
        self.window = first_delay + beta.shape[1]
        if dt is not None:
            self.markov_dt = dt
        native = self._native_copy
        if native is not None:
            ring = self._laid_out(self.beta, 2)
            if same and ring.shape == native.ring.shape and ring.device == native.ring.device:
                native.ring.copy_(ring)
            else:                           # other sizes: the program, which holds the old beta, is made again
                kernels.bump(native.beta)
        return False

    def _lowered_ring(self) -> torch.Tensor | None:
        """The lowered program's copy of beta (``_native_copy.ring``) where it is made of the present beta, one set
        per member, else None."""
        native = self._native_copy
        if native is None or native.beta is not self.beta or native.ring.shape[0] != self.beta.shape[0] or \
                self.beta.shape[0] != self.theta.shape[0]:
            return None
        return native.ring

    def _refill_members(self, idx: torch.Tensor, beta: torch.Tensor) -> bool:
        """Write the Markov parameters of the members ``idx`` into beta and, where a lowered program
        reads them, its copy, all in place; False where there is no such copy of this beta (the caller then
        sets the whole beta, and the program is made again)."""
        ring = self._lowered_ring()
        if ring is None:
            return False
        self.beta.index_copy_(0, idx, beta)
        ring.index_copy_(0, idx, self._laid_out(beta, 2))                       # as _native_beta lays them out
        return True

    def _refill_from_system(self, idx: torch.Tensor, A: torch.Tensor, B: torch.Tensor, C: torch.Tensor,
                            D: torch.Tensor, stable: bool) -> torch.Tensor | None:
        """``_refill_members`` with the Markov parameters of the systems (A, B, C, D), one per member of ``idx``,
        computed by the native kernel straight into beta and the lowered program's copy, in one pass
        (``kernels.lti_markov``). Returns which members were written (with ``stable``, those whose A the kernel's
        test shows stable), or None where this cannot be done in place (the caller computes the parameters
        and sets them)."""
        ring = self._lowered_ring()
        if ring is None:
            return None
        nu, pm, d = self.nu, self.n_z * self.n_u, self.first_delay
        width = ring.shape[-1]                              # copies of W = d + nu: nu reversed, then d zeros
        targets = [kernels.MarkovTarget(self.beta, offset=0, row_stride=nu * pm, step_stride=pm, entry_stride=1),
                   kernels.MarkovTarget(ring, offset=nu - 1, row_stride=pm * width, step_stride=-1, entry_stride=width,
                                        copies=width // (d + nu), copy_stride=d + nu)]
        return kernels.lti_markov(A, B, C, D, d, nu, targets, rows=idx, stable=stable)

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        """Markov parameters saved one per member (after ``set_markov(..., members=)``) load into an estimator
        whose parameters are still shared: it takes the saved set's shape first. A checkpoint that also holds
        beta transposed ('beta_t', a buffer of earlier versions, made from beta) loads without it."""
        state_dict.pop(prefix + "beta_t", None)
        beta = state_dict.get(prefix + "beta")
        if isinstance(beta, torch.Tensor) and beta.dim() == 4 and beta.shape != self.beta.shape and \
                beta.shape[1:] == self.beta.shape[1:]:
            self.set_markov(beta.to(self.beta), self.first_delay)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    @property
    def sample_time(self) -> float | None:
        """The identified subsystem's sample time [s]: ``dt``, or where that is None the sample time given with the
        Markov parameters (``set_markov``); None where neither is known."""
        return self.dt if self.dt else self.markov_dt

    @property
    def nu(self) -> int:
        """nu, the number of Markov parameters the retrospective cost uses (0 before they are set)."""
        return int(self.beta.shape[1])

    # --- block protocol -------------------------------------------------------------------------------
    def feedthrough(self):
        return {"u": tuple(self.ports) if self.proper else ()}

    def reset(self, batch_size: int) -> None:
        super().reset(batch_size)
        for key in ("p0", "lam", "theta0", "beta", "rd_sqrt", "norm_inv_s2", "p_max"):
            if getattr(self, key) is not None:
                self.check_batch(getattr(self, key), key)
        B, dt, dev = batch_size, self.theta0.dtype, self.theta0.device
        self.theta = self.theta0.expand(B, -1, -1).clone()
        eye = torch.eye(self.n_theta, dtype=dt, device=dev)
        self.P = (self.p0.reshape(-1, 1, 1) * eye).expand(B, -1, -1).clone()
        nc1 = max(self.nc, 1)
        self.past = torch.zeros(B, nc1, self.n_sig, dtype=dt, device=dev)
        self.past_u = torch.zeros(B, nc1, self.n_u, dtype=dt, device=dev)
        self.win = torch.zeros(max(self.window, 1), B, self.n_phi + self.n_u, dtype=dt, device=dev)
        self.phi_now = torch.zeros(B, self.n_phi, dtype=dt, device=dev)
        self.u_now = torch.zeros(B, self.n_u, dtype=dt, device=dev)
        self.z_r = torch.zeros(B, self.n_z, dtype=dt, device=dev)
        self.alive = torch.ones(B, dtype=torch.bool, device=dev)
        self.diverged_at = torch.full((B,), -1, dtype=torch.int64, device=dev)
        self.k = torch.zeros((), dtype=torch.int64, device=dev)
        self.held = False

    def _current(self, inputs) -> torch.Tensor:
        if self.proper:
            return self._regressors(inputs)
        return self.past.new_zeros(self.batch_size, self.n_sig)

    def output(self, port, inputs):
        if self._phi_is_past:   # phi = [s(k-1..k-nc) | u(k-1..k-nc)] as stored
            phi = torch.cat([self.past.flatten(1), self.past_u.flatten(1)], dim=1) if self.feed_u else \
                self.past.flatten(1).clone()
        else:
            flat = torch.cat([self._current(inputs), self.past.flatten(1), self.past_u.flatten(1)], dim=1)
            phi = flat.index_select(1, self._gather)
        u = torch.bmm(self.theta, phi.unsqueeze(-1)).squeeze(-1)
        u = torch.where(self.alive.unsqueeze(1), u, 0.0)
        if self.u_low is not None:
            u = torch.clamp(u, self.u_low, self.u_high)
        self.set_state(phi_now=phi, u_now=u)
        return u

    def _step_index(self) -> int:
        """k as a Python int, read from the buffer (a device sync) only when something other than ``update``
        changed it."""
        return memo.derived(self, "k", (self.k,), lambda: int(self.k))

    def _beta_padded(self) -> torch.Tensor:
        """beta as (Bp, n_z * n_u, nu), reversed in time with first_delay zeros after it: (Bp, n_z * n_u, W), entry
        j weighs delay W - 1 - j."""
        return memo.derived(self, "beta_padded", (self.beta,), lambda: self._laid_out(self.beta, 1))

    def _laid_out(self, beta: torch.Tensor, copies: int) -> torch.Tensor:
        """(m, nu, n_z, n_u) -> (m, n_z * n_u, copies * W): ``copies`` times over, beta as (m, n_z * n_u, nu)
        reversed in time with first_delay zeros after it (entry j of each copy weighs delay W - 1 - j)."""
        nu, W = beta.shape[1], beta.shape[1] + self.first_delay
        out = beta.new_empty(beta.shape[0], self.n_z * self.n_u, copies * W)
        out[..., :nu] = beta.flip(1).flatten(2).transpose(1, 2)
        out[..., nu:W] = 0.0
        for c in range(1, copies):
            out[..., c * W:(c + 1) * W] = out[..., :W]
        return out

    def _beta_ring(self, p: int) -> torch.Tensor:
        """The weights of the window's rows at a step with k mod W = p, (Bp, n_z * n_u, W): row r holds the
        sample of delay (p - r) mod W, weighed by beta at that delay, or by 0 below the first delay."""
        return self._beta_padded().roll(p + 1, dims=-1)

    def _lam_arg(self):
        """lam for rls_update: the Python float 1.0 when every member has lam = 1 (no division by lambda)."""
        return memo.derived(self, "lam", (self.lam,), lambda: 1.0 if bool((self.lam == 1).all()) else self.lam)

    def update(self, inputs):
        """The retrospective-cost update of theta from the error z(k), then the shift of the histories.

        The stages, each a method: store [phi(k), u(k)] in the window (``_store_in_window``); the Markov filter
        gives Psi^T and zeta(k) = z(k) - sum_i beta_i u(k-i) (``_markov_filter``, where the cost's step begins,
        ``_cost_step``, which a held estimator skips); both over the free parameters,
        T^T Psi and eta (``_over_parameters``); z_R = zeta + Psi^T eta (``_retrospective_performance``);
        ``rls_update`` on (T^T Psi, z_R), rows normalized and penalty rows added per the robustness options
        (``_rls_step``); the trace bound on P (``_bound_covariance``); Theta = T eta and the projection onto
        ``theta_bounds`` (``_write_theta``); members whose step failed are frozen (``_freeze_failed``, the step's
        end); the regressor signals and u move into the past (``_shift_histories``).

        Parameters
        ----------
        inputs : Mapping[str, torch.Tensor]
            The regressor ports, (B, width); ``z``, (B, n_z); and optionally ``valid``, (B, 1): a member with
            valid <= 0.5 keeps theta and P this step.

        Raises
        ------
        ConfigError
            If the Markov parameters are not set, or changed since ``reset``.
        """
        W = self.window
        if self.win.shape[0] != W:
            if W == 0:
                raise ConfigError(f"block '{self.name}': no Markov parameters; pass markov=, call set_markov() "
                                  "(e.g. with Graph.markov('identified.u', 'error.out', n)), or build the graph "
                                  "with rcotorch.refinement, which derives them from the known model")
            raise ConfigError(f"block '{self.name}': Markov parameters changed; call reset() before stepping")
        k = self._step_index()
        p = k % W
        self._store_in_window(p)
        if not self.held:                      # held: no step of the cost, the histories move on
            self._cost_step(p, inputs, k)
        self._shift_histories(inputs)
        self.k += 1
        memo.remember(self, "k", (self.k,), k + 1)

    def _cost_step(self, p: int, inputs, k: int) -> None:
        """The retrospective cost's step of ``update`` at step ``k`` (window row ``p``): theta, P, z_r, the
        members' health."""
        psi_t, zeta = self._markov_filter(p, inputs["z"])
        if not (self.theta.is_contiguous() and self.P.is_contiguous()):   # updated in place below
            self.set_state(theta=self.theta.contiguous(), P=self.P.contiguous())
        theta_flat = self.theta.view(self.batch_size, -1)
        psi_eta, eta = self._over_parameters(psi_t, theta_flat)
        z_r = self._retrospective_performance(zeta, psi_eta, eta)
        eta, ok = self._rls_step(eta, psi_eta, z_r, self._active(inputs))
        self._bound_covariance(ok)
        self._write_theta(theta_flat, eta)
        self._freeze_failed(z_r, ok, k)

    # --- the stages of ``update`` ---------------------------------------------------------------------------
    def _store_in_window(self, p: int) -> None:
        """Store [phi(k), u(k)] in the window, a time-major ring: row t mod W holds time t, so the W rows hold the
        delays 0 .. W-1."""
        # win[k mod W] = [phi(k), u(k)]
        self.win[p] = torch.cat([self.phi_now, self.u_now], dim=1)

    def _markov_filter(self, p: int, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The Markov filter over the window: Psi^T (B, n_z, n_u * n_phi), Theta row-major, and zeta (B, n_z).

        Every row of the window is weighed (by 0 below the first delay), the same products on both engines."""
        B, n_phi = self.batch_size, self.n_phi
        prod = self._markov_sums(p)
        # Psi^T[z, a * n_phi + j] = sum_i beta_i[z, a] phi(k-i)[j]
        psi_t = prod[..., :n_phi].reshape(B, self.n_z, -1)
        # zeta(k) = z(k) - sum_i beta_i u(k-i)
        if self.n_u == 1:
            zeta = z - prod[:, :, 0, n_phi]
        else:
            zeta = z - prod[..., n_phi:].diagonal(dim1=2, dim2=3).sum(-1)
        return psi_t, zeta

    def _over_parameters(self, psi_t: torch.Tensor, theta_flat: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The regressor and the value of the free parameters eta: Psi_eta^T (B, n_z, n_theta) and eta
        (B, n_theta). Where T = I they are ``psi_t`` and ``theta_flat`` themselves, so that the RLS step updates
        theta in place."""
        pm = self.parameter_map
        if pm.identity:
            return psi_t, theta_flat
        # Psi_eta^T = Psi^T T,  eta(k) = Theta(k)[entry_of_param]
        return pm.regressor_of_eta(psi_t), pm.eta_of(theta_flat)

    @staticmethod
    def _retrospective_performance(zeta: torch.Tensor, psi_eta: torch.Tensor, eta: torch.Tensor) -> torch.Tensor:
        """z_R(k) = z_hat(eta(k), k), (B, n_z)."""
        # z_R(k) = zeta(k) + Psi_eta(k)^T eta(k)
        return zeta + (psi_eta @ eta.unsqueeze(-1)).squeeze(-1)

    def _active(self, inputs) -> torch.Tensor:
        """The members that update this step, (B,): alive, and with valid > 0.5 where ``valid`` is given."""
        active = self.alive
        if "valid" in inputs:
            active = active & (inputs["valid"].reshape(self.batch_size) > 0.5)
        return active

    def _rls_step(self, eta: torch.Tensor, psi_eta: torch.Tensor, z_r: torch.Tensor, active: torch.Tensor
                  ) -> tuple[torch.Tensor, torch.Tensor]:
        """``rls_update`` on eta and P, both in place, over the rows of ``_rows``; returns eta and ok (B,).

        A member whose Psi or z_R is not finite fails rls_update's checks (S or the step is not finite) and is
        frozen with theta and P held, like one whose P lost definiteness."""
        psi_u, z_u, r_inv = self._rows(psi_eta, z_r)
        # S = lam R^-1 + Psi^T P Psi,  eta <- eta - P Psi S^-1 z_R,  P <- (P - P Psi S^-1 Psi^T P) / lam
        eta, _, ok = rls_update(eta, self.P, psi_u.mT, z_u, self._lam_arg(), r_inv, active, inplace=True)
        return eta, ok

    def _bound_covariance(self, ok: torch.Tensor) -> None:
        """The trace bound on P: a living member whose trace(P) exceeds p_max has P scaled down to it."""
        if self.p_max is None:
            return
        tr = self.P.diagonal(dim1=1, dim2=2).sum(-1)
        # P <- P p_max / trace(P) where trace(P) > p_max
        scale = torch.where(self.alive & ok & (tr > self.p_max), self.p_max / tr, 1.0)
        self.P.mul_(scale.reshape(self.batch_size, 1, 1))

    def _write_theta(self, theta_flat: torch.Tensor, eta: torch.Tensor) -> None:
        """Theta = T eta (already there where T = I), then the projection onto ``theta_bounds`` (P is left as it
        is)."""
        if not self.parameter_map.identity:
            # Theta = T eta
            self.parameter_map.write_theta_(theta_flat, eta)
        if self.theta_low is not None:
            # Theta <- min(max(Theta, low), high)
            theta_flat.clamp_(self.theta_low, self.theta_high)

    def _freeze_failed(self, z_r: torch.Tensor, ok: torch.Tensor, k: int) -> None:
        """Keep z_R, and freeze the members whose step failed (``ok`` False), recording k in ``diverged_at``."""
        self.set_state(z_r=z_r, alive=self.alive & ok,
                       diverged_at=torch.where(self.alive & ~ok, k, self.diverged_at))

    def _shift_histories(self, inputs) -> None:
        """Move s(k) and u(k) into the past: past[0] = s(k), past[l] = s(k-l) (and u likewise)."""
        if not self.nc:
            return
        cur = self._regressors(inputs)
        if self.nc == 1:
            self.past.copy_(cur.unsqueeze(1))
            self.past_u.copy_(self.u_now.unsqueeze(1))
        else:
            # [s(k), s(k-1) .. s(k-nc+1)], [u(k), u(k-1) .. u(k-nc+1)]
            self.set_state(past=torch.cat([cur.unsqueeze(1), self.past[:, :-1]], dim=1),
                           past_u=torch.cat([self.u_now.unsqueeze(1), self.past_u[:, :-1]], dim=1))

    def _markov_sums(self, p: int) -> torch.Tensor:
        """The Markov filter over the ring at a step with k mod W = p: sum_i beta_i[z, a] phi(k-i)[j] and
        sum_i beta_i[z, a] u(k-i)[c] in one product, (B, n_z, n_u, n_phi + n_u)."""
        W, B, m = self.window, self.batch_size, self.n_phi + self.n_u
        beta = self._beta_ring(p)                                               # (Bp, n_z * n_u, W)
        if beta.shape[0] == 1 and self.n_z * self.n_u == 1:
            return (beta[0] @ self.win.view(W, B * m)).reshape(B, 1, 1, m)
        return torch.bmm(beta.expand(B, -1, -1), self.win.transpose(0, 1)).reshape(B, self.n_z, self.n_u, m)

    def last_regressor(self) -> torch.Tensor:
        """The regressor of the parameters in the last update, Psi^T: z_hat(eta) = zeta + Psi^T eta.

        Returns
        -------
        torch.Tensor
            (B, n_z, n_theta), before the division by m of normalized regressors.

        Raises
        ------
        ConfigError
            If no update has run yet.
        """
        if not int(self.k):
            raise ConfigError(f"block '{self.name}': no update has run yet")
        B = self.batch_size
        psi_t = self._markov_sums((self._step_index() - 1) % self.window)[..., :self.n_phi].reshape(B, self.n_z, -1)
        return self.parameter_map.regressor_of_eta(psi_t)

    def regressor_history(self) -> dict[str, torch.Tensor]:
        """What ``regressors_over`` continues from.

        Returns
        -------
        dict[str, torch.Tensor]
            Copies of the histories at the current step: ``past`` and ``past_u`` (the regressor signals' and
            u's past), ``win`` (the window of [phi, u]) and ``k`` (the step).
        """
        return {"past": self.past.clone(), "past_u": self.past_u.clone(), "win": self.win.clone(),
                "k": self.k.clone()}

    def regressors_over(self, history: Mapping[str, torch.Tensor], inputs: Mapping[str, torch.Tensor],
                        u: torch.Tensor, start: int, stop: int) -> torch.Tensor:
        """The regressors of the free parameters, Psi_eta^T, that ``update`` would use at the steps ``start`` to
        ``stop`` of a recorded stretch, without stepping: phi rebuilt from the recorded inputs as ``output``
        builds it, then filtered by the Markov parameters as ``_markov_filter`` filters the window.

        Parameters
        ----------
        history : Mapping[str, torch.Tensor]
            ``regressor_history()`` taken when the stretch began.
        inputs : Mapping[str, torch.Tensor]
            The regressor ports over the stretch, each (T, B, width).
        u : torch.Tensor
            This block's output over the stretch, (T, B, n_u).
        start, stop : int
            The steps of the stretch (0 its first) whose regressors are returned.

        Returns
        -------
        torch.Tensor
            (stop - start, B, n_z, n_theta), float64, before the division by m of normalized regressors.
        """
        f64, B, nu, fd = torch.float64, u.shape[1], self.nu, self.first_delay
        W = nu + fd
        lo = max(0, start - W)                       # the recorded steps whose phi the window reaches
        ahead = W if lo == 0 else 0                  # the steps before the stretch, from the window: phi(k0 - W + j)
        phi = self._phi_over(history, inputs, u, lo, stop, ahead)            # (ahead + stop - lo, B, n_phi)
        k0 = int(history["k"])
        if ahead:
            ring = history["win"][:, :, :self.n_phi]
            phi[:W] = ring[torch.arange(k0 - W, k0, device=ring.device) % W]
            lo -= W
        # Psi^T(k)[z, a * n_phi + j] = sum_{i = fd}^{W - 1} beta_{i - fd}[z, a] phi(k - i)[j]: a product and sum
        # per Markov parameter over a stretch of steps short enough to stay in cache (beta per member or shared)
        T, n_out = stop - start, self.n_z * self.n_u
        beta = self.beta.to(f64).reshape(self.beta.shape[0], nu, n_out, 1)
        psi = self._markov_held_entries(phi, beta[..., 0], start - fd - lo, T)
        if psi is None:
            psi = kernels.markov_filter(phi, beta[..., 0], start - fd - lo, T)    # on the CPU; else in PyTorch:
        if psi is None and nu >= CONVOLVE_NU:
            psi = _markov_convolution(phi[start - fd - nu + 1 - lo:stop - fd - lo], beta, B)
        elif psi is None:
            psi = phi.new_empty(T, B, n_out, self.n_phi)
            span = max(1, (1 << 19) // max(1, B * n_out * self.n_phi))                # steps of about 4 MB
            for t0 in range(0, T, span):
                t1 = min(T, t0 + span)
                part = psi[t0:t1].zero_()
                for i in range(nu):
                    at = start - fd - i - lo                                           # phi(k - fd - i), k = start
                    part.addcmul_(beta[:, i], phi[at + t0:at + t1].unsqueeze(2))
        psi = psi.reshape(T * B, self.n_z, self.n_u * self.n_phi)
        return self.parameter_map.regressor_of_eta(psi).reshape(stop - start, B, self.n_z, -1)

    def _markov_held_entries(self, phi: torch.Tensor, beta: torch.Tensor, s0: int, T: int) -> torch.Tensor | None:
        """``kernels.markov_filter`` of the entries of Theta that hold a parameter only, the pinned ones 0: one call
        per regressor column, over the rows of u whose entry in that column is not pinned (the same sums, term
        by term, as the whole filter gives them). None where no entry is pinned (the whole filter is the same
        work) or the kernel does not apply."""
        held = self.parameter_map.unpinned
        if bool(held.all()):
            return None
        B, nb = phi.shape[1], beta.shape[0]
        by_row = beta.reshape(nb, self.nu, self.n_z, self.n_u)
        psi = phi.new_zeros(T, B, self.n_z, self.n_u, self.n_phi)
        for j in range(self.n_phi):
            rows = held[:, j].nonzero().flatten().tolist()
            if not rows:
                continue
            part = kernels.markov_filter(phi[..., j:j + 1].contiguous(),
                                         by_row[..., rows].reshape(nb, self.nu, -1).contiguous(), s0, T)
            if part is None:
                return None
            psi[:, :, :, rows, j] = part.reshape(T, B, self.n_z, len(rows))
        return psi.reshape(T, B, self.n_z * self.n_u, self.n_phi)

    def _phi_over(self, history, inputs, u: torch.Tensor, lo: int, stop: int, ahead: int = 0) -> torch.Tensor:
        """phi at the recorded steps lo .. stop - 1, as ``output`` builds it, (ahead + stop - lo, B, n_phi) float64,
        its first ``ahead`` rows left for the caller: each entry copied over the stretch from the signal and lag
        ``_gather`` maps it to."""
        f64, T, B, nc = torch.float64, stop - lo, u.shape[1], self.nc
        a = max(0, lo - nc)                          # the first recorded step the lags reach
        rows = {p: v[a:stop].to(f64).reshape(-1, v.shape[-1]) for p, v in inputs.items()}
        cur = self._regressors(rows).to(f64).reshape(stop - a, B, self.n_sig)
        if nc:
            h = max(0, nc - lo)                      # steps before the stretch: from the histories
            # S[e] = s(lo - nc + e) and U[e] = u(lo - nc + e), e = 0 .. T + nc - 1
            S = torch.cat([history["past"].to(f64).flip(1).transpose(0, 1)[nc - h:], cur])
            U = torch.cat([history["past_u"].to(f64).flip(1).transpose(0, 1)[nc - h:], u[a:stop].to(f64)])
        n_sig, nc1 = self.n_sig, max(nc, 1)
        full = cur.new_empty(ahead + T, B, self.n_phi)
        phi = full[ahead:]
        # entry f of [s(k) | past s | past u], past(k)[l] = s(k - 1 - l), l = 0 .. nc - 1 (u's likewise)
        for k, f in enumerate(self._gather.tolist()):
            if f < n_sig:
                phi[:, :, k] = cur[cur.shape[0] - T:, :, f] if self.proper else 0.0
                continue
            of_u = f >= n_sig * (1 + nc1)
            lag, c = divmod(f - n_sig * (1 + (nc1 if of_u else 0)), self.n_u if of_u else n_sig)
            if nc:
                phi[:, :, k] = (U if of_u else S)[nc - 1 - lag:nc - 1 - lag + T, :, c]
            else:
                phi[:, :, k] = history["past_u" if of_u else "past"][:, lag, c].to(f64)
        return full

    def static_output(self, inputs: Mapping[str, torch.Tensor]) -> torch.Tensor | None:
        """u = Theta phi(s) of a structure without memory (nc = 0, exactly proper): what ``output`` gives for
        the regressor ports' values ``inputs`` at any one instant, with theta as it is and nothing changed.

        Parameters
        ----------
        inputs : Mapping[str, torch.Tensor]
            The regressor ports, each (B, width).

        Returns
        -------
        torch.Tensor or None
            (B, n_u); None for a structure with memory (nc > 0) or one that is not exactly proper.
        """
        if self.nc or not self.proper:
            return None
        cur = self._regressors(inputs)
        B = cur.shape[0]
        flat = torch.cat([cur, cur.new_zeros(B, self.past[0].numel() + self.past_u[0].numel())], dim=1)
        phi = flat.index_select(1, self._gather.to(flat.device))
        u = torch.bmm(self.theta.to(phi.dtype), phi.unsqueeze(-1)).squeeze(-1)
        u = torch.where(self.alive.unsqueeze(1), u, 0.0)
        if self.u_low is not None:
            u = torch.clamp(u, self.u_low, self.u_high)
        return u

    @contextlib.contextmanager
    def theta_kept(self):
        """A context within which theta may be moved (``set_theta_free``, e.g. for finite differences): on leaving
        it, theta is back in the tensor that held it before, with its values, so that a graph (or a native program
        reading that tensor) steps on as if nothing had happened.

        Returns
        -------
        contextlib.AbstractContextManager
            Entered with ``with``; it yields nothing.
        """
        held = self.theta
        saved = held.clone()
        try:
            yield
        finally:
            held.copy_(saved)
            self.set_state(theta=held)

    def set_theta_free(self, eta: torch.Tensor) -> None:
        """Set theta from the free parameters: Theta = T eta (pinned entries stay 0).

        Parameters
        ----------
        eta : torch.Tensor
            (B, n_theta) or (1, n_theta) for every member, in the order of ``theta_names``.

        Raises
        ------
        DimensionError
            If ``eta`` has another shape.
        """
        pm = self.parameter_map
        flat = self.theta.reshape(self.theta.shape[0], -1).clone()
        if eta.dim() != 2 or eta.shape[1] != pm.n_params or eta.shape[0] not in (1, flat.shape[0]):
            raise DimensionError(f"estimator '{self.name}': the free parameters must be ({flat.shape[0]}, "
                                 f"{pm.n_params}) (batch, one per name of {self.theta_names}), got {tuple(eta.shape)}")
        # Theta[e] = eta[param_of_entry[e]] for every unpinned entry e
        flat[:, pm.unpinned_entries] = eta.to(flat.dtype)[:, pm.param_of_unpinned]
        self.set_state(theta=flat.reshape(self.theta.shape).contiguous())

    def row_scale(self, psi_t: torch.Tensor) -> torch.Tensor | None:
        """The scale m = sqrt(1 + |Psi|_R^2 / s^2) that normalized regressors divide the rows of z by.

        Parameters
        ----------
        psi_t : torch.Tensor
            Psi^T, (B, n_z, n_theta).

        Returns
        -------
        torch.Tensor or None
            m, (B,); None where the regressors are not normalized.
        """
        if self.norm_inv_s2 is None:
            return None
        return torch.sqrt(1.0 + (psi_t * (self.r_weight @ psi_t)).sum((1, 2)) * self.norm_inv_s2)

    def _rows(self, psi_t: torch.Tensor, z_r: torch.Tensor):
        """The rows of the update (Psi^T (B, l, n), their residuals (B, l), R^-1 (l, l)): the rows of z, divided
        by m = sqrt(1 + |Psi|_R^2 / s^2) when normalized, then sqrt(r_delta) I with residual 0 for the penalty."""
        r_inv = self.r_inv
        m = self.row_scale(psi_t)
        if m is not None:
            psi_t, z_r = psi_t / m.reshape(-1, 1, 1), z_r / m.reshape(-1, 1)
        if self.rd_sqrt is not None:
            B, n = psi_t.shape[0], psi_t.shape[2]
            eye = torch.eye(n, dtype=psi_t.dtype, device=psi_t.device)
            psi_t = torch.cat([psi_t, (self.rd_sqrt.reshape(-1, 1, 1) * eye).expand(B, n, n)], dim=1)
            z_r = torch.cat([z_r, z_r.new_zeros(B, n)], dim=1)
            r_inv = torch.block_diag(r_inv, eye)
        return psi_t, z_r, r_inv

    # --- native form ------------------------------------------------------------------------------------
    def lower(self, b) -> None:
        """Describe the estimator to the native engine.

        State, parameters and ports go in slots; the regressor signals s(k) (ports or features) are computed
        once per step; ``RCO_OUT`` computes ``output`` and ``RCO_UPD`` ``update``, from the fields and tables of
        ``kernels.LAYOUT['ESTIMATOR']``.

        Parameters
        ----------
        b : rcotorch.engine.lowering.Builder
            Receives the state, parameters, ports and instructions; refuses the block where a feature
            function does not compile or its Markov parameters are missing.
        """
        W = self.window
        if W == 0 or self.win.shape[0] != W:
            b.refuse("has no Markov parameters, or they changed since reset()")
        if self.alive.dtype != torch.bool:
            b.refuse("alive is not boolean")
        st = {key: b.state(key) for key in ("theta", "P", "phi_now", "u_now", "z_r", "alive", "diverged_at", "past",
                                           "past_u")}
        st["win"] = b.state("win", rows=W)
        cur = self._lower_regressors(b)
        nc1 = max(self.nc, 1)
        flat = list(range(cur, cur + self.n_sig)) + list(range(st["past"], st["past"] + nc1 * self.n_sig)) + \
            list(range(st["past_u"], st["past_u"] + nc1 * self.n_u))            # [s(k) | past s | past u]
        low_high = [(self.theta_low, self.theta_high, self.n_u * self.n_phi), (self.u_low, self.u_high, self.n_u)]
        (tlo, thi), (ulo, uhi) = [(-1, -1) if lo is None else
                                  tuple(b.param(v.reshape(-1).expand(w).reshape(1, w)) for v in (lo, hi))
                                  for lo, hi, w in low_high]
        r_inv = self.r_inv if self.rd_sqrt is None else \
            torch.block_diag(self.r_inv, torch.eye(self.n_theta, dtype=self.r_inv.dtype))
        nl = r_inv.shape[0]
        shared = b.shared(self.beta)
        fields = dict(NU=self.n_u, NZ=self.n_z, NPHI=self.n_phi, NTHETA=self.n_theta, NENT=self.n_u * self.n_phi,
                      W=W, WMOD=kernels.ring_multiplier(W), NC=self.nc, NC1=nc1, NSIG=self.n_sig,
                      LAM_ONE=int(not isinstance(self._lam_arg(), torch.Tensor)), COUNTER=b.counter(),
                      SHARED=shared,
                      THETA=st["theta"], P=st["P"], WIN=st["win"], PHI=st["phi_now"], UNOW=st["u_now"],
                      ZR=st["z_r"], ALIVE=st["alive"], DIV=st["diverged_at"], PAST=st["past"], PASTU=st["past_u"],
                      BETA=b.param(self._native_beta(), first_lane=bool(shared)), LAM=b.param(self.lam.reshape(-1, 1)),
                      RINV=b.param(r_inv.reshape(1, -1)), TLO=tlo, THI=thi, ULO=ulo, UHI=uhi,
                      Z=b.input("z"), VALID=-1 if b.input("valid") is None else b.input("valid"), CUR=cur,
                      UOUT=b.output("u"),
                      SCRATCH=b.scratch(kernels.estimator_scratch(self.n_u, self.n_z, self.n_phi, self.n_theta, nl)),
                      RW=-1 if self.norm_inv_s2 is None else b.param(self.r_weight.reshape(1, -1)),
                      NL=nl, **{key: -1 if t is None else b.param(t.reshape(-1, 1)) for key, t in
                                (("RDQ", self.rd_sqrt), ("NORM", self.norm_inv_s2), ("PMAX", self.p_max))})
        fields["IDENT"] = int(self.param_of.tolist() == list(range(self.n_u * self.n_phi)))  # entry i is parameter i
        fields["HELD"] = int(self.held)
        fields.update(phi_src=[flat[j] for j in self._gather.tolist()], param_of=self.param_of.tolist(),
                      rep=self.free_idx.tolist())
        b.emit("RCO_OUT", port="u", **fields)
        b.emit("RCO_UPD", **fields)

    def _native_beta(self) -> torch.Tensor:
        """beta as the native engine reads it, ``_beta_padded`` twice over (Bp, n_z * n_u, 2W): one tensor, kept
        as ``_native_copy`` (``NativeCopy``), which ``set_markov`` refills while its shape stays, so that the
        lowered program runs on with the new parameters (a Markov refresh between two calls of the engine)."""
        ring = self._laid_out(self.beta, 2)
        self._native_copy = NativeCopy(ring, self.beta)
        return ring

    def _lower_regressors(self, b) -> int:
        """Slots of s(k): the port itself (one port, no features), else s(k) computed into scratch, before u
        when phi holds s(k) (``proper``), else before the update (which shifts s(k) into the history)."""
        port = "u" if self.proper else None
        if self.features is None:
            return self._lower_ports_stacked(b, port)
        cur = b.scratch(self.n_sig)
        if self.terms is not None:
            b.emit("FEATURE", port=port, OUT=cur, terms=[t.encode(self.ports, b.input, b.const) for t in self.terms])
            return cur
        # Terms and functions: each function compiled (rcotorch.engine.compiled) and called on the ports stacked.
        at, stacked = cur, None
        for name, f in self.features.items():
            width = self.signals[name]
            if isinstance(f, Term):
                b.emit("FEATURE", port=port, OUT=at, terms=[f.encode(self.ports, b.input, b.const)])
            else:
                try:
                    c = compile_features(f, self.ports, width)
                except NotLowerable as e:
                    b.refuse(f"feature {name!r}, function {describe(f)}, is not compiled: {e}")
                if stacked is None:
                    stacked = self._lower_ports_stacked(b, port)
                b.emit("CALL", port=port, NIN=sum(self.ports.values()), IN=stacked, NOUT=width, OUT=at,
                       FUNCTION=b.function(c.address, c))
            at += width
        return cur

    def _lower_ports_stacked(self, b, port) -> int:
        """Slots of the ports side by side, in their order: the port's own with one port, else a copy."""
        if len(self.ports) == 1:
            return b.input(next(iter(self.ports)))
        at = stacked = b.scratch(sum(self.ports.values()))
        for p, w in self.ports.items():
            b.emit("COPY", port=port, WIDTH=w, IN=b.input(p), OUT=at)
            at += w
        return stacked

    # --- the identified subsystem -----------------------------------------------------------------------
    def coefficients(self, theta: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """theta split by lag: u(k) = sum_l N_l s(k-l) + sum_l M_l u(k-l).

        Parameters
        ----------
        theta : torch.Tensor, optional
            (B', n_u, n_phi); by default the estimator's own.

        Returns
        -------
        N : torch.Tensor
            (B, n_lags, n_u, n_sig), the coefficients of the signals at ``lags``.
        M : torch.Tensor
            (B, max(nc, 1), n_u, n_u), the coefficients of u(k-1)..u(k-nc) (zeros if ``feed_u`` is False).
        """
        theta = self.theta if theta is None else theta
        B = theta.shape[0]
        N = theta.new_zeros(B, len(self.lags), self.n_u, self.n_sig)
        j, offset = 0, 0
        for _s, w in self.signals.items():
            for li in range(len(self.lags)):
                N[:, li, :, offset:offset + w] = theta[:, :, j:j + w]
                j += w
            offset += w
        M = theta.new_zeros(B, max(self.nc, 1), self.n_u, self.n_u)
        if self.feed_u:
            M[:, : self.nc] = theta[:, :, j:].reshape(B, self.n_u, self.nc, self.n_u).permute(0, 2, 1, 3)
        return N, M

    # --- the identified subsystem as a transfer function (``rcotorch.estimator.transfer``) ---------------------------
    def frequency_response(self, omega) -> torch.Tensor:
        """The identified subsystem's frequency response at z = exp(j omega dt).

        H(z) = (I - sum_l M_l z^-l)^-1 sum_l N_l z^-l, from the regressor signals to u.

        Parameters
        ----------
        omega : array_like
            Angular frequencies [rad/s], (F,).

        Returns
        -------
        torch.Tensor
            Complex, (B, F, n_u, n_sig); NaN for a member whose denominator is singular or not finite.

        Raises
        ------
        ConfigError
            If the estimator has no sample time (``sample_time``).
        """
        return transfer.frequency_response(self, omega)

    def dc_gain(self) -> torch.Tensor:
        """DC gain of the identified subsystem: (I - sum M_l)^-1 sum N_l.

        Without fed-back u (M = 0) it is sum N_l, with no linear solve.

        Returns
        -------
        torch.Tensor
            (B, n_u, n_sig); NaN for a member whose I - sum M_l is singular or not finite.
        """
        return transfer.dc_gain(self)

    def to_control(self, member: int = 0) -> control.TransferFunction:
        """The identified subsystem of one member as a discrete python-control ``TransferFunction`` (dt),
        from the regressor signals to u, with named signals and the block's name as the system's name.

        Inputs are the regressor signals in port order, named after them (``'y0'``, ``'y0[1]'`` for a wide
        port, a feature's name such as ``'y0^3'``); outputs are ``'u'`` (``'u[i]'`` for n_u > 1). So
        ``control.interconnect([known, identified.to_control()], inputs='w', outputs='y')`` with a known model
        whose ports carry the same names (``rt.models``, ``rt.models.label_ports``) builds the refined model.

        Parameters
        ----------
        member : int, optional
            The batch member (negative counts from the end).

        Returns
        -------
        control.TransferFunction
            Discrete, with sample time ``sample_time`` (True where the estimator has none).

        Raises
        ------
        ConfigError
            If the block has no members yet or ``member`` is out of range.
        """
        return transfer.to_control(self, member)
