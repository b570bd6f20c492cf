"""The seed paper's Figure 1 as one call: physical system, simulated system, z = y - y_hat, estimator.

``refinement`` wires the blocks and declares their roles (``Graph.roles``), so that the runner, monitor and
figures find the estimator, the known model and the model error whatever the blocks are called.
``derive_markov`` gives the Markov parameters of u -> z, with their sign and the relative degree, from the
known model.
"""

from __future__ import annotations

import copy
from collections.abc import Iterable, Mapping, Sequence

import torch

from .blocks import DEFAULT_DTYPE, Block, Sum
from .errors import ConfigError, PortError
from .estimator import RCOEstimator
from .graph import Graph
from .lti import LTI


def refinement(known: Block, identified: RCOEstimator, *, truth: Block | None = None,
               physical: Block | None = None, data: Block | None = None, excitation: Block | None = None,
               nu: int | None = None, batch_size: int = 1, dtype: torch.dtype = DEFAULT_DTYPE,
               device: str | torch.device = "cpu", exogenous: str = "w", actuation: str = "u",
               measured: str = "y", feeds: Mapping[str, str] | None = None, blocks: Sequence[Block] = (),
               connections: Iterable = (), input_holdoff: int | None = None,
               noise: Block | None = None) -> Graph:
    """Build the seed paper's Figure 1: physical system, simulated system, z = y - y_hat, estimator.

    The known subsystem ``known`` has inputs ``w`` (exogenous) and ``u`` (from the unknown subsystem) and
    outputs ``y`` (measured) and the signals the unknown subsystem sees (e.g. ``y0``). The physical system is
    one of:

    * ``truth``: the true unknown subsystem (one input, one output port); the physical system is then a
      copy of ``known`` (block ``plant``) with ``truth`` (block ``unknown``) in feedback from
      ``plant.y0`` to ``plant.u``;
    * ``physical``: any block with input ``w`` and output ``y`` (e.g. a continuous truth discretized whole);
    * ``data``: recorded measurements, a source with outputs ``w`` and ``y`` (and ``valid`` if it has gaps).

    The simulated system is ``known`` in feedback with ``identified`` (the RCO estimator); its regressor
    ports are fed by the known model's outputs of the same name (or ``w``), or as mapped by ``feeds``
    ({estimator port: 'block.port'}). Further blocks of the simulated system, e.g. filters that turn a known
    model's output into the estimator's regressors, are given as ``blocks`` and wired by ``connections``
    (as in ``Graph``); ``feeds`` then names their outputs. Unless the estimator already has Markov
    parameters, ``nu`` of them are derived from ``known``: beta_i = -H_i of u -> y (z = y - y_hat), from its
    relative degree d on.

    ``noise``: measurement noise of a simulated physical system, a source whose output ``out`` has the width
    of ``y`` (e.g. ``WhiteNoise(1, std=0.01, seed=7)``); it is added to the physical system's output in a
    block ``measurement`` (y = plant.y + noise), so the refinement sees noisy data as it would from a sensor.

    Recorded data with missing samples of the input ``w``: the known model runs on with the held input, so
    after a gap the update is held (``valid`` = 0) for ``input_holdoff`` samples, by default the samples until
    the known model's impulse response w -> y has decayed below 1e-3 of its peak for good, plus the
    estimator's window (``holdoff_samples``). A hold-off set on the data block itself is kept.
    """
    given = [x is not None for x in (truth, physical, data)]
    if sum(given) != 1:
        raise ConfigError("refinement: give exactly one of truth=, physical= or data=")
    for port in (exogenous, actuation):
        if port not in known.inputs:
            raise PortError(f"refinement: known model '{known.name}' has no input '{port}'; its inputs are "
                            f"{list(known.inputs)}")
    if measured not in known.outputs:
        raise PortError(f"refinement: known model '{known.name}' has no output '{measured}'; its outputs are "
                        f"{list(known.outputs)}")
    kn, en = known.name, identified.name
    parts: list[Block] = [known, identified, *blocks]
    conns: list = list(connections)
    if data is not None:
        if data.name != "data":
            raise ConfigError(f"refinement: name the recorded-data block 'data' (got '{data.name}')")
        parts.append(data)
        w_src, y_src = f"data.{exogenous}", f"data.{measured}"
        for p in (exogenous, measured):
            if p not in data.outputs:
                raise PortError(f"refinement: data block has no output '{p}'; its outputs are {list(data.outputs)}")
    else:
        if excitation is None:
            raise ConfigError("refinement: a simulated physical system needs excitation= (e.g. WhiteNoise)")
        excitation.name = "excitation"
        parts.append(excitation)
        w_src = "excitation.out"
        if truth is not None:
            if len(truth.inputs) != 1 or len(truth.outputs) != 1:
                raise PortError(f"refinement: truth= must be a block with one input and one output port (the "
                                f"unknown subsystem: what it sees -> the force it adds); block '{truth.name}' has "
                                f"inputs {list(truth.inputs)} and outputs {list(truth.outputs)}")
            plant = copy.deepcopy(known)
            plant.name = "plant"
            truth.name = "unknown"
            (t_in,), (t_out,) = list(truth.inputs), list(truth.outputs)
            sees = [p for p in known.outputs if p != measured]
            if len(sees) != 1:
                raise ConfigError(f"refinement: with truth=, the known model needs exactly one output besides "
                                  f"'{measured}' for the unknown subsystem to see; it has {list(known.outputs)}")
            parts += [plant, truth]
            conns += [(w_src, f"plant.{exogenous}"), (f"plant.{sees[0]}", f"unknown.{t_in}"),
                      (f"unknown.{t_out}", f"plant.{actuation}")]
            y_src = f"plant.{measured}"
        else:
            physical.name = "plant"
            parts.append(physical)
            conns.append((w_src, f"plant.{exogenous}"))
            y_src = f"plant.{measured}"
    width = known.outputs[measured]
    if noise is not None:
        if data is not None:
            raise ConfigError("refinement: noise= is for a simulated physical system; recorded data carry "
                              "their own noise")
        if list(noise.inputs) or "out" not in noise.outputs or noise.outputs["out"] != width:
            raise PortError(f"refinement: noise block '{noise.name}' must be a source with one output 'out' "
                            f"of width {width} (the width of '{measured}'); it has inputs {list(noise.inputs)} "
                            f"and outputs {dict(noise.outputs)}")
        noise.name = "noise"
        parts += [noise, Sum({"clean": 1, "noise": 1}, width, name="measurement")]
        conns += [(y_src, "measurement.clean"), ("noise.out", "measurement.noise")]
        y_src = "measurement.out"
    parts.append(Sum({"y": 1, "y_hat": -1}, width, name="error"))
    conns += [(y_src, "error.y"), (f"{kn}.{measured}", "error.y_hat"), (w_src, f"{kn}.{exogenous}"),
              (f"{en}.u", f"{kn}.{actuation}"), ("error.out", f"{en}.z")]
    feeds = dict(feeds or {})
    for port in identified.ports:
        if port in feeds:
            conns.append((feeds[port], f"{en}.{port}"))
        elif port == exogenous:
            conns.append((w_src, f"{en}.{port}"))
        elif port in known.outputs:
            conns.append((f"{kn}.{port}", f"{en}.{port}"))
        else:
            raise PortError(f"refinement: estimator input '{port}' has no source: the known model's outputs are "
                            f"{list(known.outputs)}; map it with feeds={{'{port}': 'block.port'}}")
    if identified.beta.shape[1] == 0:
        if nu is None:
            raise ConfigError("refinement: pass nu= (how many Markov parameters) or give the estimator markov=")
        beta, d = derive_markov(known, actuation, measured, nu)
        identified.set_markov(beta, d)
    if data is not None and hasattr(data, "gaps") and data.gaps(exogenous) and exogenous not in data.holdoff:
        n = holdoff_samples(known, identified, exogenous, measured) if input_holdoff is None else input_holdoff
        data.set_holdoff({exogenous: n})
    if data is not None and "valid" in data.outputs:
        conns.append(("data.valid", f"{en}.valid"))
    if identified.dt is None:
        identified.dt = known.dt
    roles = {"estimator": en, "known": kn, "physical": "data" if data is not None else "plant",
             "error": "error.out", "measured": y_src, "prediction": f"{kn}.{measured}", "exogenous": w_src}
    if data is None:
        roles["excitation"] = "excitation"
    return Graph(parts, conns, batch_size=batch_size, dtype=dtype, device=device, roles=roles)


