"""Electrical circuits used as known subsystems, with named signals (like ``models.structure``)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from .structures import vector

if TYPE_CHECKING:
    import control

SIGNALS = ("charge", "current", "v_C", "v_R")


def series_rlc(R: float, L: float, C: float, measured: Sequence[str] = ("v_R",),
               sees: Sequence[str] = ("v_C", "v_R"), actuation: bool = True) -> control.StateSpace:
    """Series RLC circuit driven by a voltage source w (and, if ``actuation``, a second series source u):

        L i' + R i + q / C = w + u,   q' = i,   state [q, i].

    Outputs are ``measured`` then ``sees``, each one of 'charge' (q), 'current' (i), 'v_C' (q / C, the
    capacitor voltage) or 'v_R' (R i, the voltage across the resistor). No output feeds an input through
    (D = 0). Inputs are w, then u. Signals are named as rcotorch's known model expects them: inputs ``w``,
    ``u``; outputs ``y`` (``measured``) and ``y0`` (``sees``), ``[i]`` appended where there are several;
    states ``q`` (charge) and ``i`` (current).

    Parameters
    ----------
    R : float
        Resistance [ohm], > 0.
    L : float
        Inductance [H], > 0.
    C : float
        Capacitance [F], > 0.
    measured : Sequence[str], optional
        The measured outputs (``y``).
    sees : Sequence[str], optional
        The outputs the unknown subsystem sees (``y0``).
    actuation : bool, optional
        Add the input u of the unknown subsystem.

    Returns
    -------
    control.StateSpace
        Continuous.

    Raises
    ------
    ValueError
        If R, L or C is not positive, or a signal is unknown.
    """
    import control
    R, L, C = float(R), float(L), float(C)
    if min(R, L, C) <= 0:
        raise ValueError(f"series_rlc: R, L, C must be positive, got R={R}, L={L}, C={C}")
    A = np.array([[0.0, 1.0], [-1.0 / (L * C), -R / L]])
    b = np.array([[0.0], [1.0 / L]])
    Bm = np.hstack([b, b]) if actuation else b
    rows = {"charge": [1.0, 0.0], "current": [0.0, 1.0], "v_C": [1.0 / C, 0.0], "v_R": [0.0, R]}
    outs = list(measured) + list(sees)
    for sig in outs:
        if sig not in rows:
            raise ValueError(f"unknown circuit signal {sig!r}: use one of {list(SIGNALS)}")
    Cm = np.array([rows[s] for s in outs])
    names = dict(inputs=["w", "u"] if actuation else ["w"],
                 outputs=vector("y", len(measured)) + vector("y0", len(sees)), states=["q", "i"])
    return control.ss(A, Bm, Cm, np.zeros((len(outs), Bm.shape[1])), **names)
