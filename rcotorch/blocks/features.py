"""Basis features: a small vocabulary of functions of an estimator's input ports that both engines run.

The identified subsystem stays linear in theta, u = theta phi, but phi may be built from basis functions of
the ports instead of the ports themselves (a cubic spring, Coulomb friction, a saturation)::

    import rcotorch as rt
    f = rt.features
    rt.RCOEstimator.static_gain({"y0": 1}, features=f.power("y0", 3))               # u = theta y0^3
    rt.RCOEstimator.static_gain({"v": 1}, features=[f.port("v"), f.sign("v"), f.power("v", 2) * f.sign("v")])

A term is ``coefficient * f_1(x_1) * f_2(x_2) * ...`` where each factor f is one of

===================  ====================================  ===============================
``port(p)``          x                                      ``p``
``power(p, e)``      x^e (integer e >= 1)                   ``p^e``
``sign(p)``          -1, 0 or 1                             ``sign(p)``
``abs(p)``           abs(x)                                 ``|p|``
``saturation``       clamp(x, lo, hi)                       ``sat(p, lo, hi)``
``dead_zone``        x - clamp(x, lo, hi): 0 inside         ``dz(p, lo, hi)``
``tanh(p, scale)``   tanh(x / scale)                        ``tanh(p/scale)``
``affine(p, a, b)``  a x + b                                ``(a*p+b)``
===================  ====================================  ===============================

and x is an input port (``'y0'``) or one channel of it (``'y0[1]'``). A term over a whole port of width w > 1
is w features, one per channel; the whole-port factors of one term must have the same width. Terms multiply
(``f.sign("v") * f.power("v", 2)``; ``product('y0', 'w')`` and ``monomial(y0=2, w=1)`` are shortcuts), scale
(``0.5 * f.port("v")``), and ``constant(c)`` is a term without factors (an offset). A list of terms is the
regressor vector, in order; the names (the last column) label theta's entries (``theta_names``).

The PyTorch engine evaluates a term with tensor operations in the order the native engine uses
(``csrc/lanes.h``, ``feature``), so the two agree to rounding. Functions of the user's own are possible too
(``features={'name': callable}``); written with NumPy, they are compiled for the native engine
(``rcotorch.engine.compiled.compile_features``).
"""

from __future__ import annotations

import builtins
import math
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import torch

from ..engine import kernels
from ..errors import ConfigError, DimensionError

_REF = re.compile(r"^\s*([A-Za-z_]\w*)\s*(?:\[\s*(\d+)\s*\])?\s*$")


def _fmt(v: float) -> str:
    return f"{v:g}"


@dataclass(frozen=True)
class Factor:
    """One factor f(x) of a term; build them with the functions of this module.

    Parameters
    ----------
    kind : str
        'pow', 'sign', 'abs', 'sat', 'deadzone', 'tanh' or 'affine' (see the module table).
    port : str
        The input port x is read from.
    channel : int, optional
        The channel of the port; None: the whole port.
    power : int, optional
        The exponent of 'pow'.
    params : tuple of float, optional
        (lo, hi) for 'sat' and 'deadzone', (scale,) for 'tanh', (a, b) for 'affine'.
    """

    kind: str
    port: str
    channel: int | None = None
    power: int = 1
    params: tuple[float, ...] = ()

    def ref(self, c: int | None = None) -> str:
        """The reference of x: ``'p'`` or ``'p[c]'``.

        Parameters
        ----------
        c : int, optional
            The channel read from a whole port (ignored where the factor names its channel).

        Returns
        -------
        str
        """
        ch = self.channel if self.channel is not None else c
        return self.port if ch is None else f"{self.port}[{ch}]"

    def name(self, c: int | None = None) -> str:
        """The readable name of the factor, e.g. ``'y0^3'``, ``'sign(v)'``, ``'sat(x, -1, 1)'``.

        Parameters
        ----------
        c : int, optional
            The channel read from a whole port.

        Returns
        -------
        str
        """
        x, p = self.ref(c), self.params
        if self.kind == "pow":
            return x if self.power == 1 else f"{x}^{self.power}"
        if self.kind == "sign":
            return f"sign({x})"
        if self.kind == "abs":
            return f"|{x}|"
        if self.kind == "tanh":
            return f"tanh({x})" if p[0] == 1.0 else f"tanh({x}/{_fmt(p[0])})"
        if self.kind == "affine":
            return f"({_fmt(p[0])}*{x}{'-' if p[1] < 0 else '+'}{_fmt(builtins.abs(p[1]))})"
        return f"{'sat' if self.kind == 'sat' else 'dz'}({x}, {_fmt(p[0])}, {_fmt(p[1])})"

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        """f(x) elementwise, in the native engine's order of operations.

        Parameters
        ----------
        x : torch.Tensor
            (B, width), the port (or channel) values.

        Returns
        -------
        torch.Tensor
            (B, width).
        """
        k, p = self.kind, self.params
        if k == "pow":
            r = x
            for _ in range(self.power - 1):
                r = r * x
            return r
        if k == "sign":
            return (x > 0).to(x.dtype) - (x < 0).to(x.dtype)
        if k == "abs":
            return x.abs()
        if k == "sat":
            return torch.clamp(x, p[0], p[1])
        if k == "deadzone":
            return x - torch.clamp(x, p[0], p[1])
        if k == "tanh":
            return torch.tanh(x / p[0])
        return p[0] * x + p[1]                                   # affine