def holdoff_samples(known: LTI, identified: RCOEstimator, exogenous: str = "w", measured: str = "y",
                    tol: float = 1e-3, horizon: int = 20_000) -> int:
    """Samples to hold the update after a missing input sample: until the known model's impulse response
    exogenous -> measured stays below ``tol`` times its peak (within ``horizon``), plus the estimator's window
    (its Markov parameters and past regressors)."""
    H = known.markov(exogenous, measured, horizon).abs().flatten(2).amax(2).amax(0)      # (horizon,)
    above = (H > tol * H.max()).nonzero()
    decay = int(above[-1]) + 1 if above.numel() else 0
    return decay + identified.window + identified.nc


def derive_markov(known: LTI, actuation: str, measured: str, nu: int, tol: float = 1e-12
                  ) -> tuple[torch.Tensor, int]:
    """beta_d..beta_(d+nu-1) of u -> z for z = y - y_hat (minus the known model's Markov parameters) and the
    relative degree d (the first nonzero one, relative to the largest in a long horizon)."""
    if nu < 1:
        raise ConfigError(f"nu must be at least 1, got {nu}")
    horizon = max(4 * nu, 64)
    H = known.markov(actuation, measured, horizon + nu)
    scale = H.abs().amax()
    if not bool(scale > 0):
        raise ConfigError(f"known model '{known.name}': u -> {measured} has zero Markov parameters; "
                          "the unknown subsystem cannot be seen in the measurement")
    nonzero = (H.abs().flatten(2).amax(2).amax(0) > tol * scale).nonzero()
    d = int(nonzero[0])
    return -H[:, d:d + nu], d
