"""Initial models from measured data, and free-run simulation of a known model with a fitted unknown part.

RCMR refines a model that is almost right; with real measurements someone has to supply that model first.
``MassSpringDamper`` is the linear second-order model

    y'' = -a y' - b y + g (w + u) + d0

(mass-spring-damper per unit mass: damping a = d/m, stiffness b = k1/m, input gain g, constant force d0)
with the measured input w, the measured output y (a position) and a port u, in the units of w, through which
an unknown subsystem acts (a cubic spring: u = theta y0^3, see ``cubic_coefficient``). It is fitted to a
stretch of data by output error (``MassSpringDamper.fit``: an ARX guess refined by least squares on the
free-run simulation error), turned into the known model of a refinement (``lti``), and simulated free run,
with or without a feedback law for u (``simulate``, ``initial_state``).

Discretization (sample time dt), chosen for measured data:

* w is a sampled continuous signal, so between samples it is interpolated linearly (first-order hold,
  ``foh=True``), or with ``spline=True`` by the cubic spline through its samples (``spline_slopes``): the
  input then has two channels, w(k) and the spline's slope there, and the model sees w(k), s(k), w(k+1) and
  s(k+1) over each sample (the cubic Hermite piece between them). A zero-order hold delays the input by half a
  sample, which for a resonance at f0 ~ fs / 9 (the Silverbox) costs more model error than the nonlinearity
  being looked for; the linear interpolation's corners distort its harmonics enough that the cubic spline
  lowers the Silverbox's model error about threefold.
* u(k) comes from the identified subsystem once per sample and is held over the sample (zero-order hold).
* y0, the signal the unknown subsystem sees, is the position predicted ``lead`` samples after t_k from the
  state and input at t_k (lead = 0.5: mid-sample). A force held over [t_k, t_k+1) is then the midpoint rule
  of the continuous force; evaluating the spring at t_k instead (lead = 0) lags it by half a sample, which acts
  as negative damping growing with amplitude, and biases a cubic coefficient low.

The discrete state is xi = x - G2 w(k) with x = [y, y', 1] (the constant 1 carries d0) and G2 the term of
the next sample's input channels (zero for a ZOH), so the model is causal: x(k+1) = A xi(k) + B [w(k); u(k)],
[y; y0](k) = C xi(k) + D [w(k); u(k)], with D's u column zero (u never acts on y or y0 at once). The position
y0 sees between t_k and t_k+1 is predicted from the input's value and slope at t_k (the spline's Taylor
line; the held value without the spline).
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from ..blocks.base import DEFAULT_DTYPE
from ..blocks.lti import LTI
from ..errors import ConfigError, DataError


def rmse(a, b) -> float:
    """Root mean square of a - b.

    Parameters
    ----------
    a, b : array_like
        Of the same shape (or broadcastable).

    Returns
    -------
    float
    """
    d = np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64)
    return float(np.sqrt(np.mean(d * d)))


SEES = ("position", "velocity", "input")        # the channels y0 may hold (MassSpringDamper.lti)


@dataclass(frozen=True, eq=False)
class DiscreteModel:
    """x(k+1) = A x(k) + B [w(k); u(k)], [y(k); y0(k)] = C x(k) + D [w(k); u(k)] with D[:, -1] = 0.

    An input w of m channels (1, or 2 with a spline's slope), one feedback port u, outputs y (measured) and y0
    (seen by the unknown subsystem).

    Parameters
    ----------
    A : numpy.ndarray
        (n, n).
    B : numpy.ndarray
        (n, m + 1), the columns of w and u.
    C : numpy.ndarray
        (2, n), the rows of y and y0.
    D : numpy.ndarray
        (2, m + 1), its u column zero.
    dt : float
        Sample time [s].

    Raises
    ------
    ConfigError
        If the shapes do not fit, or u acts on y or y0 at once.
    """

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray
    dt: float

    def __post_init__(self):
        n, m1 = self.A.shape[0], self.B.shape[-1]
        if self.A.shape != (n, n) or self.B.shape != (n, m1) or m1 < 2 or self.C.shape != (2, n) or \
                self.D.shape != (2, m1):
            raise ConfigError(f"DiscreteModel: shapes A {self.A.shape}, B {self.B.shape}, C {self.C.shape}, "
                              f"D {self.D.shape}; expected (n, n), (n, m + 1), (2, n), (2, m + 1)")
        if np.any(self.D[:, -1] != 0):
            raise ConfigError("DiscreteModel: u must not act on y or y0 at once (D[:, -1] must be zero)")

    @property
    def channels(self) -> int:
        """m, the input's channels."""
        return self.B.shape[1] - 1

    def simulate(self, w, x0, feedback: Callable[[float], float] | Polynomial | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Free run from a state driven by w: no measurement is fed back.

        Parameters
        ----------
        w : array_like
            (T,) or (T, m), the input.
        x0 : array_like
            (n,), the initial state.
        feedback : callable or Polynomial, optional
            u(k) = feedback(y0(k)) (e.g. ``lambda q: theta * q**3``, or a ``Polynomial``, which runs compiled);
            without it u = 0.

        Returns
        -------
        y, y0, u : numpy.ndarray
            (T,) each.

        Raises
        ------
        ConfigError
            If ``x0`` has the wrong number of entries, or ``w`` the wrong number of channels.
        """
        m = self.channels
        w = np.asarray(w, dtype=np.float64)
        w = w.reshape(-1, 1) if w.ndim == 1 else w
        if w.ndim != 2 or w.shape[1] != m:
            raise ConfigError(f"simulate: w has shape {w.shape}; the model's input has {m} channel(s), (T, {m})")
        x0 = np.asarray(x0, dtype=np.float64).reshape(-1)
        if x0.shape != (self.A.shape[0],):
            raise ConfigError(f"simulate: x0 has {x0.size} entries, the model has {self.A.shape[0]} states")
        T = w.shape[0]
        if feedback is None:
            out = _lsim(self.A, self.B[:, :m], self.C, self.D[:, :m], w, x0)
            return out[:, 0], out[:, 1], np.zeros(T)
        if isinstance(feedback, Polynomial):
            out = np.empty((3, T))
            _polynomial_loop()(self.A, np.ascontiguousarray(self.B[:, :m]), self.B[:, m].copy(), self.C[0].copy(),
                               self.C[1].copy(), self.D[0, :m].copy(), self.D[1, :m].copy(),
                               np.ascontiguousarray(w), x0.copy(), np.asarray(feedback.coefficients, dtype=np.float64),
                               np.asarray(feedback.powers, dtype=np.float64), out)
            return out[0], out[1], out[2]
        A, bw, bu = self.A, self.B[:, :m], self.B[:, m].copy()
        cy, c0 = self.C[0].copy(), self.C[1].copy()
        dy, d0 = self.D[0, :m], self.D[1, :m]
        y, y0, u = np.empty(T), np.empty(T), np.empty(T)
        x = x0.copy()
        for k in range(T):
            wk = w[k]
            y[k] = cy @ x + dy @ wk
            q = c0 @ x + d0 @ wk
            y0[k] = q
            uk = float(feedback(q))
            u[k] = uk
            x = A @ x + bw @ wk + bu * uk
        return y, y0, u


@dataclass(frozen=True)
class Polynomial:
    """The feedback u = sum_i coefficients[i] q^powers[i] of the position q the unknown subsystem sees.

    Parameters
    ----------
    coefficients : tuple of float
        theta_i.
    powers : tuple of int
        The exponents, one per coefficient.
    """

    coefficients: tuple[float, ...]
    powers: tuple[int, ...]

    def __call__(self, q):
        """u for a position q.

        Parameters
        ----------
        q : float or numpy.ndarray
            The position the unknown subsystem sees.

        Returns
        -------
        float or numpy.ndarray
            Of q's shape.
        """
        return sum(c * q ** p for c, p in zip(self.coefficients, self.powers))


def _polynomial_step(A, bw, bu, cy, c0, dy, d0, w, x, coef, powers, out):
    """``DiscreteModel.simulate`` with u = sum_i coef[i] q^powers[i]: rows y, y0, u of ``out``; w (T, m), bw
    (n, m), dy and d0 (m,)."""
    n, m = x.shape[0], w.shape[1]
    nxt = np.empty(n)
    for k in range(w.shape[0]):
        y, q = 0.0, 0.0
        for c in range(m):
            y += dy[c] * w[k, c]
            q += d0[c] * w[k, c]
        for i in range(n):
            y += cy[i] * x[i]
            q += c0[i] * x[i]
        u = 0.0
        for j in range(coef.shape[0]):
            u += coef[j] * q ** powers[j]
        out[0, k], out[1, k], out[2, k] = y, q, u
        for i in range(n):
            acc = bu[i] * u
            for c in range(m):
                acc += bw[i, c] * w[k, c]
            for j in range(n):
                acc += A[i, j] * x[j]
            nxt[i] = acc
        x[:] = nxt


_compiled_loop = None


def _polynomial_loop():
    """``_polynomial_step`` compiled by numba (kept on disk between processes), or as it is without numba."""
    global _compiled_loop
    if _compiled_loop is None:
        try:
            import numba
            _compiled_loop = numba.njit(cache=True)(_polynomial_step)
        except ImportError:
            _compiled_loop = _polynomial_step
    return _compiled_loop


def _lsim(A, B, C, D, u, x0) -> np.ndarray:
    """Linear response (T, p) of x(k+1) = A x + B u, y = C x + D u from x0, one IIR filter per input."""
    import scipy.signal
    T = u.shape[0]
    y = np.zeros((T, C.shape[0]))
    for j in range(B.shape[1]):
        num, den = scipy.signal.ss2tf(A, B[:, j:j + 1], C, D[:, j:j + 1])
        for i in range(C.shape[0]):
            y[:, i] += scipy.signal.lfilter(num[i], den, u[:, j])
    if np.any(x0 != 0):  # C A^k x0: the impulse response of (A, A x0, C, C x0)
        impulse = np.zeros(T)
        impulse[0] = 1.0
        num, den = scipy.signal.ss2tf(A, (A @ x0)[:, None], C, (C @ x0)[:, None])
        for i in range(C.shape[0]):
            y[:, i] += scipy.signal.lfilter(num[i], den, impulse)
    return y


def spline_slopes(w) -> np.ndarray:
    """The slope per sample, dw/dk, at every sample of the cubic spline through the samples of ``w`` (not-a-knot
    ends, ``scipy.interpolate.CubicSpline``): the second input channel of a ``MassSpringDamper(spline=True)``.

    Parameters
    ----------
    w : array_like
        (T,), T >= 2.

    Returns
    -------
    numpy.ndarray
        (T,).
    """
    import scipy.interpolate
    w = np.asarray(w, dtype=np.float64).reshape(-1)
    if w.size < 2:
        return np.zeros_like(w)
    k = np.arange(w.size, dtype=np.float64)
    return scipy.interpolate.CubicSpline(k, w)(k, 1)


def _input_powers(A, b, h, dt, degree):
    """Phi = e^(A h) and Gamma_j = int_0^h e^(A (h - t)) b (t / dt)^j dt for j = 0..degree, (n, degree + 1), by
    one exponential of [[A, b e_0^T], [0, N]] h, N the shift of the chain t^k / k! (its top right block holds
    int_0^h e^(A (h - t)) b t^k / k! dt)."""
    import scipy.linalg
    n = A.shape[0]
    M = np.zeros((n + degree + 1, n + degree + 1))
    M[:n, :n], M[:n, n] = A, b
    for k in range(degree):
        M[n + k, n + k + 1] = 1.0
    E = scipy.linalg.expm(M * h)
    scale = np.array([math.factorial(j) / dt ** j for j in range(degree + 1)])
    return E[:n, :n], E[:n, n:] * scale


def _hermite_input(A, b, dt):
    """Phi and the input terms (n, 4) of one sample whose input is the cubic Hermite piece of w(k), s(k),
    w(k+1), s(k+1) (values and slopes per sample at both ends)."""
    Phi, g = _input_powers(A, b, dt, dt, 3)
    g0, g1, g2, g3 = g.T
    return Phi, np.c_[g0 - 3 * g2 + 2 * g3, g1 - 2 * g2 + g3, 3 * g2 - 2 * g3, g3 - g2]


def _expm_input(A, b, h, foh=False):
    """exp of the augmented matrix: (Phi, Gamma) of a ZOH over h (``_input_powers`` of degree 0), and with ``foh``
    also the ramp term (its own augmented matrix, the ramp scaled by 1/h inside it)."""
    import scipy.linalg
    n = A.shape[0]
    if not foh:
        Phi, gamma = _input_powers(A, b, h, h, 0)
        return Phi, gamma[:, 0]
    M = np.zeros((n + 2, n + 2))
    M[:n, :n], M[:n, n], M[n, n + 1] = A, b, 1.0 / h
    E = scipy.linalg.expm(M * h)
    return E[:n, :n], E[:n, n], E[:n, n + 1]


@dataclass(frozen=True)
class MassSpringDamper:
    """Linear second-order model y'' = -a y' - b y + g (w + u) + d0 sampled every ``dt`` seconds.

    Parameters
    ----------
    a : float
        Damping per unit mass [1/s].
    b : float
        Stiffness per unit mass [1/s^2].
    g : float
        Input gain [y/(w s^2)].
    d0 : float, optional
        Constant force per unit mass [y/s^2].
    dt : float, optional
        Sample time [s], > 0.
    foh : bool, optional
        Interpolate w linearly between samples (else hold it).
    lead : float, optional
        y0 is the position ``lead`` samples after t_k, in [0, 1] (see the module notes).
    spline : bool, optional
        Interpolate w by the cubic spline through its samples (overrides ``foh``): the input has two channels,
        w and ``spline_slopes(w)``; the methods take w as (T,) and add the slopes, or as (T, 2) (``inputs``).
    u_ahead : bool, optional
        y0 (``lead`` samples after t_k) includes the motion that u(k-1), held from t_k on, makes meanwhile: u(k)
        is not known when y0 is, and u(k-1) is its best guess. A fourth state carries u(k-1).
    fit_rmse : float, optional
        The free-run error of the fit that made the model (NaN where it was not fitted).

    Raises
    ------
    ConfigError
        If ``dt`` is not positive, ``lead`` lies outside [0, 1], or a parameter is not finite.
    """

    a: float
    b: float
    g: float
    d0: float = 0.0
    dt: float = 1.0
    foh: bool = True
    lead: float = 0.5
    fit_rmse: float = field(default=math.nan, compare=False)
    spline: bool = False
    u_ahead: bool = False

    def __post_init__(self):
        if not self.dt or self.dt <= 0:
            raise ConfigError(f"MassSpringDamper: dt must be positive, got {self.dt!r}")
        if not 0 <= self.lead <= 1:
            raise ConfigError(f"MassSpringDamper: lead must lie in [0, 1] samples, got {self.lead!r}")
        if not all(math.isfinite(v) for v in (self.a, self.b, self.g, self.d0)):
            raise ConfigError(f"MassSpringDamper: parameters must be finite, got {self}")

    @property
    def f0(self) -> float:
        """Undamped natural frequency sqrt(b) / (2 pi) [Hz]."""
        return math.sqrt(max(self.b, 0.0)) / (2 * math.pi)

    @property
    def damping_ratio(self) -> float:
        """a / (2 sqrt(b)), NaN where b <= 0."""
        return self.a / (2 * math.sqrt(self.b)) if self.b > 0 else math.nan

    def continuous(self) -> tuple[np.ndarray, np.ndarray]:
        """The continuous model with state [y, y', 1].

        Returns
        -------
        A : numpy.ndarray
            (3, 3).
        b : numpy.ndarray
            (3,), the input vector of w (and of u).
        """
        A = np.array([[0.0, 1.0, 0.0], [-self.b, -self.a, self.d0], [0.0, 0.0, 0.0]])
        return A, np.array([0.0, self.g, 0.0])

    @cached_property
    def discrete(self) -> DiscreteModel:
        """The sampled model (state xi = [y, y', 1] - G2 w(k), see the module notes)."""
        A, bg = self.continuous()
        Phi, bw, G2 = self._sampled_input
        _, bu = _expm_input(A, bg, self.dt)
        n = self.states
        if n > 3:                                  # the 4th state is u of the sample before: u(k-1)
            Phi = np.pad(Phi, ((0, 1), (0, 1)))
            bw, bu = np.pad(bw, ((0, 1), (0, 0))), np.r_[bu, 1.0]
        cy = np.eye(n)[0]
        c0, d0 = self._ahead(0)
        D = np.zeros((2, G2.shape[1] + 1))
        D[0, :-1], D[1, :-1] = cy[:3] @ G2, d0
        return DiscreteModel(Phi, np.c_[bw, bu], np.vstack([cy, c0]), D, self.dt)

    @cached_property
    def _sampled_input(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Phi = e^(A dt), the input columns B_w of the causal state xi and G2 (3, ``channels``): one sample of
        the input as the model interpolates it (module notes)."""
        A, bg = self.continuous()
        if self.spline:
            Phi, G = _hermite_input(A, bg, self.dt)
            G2 = G[:, 2:]
            return Phi, Phi @ G2 + G[:, :2], G2
        if self.foh:
            Phi, G1, G2 = _expm_input(A, bg, self.dt, foh=True)
            return Phi, (Phi @ G2 + G1 - G2)[:, None], G2[:, None]
        Phi, b0 = _expm_input(A, bg, self.dt)
        return Phi, b0[:, None], np.zeros((3, 1))

    @property
    def states(self) -> int:
        """The discrete model's states: y, y', 1, and with ``u_ahead`` u(k-1)."""
        return 4 if self.u_ahead else 3

    def _ahead(self, row: int) -> tuple[np.ndarray, np.ndarray]:
        """The row of C and the entries of D's w columns of state entry ``row`` (0 position, 1 velocity)
        ``lead`` samples after t_k, from the state and the input's value (and slope) at t_k, and with ``u_ahead``
        u(k-1) held from t_k on."""
        A, bg = self.continuous()
        G2 = self._sampled_input[2]
        if self.lead == 0:
            c, d = np.eye(3)[row], G2[row]
        elif not self.spline:                      # the input held at w(k)
            Ph, Gh = _expm_input(A, bg, self.lead * self.dt)
            c, d = Ph[row], Ph[row] @ G2 + Gh[row]
        else:
            Ph, g = _input_powers(A, bg, self.lead * self.dt, self.dt, 1)
            c, d = Ph[row], Ph[row] @ G2 + g[row]
        if self.u_ahead:
            c = np.r_[c, _expm_input(A, bg, self.lead * self.dt)[1][row] if self.lead > 0 else 0.0]
        return c, d

    @property
    def channels(self) -> int:
        """The input's channels: 2 with ``spline`` (w and its slope), else 1."""
        return 2 if self.spline else 1

    def inputs(self, w) -> np.ndarray:
        """The model's input channels for the input samples ``w``: (T, 1), or (T, 2) with the spline's slopes
        (``spline_slopes``, over the samples given); an array that already has them is returned as it is.

        Parameters
        ----------
        w : array_like
            (T,), or (T, ``channels``).

        Returns
        -------
        numpy.ndarray
            (T, ``channels``).
        """
        w = np.asarray(w, dtype=np.float64)
        if w.ndim == 2 and w.shape[1] == self.channels:
            return w
        w = w.reshape(-1)
        return np.c_[w, spline_slopes(w)] if self.spline else w[:, None]

    @property
    def hold_offset(self) -> np.ndarray:
        """G2 (``states``, ``channels``): the discrete state is xi = [y, y', 1] - G2 w(k) (u(k-1) as it is)."""
        return np.pad(self._sampled_input[2], ((0, self.states - 3), (0, 0)))

    def state(self, y: float, v: float, w0=0.0) -> np.ndarray:
        """The discrete state for a position, velocity and input at the same instant.

        Parameters
        ----------
        y : float
            The position.
        v : float
            The velocity.
        w0 : float or array_like, optional
            The input at that instant: its channels (``inputs``), or its value alone (a slope of 0).

        Returns
        -------
        numpy.ndarray
            (``states``,), xi = [y, v, 1] - G2 w0, and u(k-1) = 0 with ``u_ahead``.
        """
        w0 = np.r_[np.asarray(w0, dtype=np.float64).reshape(-1), np.zeros(self.channels)][:self.channels]
        return np.r_[y, v, 1.0, np.zeros(self.states - 3)] - self.hold_offset @ w0

    def lti(self, x0=None, name: str = "known", dtype=DEFAULT_DTYPE, sees: tuple[str, ...] = ("position",)) -> LTI:
        """The model as an rcotorch ``LTI`` with inputs w, u and outputs y, y0 (the known model of a refinement).

        Parameters
        ----------
        x0 : array_like, optional
            Initial discrete state (see ``state``, ``initial_state``); [0, 0, 1] by default.
        name : str, optional
            The block's name.
        dtype : torch.dtype, optional
            Floating-point type (float64 by default).
        sees : tuple of str, optional
            The channels of y0, in order: 'position' (the position ``lead`` samples after t_k), 'velocity' (the
            velocity at the same instant), 'input' (w(k)). A subsystem that sees the velocity and the input can
            refine the damping and the input gain as well as the spring.

        Returns
        -------
        LTI
            Ports w (width ``channels``), u -> y (width 1), y0 (width ``len(sees)``); ``states`` states.

        Raises
        ------
        ConfigError
            If ``sees`` is empty or names another channel.
        """
        m = self.discrete
        if not sees or any(c not in SEES for c in sees):
            raise ConfigError(f"MassSpringDamper.lti: sees must name channels among {SEES}, got {sees!r}")
        rows, feed = [], []
        for channel in sees:
            c, d = self._seen(channel)
            rows.append(c)
            feed.append(d)
        C = np.vstack([m.C[0], *rows])
        D = np.zeros((1 + len(sees), self.channels + 1))
        D[0, :-1], D[1:, :-1] = m.D[0, :-1], feed
        x0 = self.state(0.0, 0.0) if x0 is None else x0
        block = LTI(m.A, m.B, C, D, inputs={"w": self.channels, "u": 1}, outputs={"y": 1, "y0": len(sees)},
                    dt=self.dt, name=name, x0=x0, dtype=dtype)
        block.fitted_states = (0, 1, 2)             # a fit of the initial state leaves u(k-1) as it is
        return block

    def _seen(self, channel: str) -> tuple[np.ndarray, np.ndarray]:
        """The row of C and the entries of D's w columns of one channel of y0 (see ``lti``)."""
        if channel == "position":
            return self._ahead(0)
        if channel == "input":
            return np.zeros(self.states), np.eye(self.channels)[0]
        return self._ahead(1)

    def cubic_coefficient(self, theta):
        """c in y'' = ... - c y^3 for the identified subsystem u = theta y0^3 (u enters as g u): c = -g theta.

        Parameters
        ----------
        theta : float or array_like
            The identified coefficient(s).

        Returns
        -------
        float or array_like
            c, of theta's type and shape.
        """
        return -self.g * theta

    def simulate(self, w, x0, feedback: Callable[[float], float] | None = None) -> np.ndarray:
        """Free-run output from a discrete state (see ``DiscreteModel.simulate``).

        Parameters
        ----------
        w : array_like
            (T,), the input, or its channels (T, ``channels``) (``inputs``).
        x0 : array_like
            (``states``,), the initial discrete state.
        feedback : callable, optional
            u(k) = feedback(y0(k)); u = 0 without it.

        Returns
        -------
        numpy.ndarray
            y, (T,).
        """
        return self.discrete.simulate(self.inputs(w), x0, feedback)[0]

    def initial_state(self, w, y, feedback: Callable[[float], float] | None = None) -> np.ndarray:
        """The discrete state at the first sample whose free run best fits the measured output.

        Least squares over the given samples (e.g. the first 50 of a validation record); the constant state
        stays 1.

        Parameters
        ----------
        w : array_like
            (T,), the input, T >= 2, or its channels (T, ``channels``) (``inputs``: slopes of the whole record
            where the free run goes on beyond these samples).
        y : array_like
            (T,), the measured output.
        feedback : callable, optional
            u(k) = feedback(y0(k)) during the free run; u = 0 without it.

        Returns
        -------
        numpy.ndarray
            (``states``,).

        Raises
        ------
        DataError
            If w and y differ in length, are too short or hold a non-finite sample.
        """
        import scipy.optimize
        w, y = self._signals(w, y, "initial_state", minimum=2)
        base = self.state(0.0, 0.0, w[0])
        e_y, e_v = np.eye(self.states)[0], np.eye(self.states)[1]
        # Linear model: y = y_base + p_y s_y + p_v s_v exactly; with feedback this is the starting point.
        lin = self.discrete
        y_base, zero = lin.simulate(w, base)[0], np.zeros_like(w)
        S = np.c_[lin.simulate(zero, e_y)[0], lin.simulate(zero, e_v)[0]]   # free responses of y and y'
        p, *_ = np.linalg.lstsq(S, y - y_base, rcond=None)
        if feedback is not None:
            scale = np.array([max(np.abs(y).max(), 1e-12), max(np.abs(y).max(), 1e-12) * math.sqrt(self.b)])

            def res(q):
                return lin.simulate(w, base + q[0] * e_y + q[1] * e_v, feedback)[0] - y

            p = scipy.optimize.least_squares(res, p, x_scale=scale).x
        return base + p[0] * e_y + p[1] * e_v

    def _signals(self, w, y, what: str, minimum: int) -> tuple[np.ndarray, np.ndarray]:
        """w as the model's input channels (T, ``channels``) and y as (T,), checked (``_as_signals``)."""
        w = np.asarray(w, dtype=np.float64)
        w2 = w.ndim == 2 and w.shape[1] == self.channels
        w1, y = _as_signals(w[:, 0] if w2 else w, y, what, minimum)
        if w2 and not np.all(np.isfinite(w)):
            raise DataError(f"{what}: sample {int(np.argmax(~np.isfinite(w).all(1)))} is not finite")
        return (w if w2 else self.inputs(w1)), y

    @classmethod
    def fit(cls, w, y, dt: float, foh: bool = True, lead: float = 0.5, spline: bool = False,
            u_ahead: bool = False) -> MassSpringDamper:
        """Fit a, b, g, d0 (and the initial state) to a nearly linear stretch of data by output error.

        A discrete ARX model y(k) = a1 y(k-1) + a2 y(k-2) + b0 w(k) + b1 w(k-1) + b2 w(k-2) + c gives the
        starting point (its poles give a and b, its DC gain g / b, its constant d0 / b); then
        ``scipy.optimize.least_squares`` minimizes the free-run simulation error of this model over the data.
        ``fit_rmse`` is that error.

        Parameters
        ----------
        w : array_like
            (T,), the input, T >= 20.
        y : array_like
            (T,), the measured output.
        dt : float
            Sample time [s].
        foh : bool, optional
            Interpolate w linearly between samples (else hold it).
        lead : float, optional
            y0 is the position ``lead`` samples after t_k.
        spline : bool, optional
            Interpolate w by the cubic spline through its samples (overrides ``foh``).
        u_ahead : bool, optional
            y0 includes the motion of u(k-1) held over the lead (see the class).

        Returns
        -------
        MassSpringDamper

        Raises
        ------
        ConfigError
            If ``dt`` is not positive.
        DataError
            If the data are malformed, or do not look like a stable, second-order system.
        """
        import scipy.optimize
        w, y = _as_signals(w, y, "fit", minimum=20)
        if not dt or dt <= 0:
            raise ConfigError(f"fit: dt must be a positive sample time, got {dt!r}")
        Y = np.c_[y[1:-1], y[:-2], w[2:], w[1:-1], w[:-2], np.ones(len(y) - 2)]
        coef, *_ = np.linalg.lstsq(Y, y[2:], rcond=None)
        a1, a2 = coef[:2]
        poles = np.roots([1.0, -a1, -a2]).astype(complex)
        if np.any(np.abs(poles) >= 1) or np.any((np.abs(poles.imag) < 1e-12) & (poles.real <= 0)):
            raise DataError(f"fit: the ARX model of these data has poles {np.round(poles, 6).tolist()}; they do "
                            "not look like a stable second-order system sampled fast enough (poles inside the "
                            "unit circle, not on the negative real axis). Check the columns, the rows and dt.")
        s = np.log(poles) / dt
        a0, b0 = float(-(s.sum()).real), float(np.prod(s).real)
        gain = 1.0 - a1 - a2
        g0, d00 = float(coef[2:5].sum() / gain * b0), float(coef[5] / gain * b0)
        v0 = (y[1] - y[0]) / dt

        def model(q):
            return cls(q[0], q[1], q[2], q[3], dt, foh, lead, spline=spline, u_ahead=u_ahead)

        channels = model(np.array([a0, b0, g0, d00])).inputs(w)

        def res(q):
            m = model(q)
            return m.simulate(channels, m.state(q[4], q[5], channels[0])) - y

        q0 = np.array([a0, b0, g0, d00, y[0], v0])
        ys = max(float(np.abs(y).max()), 1e-12)
        scale = np.array([max(abs(a0), 1.0), abs(b0), max(abs(g0), 1e-12), max(abs(d00), abs(b0) * ys * 1e-3),
                          ys, ys * math.sqrt(abs(b0))])
        failed = DataError(f"fit: the output-error fit of the linear model failed on these data (max |y| = "
                           f"{ys:.3g}, max |w| = {float(np.abs(w).max()):.3g}); check the columns, their units and dt")
        # Data of extreme scale overflow inside the optimizer: that is reported once, as the fit's failure.
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore", RuntimeWarning)
            try:
                sol = scipy.optimize.least_squares(res, q0, x_scale=scale)
            except (ConfigError, ValueError):          # a step to parameters that are not finite
                raise failed from None
        q = sol.x
        if not np.all(np.isfinite(q)) or q[1] <= 0:
            raise failed
        return cls(*(float(v) for v in q[:4]), float(dt), bool(foh), float(lead), fit_rmse=rmse(sol.fun, 0.0),
                   spline=bool(spline), u_ahead=bool(u_ahead))


    def fit_with_spring(self, w, y, powers: tuple[int, ...] = (3,)) -> tuple[MassSpringDamper, Polynomial]:
        """Offline output-error fit of this linear model and a polynomial spring together.

        a, b, g, d0, the spring's coefficients (u = sum_i theta_i y0^powers[i], starting from zero) and the
        initial state are fitted by ``scipy.optimize.least_squares`` on the free-run simulation error over all
        of ``w``, ``y``, starting from this model. ``fit_rmse`` of the result is that error.

        Parameters
        ----------
        w : array_like
            (T,), the input, T >= 20, or its channels (T, ``channels``).
        y : array_like
            (T,), the measured output.
        powers : tuple of int, optional
            The spring's exponents.

        Returns
        -------
        model : MassSpringDamper
            The fitted linear part.
        spring : Polynomial
            The fitted spring.

        Raises
        ------
        DataError
            If the data are malformed.
        """
        import scipy.optimize
        w, y = self._signals(w, y, "fit_with_spring", minimum=20)
        npw = len(powers)
        ys = max(float(np.abs(y).max()), 1e-12)

        def split(q):
            m = MassSpringDamper(q[0], q[1], q[2], q[3], self.dt, self.foh, self.lead, spline=self.spline,
                                 u_ahead=self.u_ahead)
            return m, Polynomial(tuple(float(v) for v in q[4:4 + npw]), tuple(powers))

        def res(q):
            m, spring = split(q)
            with np.errstate(over="ignore", invalid="ignore"):
                r = m.simulate(w, m.state(q[-2], q[-1], w[0]), spring) - y
            return np.where(np.isfinite(r), r, 1e3 * ys)

        x0 = self.initial_state(w[:50], y[:50])
        q0 = np.r_[self.a, self.b, self.g, self.d0, np.zeros(npw), x0[0] + self.hold_offset[0] @ w[0],
                   x0[1] + self.hold_offset[1] @ w[0]]
        scale = np.r_[max(abs(self.a), 1.0), abs(self.b), max(abs(self.g), 1e-12),
                      max(abs(self.d0), abs(self.b) * ys * 1e-3),
                      [abs(self.b) / max(self.g, 1e-12) * 0.01 * ys ** (1 - p) for p in powers],
                      ys, ys * math.sqrt(abs(self.b))]
        sol = scipy.optimize.least_squares(res, q0, x_scale=scale)
        m, spring = split(sol.x)
        return dataclasses.replace(m, fit_rmse=rmse(sol.fun, 0.0)), spring


def _as_signals(w, y, what: str, minimum: int) -> tuple[np.ndarray, np.ndarray]:
    w = np.asarray(w, dtype=np.float64).reshape(-1)
    y = np.asarray(y, dtype=np.float64).reshape(-1)
    if w.shape != y.shape:
        raise DataError(f"{what}: w and y have different lengths ({w.size} and {y.size})")
    if w.size < minimum:
        raise DataError(f"{what}: needs at least {minimum} samples, got {w.size}")
    bad = ~(np.isfinite(w) & np.isfinite(y))
    if bad.any():
        raise DataError(f"{what}: sample {int(np.argmax(bad))} is not finite (drop or fill gaps first)")
    return w, y
