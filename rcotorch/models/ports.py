"""Any python-control plant as rcotorch's known model: its inputs and outputs picked by name and renamed.

A known model has the inputs ``w`` (measured excitation) and ``u`` (where the unknown subsystem acts) and the
outputs ``y`` (measured) and ``y0`` (what the unknown subsystem sees). ``label_ports`` picks them from a plant's
own signals (by name, by the base name of a vector signal such as ``'q'`` for ``q[0], q[1]``, or by index) and
returns the plant with its signals renamed (``w``, ``w[i]``, ...), ready for ``control.interconnect`` by name;
``known_model`` turns it into the ``LTI`` block that ``rt.refinement`` takes.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from ..blocks.base import DEFAULT_DTYPE
from ..blocks.lti import LTI
from ..errors import ConfigError
from .structures import vector

if TYPE_CHECKING:
    import control

Signals = str | int | Sequence[str | int]


def label_ports(plant, w: Signals, u: Signals, y: Signals, y0: Signals, name: str = "known") -> control.StateSpace:
    """The plant with inputs [w..., u...] and outputs [y..., y0...], named as rcotorch's known model expects.

    Each of w, u, y, y0 is a signal name, the base name of a vector signal, an index, or a list of them.

    Parameters
    ----------
    plant : control.StateSpace or control.TransferFunction
        The plant (continuous or discrete).
    w, u : str, int or sequence of them
        The plant's inputs that carry the measured excitation and the unknown subsystem's action; one input
        may serve both (a force that the excitation and the unknown spring share).
    y, y0 : str, int or sequence of them
        The plant's outputs that are measured and that the unknown subsystem sees; one output may be both.
    name : str, optional
        The system's name (for ``control.interconnect``).

    Returns
    -------
    control.StateSpace
        Inputs ``w``/``w[i]``, ``u``/``u[i]``; outputs ``y``/``y[i]``, ``y0``/``y0[i]``; the plant's states.

    Raises
    ------
    ConfigError
        If ``plant`` is of another type, or a signal is unknown, out of range or names nothing.
    """
    import control
    if isinstance(plant, control.TransferFunction):
        plant = control.tf2ss(plant)
    if not isinstance(plant, control.StateSpace):
        raise ConfigError(f"label_ports: expected a control.StateSpace or TransferFunction, got {type(plant).__name__}")
    ins = {port: _pick(plant.input_labels, spec, f"input {port}") for port, spec in (("w", w), ("u", u))}
    outs = {port: _pick(plant.output_labels, spec, f"output {port}") for port, spec in (("y", y), ("y0", y0))}
    i, o = ins["w"] + ins["u"], outs["y"] + outs["y0"]
    return control.ss(plant.A, plant.B[:, i], plant.C[o], plant.D[np.ix_(o, i)], plant.dt, name=name,
                      inputs=[s for p, idx in ins.items() for s in vector(p, len(idx))],
                      outputs=[s for p, idx in outs.items() for s in vector(p, len(idx))],
                      states=plant.state_labels)


def known_model(plant, w: Signals, u: Signals, y: Signals, y0: Signals, dt: float | None = None,
                name: str = "known", x0=None, dtype=DEFAULT_DTYPE) -> LTI:
    """The known-model block (ports w, u -> y, y0) of a python-control plant (see ``label_ports``).

    A continuous plant is discretized by zero-order hold at ``dt``.

    Parameters
    ----------
    plant : control.StateSpace or control.TransferFunction
        The plant.
    w, u, y, y0 : str, int or sequence of them
        Its signals, as for ``label_ports``.
    dt : float, optional
        Sample time [s]; needed for a continuous plant.
    name : str, optional
        The block's name.
    x0 : array_like, optional
        Initial state (n,) or (B, n); zero by default.
    dtype : torch.dtype, optional
        Floating-point type (float64 by default).

    Returns
    -------
    LTI
        Ports ``w``, ``u`` -> ``y``, ``y0``, each as wide as the signals picked for it.

    Raises
    ------
    ConfigError
        As ``label_ports`` and ``LTI.from_control`` do.
    """
    sys = label_ports(plant, w, u, y, y0, name=name)
    widths = {}
    for label in sys.input_labels + sys.output_labels:
        port = label.split("[")[0]
        widths[port] = widths.get(port, 0) + 1
    return LTI.from_control(sys, inputs={p: widths[p] for p in ("w", "u")}, outputs={p: widths[p] for p in ("y", "y0")},
                            dt=dt, name=name, x0=x0, dtype=dtype)


def _pick(labels: list[str], spec: Signals, what: str) -> list[int]:
    """Indices of the named signals: exact names, base names of vectors (``q`` for ``q[0]``, ``q[1]``), indices."""
    items = [spec] if isinstance(spec, (str, int)) else list(spec)
    if not items:
        raise ConfigError(f"label_ports: {what} names no signal; the plant's signals are {labels}")
    out = []
    for item in items:
        if isinstance(item, int) and not isinstance(item, bool):
            if not 0 <= item < len(labels):
                raise ConfigError(f"label_ports: {what}: index {item} is out of range; the plant's signals are "
                                  f"{labels}")
            out.append(item)
        elif item in labels:
            out.append(labels.index(item))
        else:
            members = [k for k, label in enumerate(labels) if label.startswith(f"{item}[")]
            if not members:
                raise ConfigError(f"label_ports: {what}: the plant has no signal {item!r}; its signals are {labels}")
            out += members
    return out