class Term:
    """A feature ``coefficient * f_1(x_1) * ...``; build terms with the functions of this module.

    Terms multiply (``*``) with each other and with numbers.

    Parameters
    ----------
    factors : Sequence[Factor], optional
        The factors; none for a constant.
    coefficient : float, optional
        The constant factor.

    Raises
    ------
    ConfigError
        If ``coefficient`` is not finite.

    Shape
    -----
    Called with port tensors (B, port width), a term returns (B, w): w = 1, or the width of the whole ports it
    reads.
    """

    def __init__(self, factors: Sequence[Factor] = (), coefficient: float = 1.0):
        self.factors = tuple(factors)
        self.coefficient = float(coefficient)
        if not math.isfinite(self.coefficient):
            raise ConfigError(f"features: coefficient must be finite, got {coefficient!r}")

    def __mul__(self, other) -> Term:
        if isinstance(other, Term):
            return Term(self.factors + other.factors, self.coefficient * other.coefficient)
        if isinstance(other, (int, float)):
            return Term(self.factors, self.coefficient * other)
        return NotImplemented

    __rmul__ = __mul__

    def __repr__(self) -> str:
        return f"Term({self.name({})!r})"

    # --- checks against an estimator's ports -----------------------------------------------------------
    def width(self, ports: Mapping[str, int], block: str = "identified") -> int:
        """The number of features this term gives for the estimator's port widths (checks the references).

        Parameters
        ----------
        ports : Mapping[str, int]
            The estimator's input ports and widths.
        block : str, optional
            The estimator's name, for error messages.

        Returns
        -------
        int
            1, or the width of the whole ports the term reads.

        Raises
        ------
        ConfigError
            If a factor reads a port the estimator does not have.
        DimensionError
            If a channel is out of range, or whole ports of different widths are multiplied.
        """
        widths = set()
        for f in self.factors:
            if f.port not in ports:
                close = [p for p in ports if p.lower() == f.port.lower()]
                raise ConfigError(f"block '{block}': feature {self.name({})!r} reads port '{f.port}', but the "
                                  f"estimator's ports are {list(ports)}" +
                                  (f" (did you mean '{close[0]}'?)" if close else ""))
            w = ports[f.port]
            if f.channel is not None:
                if f.channel >= w:
                    raise DimensionError(f"block '{block}': feature {self.name({})!r} reads channel {f.channel} of "
                                         f"port '{f.port}', which has width {w}")
            elif w > 1:
                widths.add(w)
        if len(widths) > 1:
            raise DimensionError(f"block '{block}': feature {self.name({})!r} multiplies whole ports of different "
                                 f"widths {sorted(widths)}; pick channels, e.g. 'y0[0]'")
        return widths.pop() if widths else 1

    def names(self, ports: Mapping[str, int]) -> list[str]:
        """One readable name per feature, e.g. ['y0^3'] or ['y0[0]^3', 'y0[1]^3'].

        Parameters
        ----------
        ports : Mapping[str, int]
            The estimator's input ports and widths.

        Returns
        -------
        list of str
        """
        return [self.name(ports, c) for c in range(self.width(ports))]

    def name(self, ports: Mapping[str, int], c: int = 0) -> str:
        """The name of one feature of the term.

        Parameters
        ----------
        ports : Mapping[str, int]
            The estimator's input ports and widths.
        c : int, optional
            The feature (whole ports of width > 1 read channel c).

        Returns
        -------
        str
        """
        parts = [f.name(c if f.channel is None and ports.get(f.port, 1) > 1 else None) for f in self.factors]
        if not parts:
            return _fmt(self.coefficient)
        body = "*".join(parts)
        return body if self.coefficient == 1.0 else f"{_fmt(self.coefficient)}*{body}"

    # --- the two engines --------------------------------------------------------------------------------
    def __call__(self, inputs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """The features from the port tensors.

        Parameters
        ----------
        inputs : Mapping[str, torch.Tensor]
            Port -> (B, port width).

        Returns
        -------
        torch.Tensor
            (B, w), w from ``width``.
        """
        ports = {p: t.shape[1] for p, t in inputs.items()}
        B = next(iter(inputs.values())).shape[0]
        ref = next(iter(inputs.values()))
        w = self.width(ports)
        v = torch.full((B, w), self.coefficient, dtype=ref.dtype, device=ref.device)
        for f in self.factors:
            x = inputs[f.port]
            x = x[:, f.channel:f.channel + 1] if f.channel is not None else x
            v = v * f(x)
        return v

    def encode(self, ports: Mapping[str, int], slot: Callable[[str], int], const: Callable[..., int]) -> dict:
        """This term as an entry of the native engine's FEATURE record by name (engine.h: FEATURE_TERM and
        its FACTORS; ``rcotorch.engine.lowering.Builder.emit`` lays it out).

        Parameters
        ----------
        ports : Mapping[str, int]
            The estimator's input ports and widths.
        slot : Callable[[str], int]
            Port -> the slot of its first channel.
        const : Callable[..., int]
            Stores constants and returns the slot of the first one.

        Returns
        -------
        dict
            WIDTH, COEF (the coefficient's slot) and ``factors``: per factor KIND, SRC, STRIDE, POWER, PARAM.
        """
        coefficient = const(self.coefficient)
        factors = [dict(KIND=kernels.FACTOR[_KINDS[f.kind]],
                        SRC=slot(f.port) + (f.channel if f.channel is not None else 0),
                        STRIDE=1 if f.channel is None and ports[f.port] > 1 else 0, POWER=f.power,
                        PARAM=const(*f.params) if f.params else const(0.0)) for f in self.factors]
        return dict(WIDTH=self.width(ports), COEF=coefficient, factors=factors)


_KINDS = {"pow": "POW", "sign": "SIGN", "abs": "ABS", "sat": "SAT", "deadzone": "DEADZONE", "tanh": "TANH",
          "affine": "AFFINE"}


def _parse(ref: str) -> tuple[str, int | None]:
    m = _REF.match(ref) if isinstance(ref, str) else None
    if not m:
        raise ConfigError(f"features: {ref!r} is not a port reference such as 'y0' or 'y0[1]'")
    return m.group(1), None if m.group(2) is None else int(m.group(2))


def _term(kind: str, ref: str, power: int = 1, params: tuple[float, ...] = ()) -> Term:
    port, ch = _parse(ref)
    params = tuple(float(p) for p in params)
    if not all(math.isfinite(p) for p in params):
        raise ConfigError(f"features: {kind} of {ref!r} needs finite parameters, got {params}")
    return Term([Factor(kind, port, ch, power, params)])


# --- the vocabulary --------------------------------------------------------------------------------------
def port(ref: str) -> Term:
    """x itself.

    Parameters
    ----------
    ref : str
        A port (``'y0'``) or one channel of it (``'y0[1]'``).

    Returns
    -------
    Term

    Raises
    ------
    ConfigError
        If ``ref`` is not a port reference.
    """
    return _term("pow", ref)


def power(ref: str, exponent: int) -> Term:
    """x^exponent (x^3: a cubic spring).

    Parameters
    ----------
    ref : str
        A port or one channel of it.
    exponent : int
        An integer >= 1.

    Returns
    -------
    Term

    Raises
    ------
    ConfigError
        If ``exponent`` is not an integer >= 1, or ``ref`` is not a port reference.
    """
    if not isinstance(exponent, int) or isinstance(exponent, bool) or exponent < 1:
        raise ConfigError(f"features: power of {ref!r} needs an integer exponent >= 1, got {exponent!r}")
    return _term("pow", ref, exponent)


def monomial(exponents: Mapping[str, int] | None = None, **by_port: int) -> Term:
    """prod_p x_p^e_p, e.g. ``monomial(y0=2, w=1)`` or ``monomial({'y0[1]': 2})``.

    Parameters
    ----------
    exponents : Mapping[str, int], optional
        Port reference -> integer exponent >= 1 (for references that are not Python names, e.g. channels).
    **by_port : int
        Port name -> integer exponent >= 1.

    Returns
    -------
    Term

    Raises
    ------
    ConfigError
        If no port is given, or an exponent or reference is invalid.
    """
    exps = {**(exponents or {}), **by_port}
    if not exps:
        raise ConfigError("features: monomial needs at least one port")
    term = Term()
    for ref, e in exps.items():
        term = term * power(ref, e)
    return term


def product(*refs: str) -> Term:
    """x_1 x_2 ... of ports (or channels).

    Parameters
    ----------
    *refs : str
        Port references, at least one.

    Returns
    -------
    Term

    Raises
    ------
    ConfigError
        If no port is given, or a reference is invalid.
    """
    if not refs:
        raise ConfigError("features: product needs at least one port")
    term = Term()
    for ref in refs:
        term = term * port(ref)
    return term


def sign(ref: str) -> Term:
    """sign(x) in {-1, 0, 1} (Coulomb friction).

    Parameters
    ----------
    ref : str
        A port or one channel of it.

    Returns
    -------
    Term
    """
    return _term("sign", ref)


def absolute(ref: str) -> Term:
    """abs(x) (e.g. ``absolute('v') * port('v')`` for quadratic damping).

    Parameters
    ----------
    ref : str
        A port or one channel of it.

    Returns
    -------
    Term
    """
    return _term("abs", ref)


def saturation(ref: str, low: float, high: float) -> Term:
    """clamp(x, low, high).

    Parameters
    ----------
    ref : str
        A port or one channel of it.
    low, high : float
        The bounds, low <= high, finite.

    Returns
    -------
    Term

    Raises
    ------
    ConfigError
        If low > high or a bound is not finite.
    """
    if not low <= high:
        raise ConfigError(f"features: saturation of {ref!r} needs low <= high, got {low}, {high}")
    return _term("sat", ref, params=(low, high))


def dead_zone(ref: str, low: float, high: float | None = None) -> Term:
    """x - clamp(x, low, high): zero inside [low, high]; ``dead_zone('x', d)`` is [-d, d].

    Parameters
    ----------
    ref : str
        A port or one channel of it.
    low : float
        The lower bound, or with ``high`` left out the half-width d of [-|d|, |d|].
    high : float, optional
        The upper bound.

    Returns
    -------
    Term

    Raises
    ------
    ConfigError
        If low > high or a bound is not finite.
    """
    lo, hi = (-builtins.abs(low), builtins.abs(low)) if high is None else (low, high)
    if not lo <= hi:
        raise ConfigError(f"features: dead zone of {ref!r} needs low <= high, got {lo}, {hi}")
    return _term("deadzone", ref, params=(lo, hi))


def tanh(ref: str, scale: float = 1.0) -> Term:
    """tanh(x / scale) (a smooth sign).

    Parameters
    ----------
    ref : str
        A port or one channel of it.
    scale : float, optional
        > 0, finite.

    Returns
    -------
    Term

    Raises
    ------
    ConfigError
        If ``scale`` is not a finite number > 0.
    """
    if not scale > 0:
        raise ConfigError(f"features: tanh of {ref!r} needs scale > 0, got {scale!r}")
    return _term("tanh", ref, params=(scale,))


def affine(ref: str, gain: float = 1.0, offset: float = 0.0) -> Term:
    """gain x + offset.

    Parameters
    ----------
    ref : str
        A port or one channel of it.
    gain : float, optional
        Finite.
    offset : float, optional
        Finite.

    Returns
    -------
    Term
    """
    return _term("affine", ref, params=(gain, offset))


def constant(value: float = 1.0) -> Term:
    """A constant feature (an offset the estimator can fit).

    Parameters
    ----------
    value : float, optional
        The constant, finite.

    Returns
    -------
    Term
    """
    return Term((), value)


abs = absolute  # noqa: A001  rcotorch.blocks.features.abs reads like the other names


def as_terms(features) -> list[Term] | None:
    """An estimator's features as a list of terms, where they are vocabulary only.

    Parameters
    ----------
    features : Term, sequence, or Mapping
        A term, a list of terms, or a mapping whose values are terms or Python callables.

    Returns
    -------
    list of Term or None
        None where some value is a Python callable (compiled apart, ``RCOEstimator.lower``).
    """
    if isinstance(features, Term):
        return [features]
    values = list(features.values()) if isinstance(features, Mapping) else list(features)
    return values if all(isinstance(v, Term) for v in values) else None
