"""The seed paper's Figure 1 as one call: physical system, simulated system, z = y - y_hat, estimator.

``refinement`` wires the blocks and declares their roles (``Graph.roles``), so that the runner, monitor and
figures find the estimator, the known model and the model error whatever the blocks are called. The blocks
given enter the graph under the names their user gave them; one left with its class's default name enters as
a copy named for its part of the figure (``excitation``, ``plant``, ``unknown``, ``noise``), so the caller's
block is never renamed.
``derive_markov`` gives the Markov parameters of u -> z, with their sign and the relative degree, from the
known model.
"""

from __future__ import annotations

import copy
import inspect
from collections.abc import Iterable, Mapping, Sequence

import torch

from .blocks.base import DEFAULT_DTYPE, Block, Sum
from .blocks.lti import LTI
from .errors import ConfigError, PortError
from .estimator.rco import RCOEstimator
from .graph import Graph


def refinement(known: Block, identified: RCOEstimator, *, truth: Block | None = None,
               physical: Block | None = None, data: Block | None = None, excitation: Block | None = None,
               nu: int | None = None, batch_size: int = 1, dtype: torch.dtype = DEFAULT_DTYPE,
               device: str | torch.device = "cpu", exogenous: str = "w", actuation: str = "u",
               measured: str = "y", feeds: Mapping[str, str] | None = None, blocks: Sequence[Block] = (),
               connections: Iterable = (), input_holdoff: int | None = None,
               noise: Block | None = None, feedback: str | None = None) -> Graph:
    """Build the seed paper's Figure 1: physical system, simulated system, z = y - y_hat, estimator.

    The known subsystem ``known`` has inputs ``w`` (exogenous) and ``u`` (from the unknown subsystem) and
    outputs ``y`` (measured) and the signals the unknown subsystem sees (e.g. ``y0``). The physical system is
    given by exactly one of:

    * ``truth``: the true unknown subsystem (one input, one output port); the physical system is then a
      copy of ``known`` (block ``plant``) with ``truth`` in feedback from ``plant.y0`` to ``plant.u``;
    * ``physical``: any block with input ``w`` and output ``y`` (e.g. a continuous truth discretized whole);
    * ``data``: recorded measurements, a source with outputs ``w`` and ``y`` (and ``valid`` if it has gaps).

    The simulated system is ``known`` in feedback with ``identified`` (the RCO estimator); its regressor
    ports are fed by the known model's outputs of the same name (or ``w``), or as mapped by ``feeds``
    ({estimator port: 'block.port'}). Further blocks of the simulated system, e.g. filters that turn a known
    model's output into the estimator's regressors, are given as ``blocks`` and wired by ``connections``
    (as in ``Graph``); ``feeds`` then names their outputs. Unless the estimator already has Markov
    parameters, ``nu`` of them are derived from ``known``: beta_i = -H_i of u -> y (z = y - y_hat), from its
    relative degree d on.

    Recorded data with missing samples of the input ``w``: the known model runs on with the held input, so
    after a gap the update is held (``valid`` = 0) for ``input_holdoff`` samples, by default the samples until
    the known model's impulse response w -> y has decayed below 1e-3 of its peak for good, plus the
    estimator's window (``holdoff_samples``). A hold-off set on the data block itself is kept.

    The blocks given become parts of the graph, their names and sample times as given, as the modules given
    to a ``torch.nn`` container become its own: ``excitation``, the physical block, ``truth`` and ``noise``
    enter as they are where their user named them (``graph.blocks[name]``); one that still has its class's
    default name (or a name another block of the graph has) enters as a copy named for its part,
    ``excitation``, ``plant``, ``unknown`` or ``noise`` (reach it through ``graph.blocks`` or ``graph.role``).
    The known model, the estimator and ``blocks`` enter as they are: the estimator given is the one that runs,
    so its ``theta``, ``P`` and ``to_control()`` give the refinement's results after a run. Where it has no
    Markov parameters, those derived here are set on it (``set_markov``) with the known model's sample time
    (the estimator's ``sample_time`` where it has no ``dt``). The data block enters as it is, unless a hold-off
    is set here: then the graph plays a copy with that hold-off (``Recorded.with_holdoff``, which shares the
    recorded samples), and the block given keeps its own (``graph.blocks['data'].holdoff`` is the one played).

    Parameters
    ----------
    known : Block
        The known subsystem, with inputs ``exogenous`` and ``actuation`` and output ``measured``.
    identified : RCOEstimator
        The estimator, the identified subsystem.
    truth : Block, optional
        The true unknown subsystem (one input, one output port) of a simulated physical system.
    physical : Block, optional
        A simulated physical system with input ``w`` and output ``y``.
    data : Block, optional
        Recorded measurements (named 'data'), a source with outputs ``w`` and ``y``.
    excitation : Block, optional
        The source of ``w`` for a simulated physical system (e.g. ``WhiteNoise``).
    nu : int, optional
        How many Markov parameters to derive from ``known`` (needed unless the estimator has them).
    batch_size : int, optional
        B, the number of parallel members.
    dtype : torch.dtype, optional
        Floating-point type of the graph (float64 by default).
    device : str or torch.device, optional
        Device of the graph.
    exogenous : str, optional
        The known model's input port for the exogenous signal (and the data's column port).
    actuation : str, optional
        The known model's input port for u, the unknown subsystem's output.
    measured : str, optional
        The known model's (and the physical system's) measured output port.
    feeds : Mapping[str, str], optional
        Estimator port -> 'block.port' that feeds it, where it is not the known model's output of the same
        name (or ``w``).
    blocks : Sequence[Block], optional
        Further blocks of the simulated system (e.g. filters that make the estimator's regressors).
    connections : Iterable, optional
        Their connections, as for ``Graph``.
    input_holdoff : int, optional
        Samples to hold the update after a missing sample of ``w`` (default: ``holdoff_samples``).
    noise : Block, optional
        Measurement noise of a simulated physical system, a source whose output ``out`` has the width of
        ``y`` (e.g. ``WhiteNoise(1, std=0.01, seed=7)``); it is added to the physical system's output in a
        block ``measurement`` (y = plant.y + noise), so the refinement sees noisy data as it would from a
        sensor.
    feedback : {'sampled', 'continuous'}, optional
        How the physics the identified subsystem stands for acts: once per sample, as the refined model applies
        it, or at every instant (a stiffness or a friction of a continuous system). With ``'continuous'`` and a
        known model that samples a continuous system (``LTI.continuous``), the verdict measures the estimates'
        bias from sampling the feedback (``rcotorch.verdict.sampling``). By default ``'sampled'`` for a
        ``truth`` block in feedback and ``'continuous'`` for a ``physical`` system or recorded ``data``.

    Returns
    -------
    Graph
        With the roles 'estimator', 'known', 'physical', 'error', 'measured', 'prediction', 'exogenous' (and
        'excitation' for a simulated physical system).

    Raises
    ------
    ConfigError
        If not exactly one of ``truth``, ``physical`` and ``data`` is given (the message names those given), the
        data block is not named 'data', a simulated system has no excitation, ``noise`` comes with recorded
        data, ``nu`` is missing, or the known model does not give the unknown subsystem exactly one signal to
        see.
    PortError
        If a port the figure wires is missing, ``truth`` or ``noise`` has other ports than it needs, or an
        estimator input has no source.
    """
    given = [f"{k}=" for k, x in (("truth", truth), ("physical", physical), ("data", data)) if x is not None]
    if len(given) != 1:
        raise ConfigError("refinement: give exactly one of truth=, physical= or data= (the physical system); "
                          + (f"got {' and '.join(given)}" if given else "got none of them"))
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
    w_src, y_src, physical_name = _physical_system(known, parts, conns, truth, physical, data, excitation,
                                                   exogenous, actuation, measured)
    y_src = _measurement(noise, data, known.outputs[measured], measured, y_src, parts, conns)
    parts.append(Sum({"y": 1, "y_hat": -1}, known.outputs[measured], name="error"))
    conns += [(y_src, "error.y"), (f"{kn}.{measured}", "error.y_hat"), (w_src, f"{kn}.{exogenous}"),
              (f"{en}.u", f"{kn}.{actuation}"), ("error.out", f"{en}.z")]
    conns += _feeds(known, identified, dict(feeds or {}), exogenous, w_src)
    if identified.beta.shape[1] == 0:
        if nu is None:
            raise ConfigError("refinement: pass nu= (how many Markov parameters) or give the estimator markov=")
        beta, d = derive_markov(known, actuation, measured, nu)
        identified.set_markov(beta, d, dt=known.dt)
    if data is not None:
        played = _played_data(data, known, identified, exogenous, measured, input_holdoff)
        parts = [played if b is data else b for b in parts]
    if data is not None and "valid" in data.outputs:
        conns.append(("data.valid", f"{en}.valid"))
    roles = {"estimator": en, "known": kn, "physical": physical_name,
             "error": "error.out", "measured": y_src, "prediction": f"{kn}.{measured}", "exogenous": w_src}
    if data is None:
        roles["excitation"] = next(b.name for b in parts if w_src == f"{b.name}.out")
    graph = Graph(parts, conns, batch_size=batch_size, dtype=dtype, device=device, roles=roles)
    if feedback is None:
        feedback = "sampled" if truth is not None else "continuous"
    if feedback not in ("sampled", "continuous"):
        raise ConfigError(f"refinement: feedback must be 'sampled' or 'continuous', got {feedback!r}")
    graph.feedback = feedback
    return graph


def _physical_system(known: Block, parts: list, conns: list, truth, physical, data, excitation, exogenous: str,
                     actuation: str, measured: str) -> tuple[str, str, str]:
    """Add the physical system of ``refinement`` (recorded ``data``, the known model with ``truth`` in feedback, or
    a ``physical`` block, driven by ``excitation``) to ``parts`` and ``conns``: its exogenous signal, its measured
    output ('block.port') and its block's name."""
    if data is not None:
        if data.name != "data":
            raise ConfigError(f"refinement: name the recorded-data block 'data' (got '{data.name}')")
        parts.append(data)
        for p in (exogenous, measured):
            if p not in data.outputs:
                raise PortError(f"refinement: data block has no output '{p}'; its outputs are {list(data.outputs)}")
        return f"data.{exogenous}", f"data.{measured}", "data"
    if excitation is None:
        raise ConfigError("refinement: a simulated physical system needs excitation= (e.g. WhiteNoise)")
    excitation = _role_block(excitation, "excitation", parts)
    parts.append(excitation)
    w_src = f"{excitation.name}.out"
    if truth is None:
        physical = _role_block(physical, "plant", parts)
        parts.append(physical)
        conns.append((w_src, f"{physical.name}.{exogenous}"))
        return w_src, f"{physical.name}.{measured}", physical.name
    if len(truth.inputs) != 1 or len(truth.outputs) != 1:
        raise PortError(f"refinement: truth= must be a block with one input and one output port (the "
                        f"unknown subsystem: what it sees -> the force it adds); block '{truth.name}' has "
                        f"inputs {list(truth.inputs)} and outputs {list(truth.outputs)}")
    plant = copy.deepcopy(known)
    plant.name = "plant"
    truth = _role_block(truth, "unknown", [*parts, plant])
    (t_in,), (t_out,) = list(truth.inputs), list(truth.outputs)
    sees = [p for p in known.outputs if p != measured]
    if len(sees) != 1:
        raise ConfigError(f"refinement: with truth=, the known model needs exactly one output besides "
                          f"'{measured}' for the unknown subsystem to see; it has {list(known.outputs)}")
    parts += [plant, truth]
    conns += [(w_src, f"plant.{exogenous}"), (f"plant.{sees[0]}", f"{truth.name}.{t_in}"),
              (f"{truth.name}.{t_out}", f"plant.{actuation}")]
    return w_src, f"plant.{measured}", "plant"


def _played_data(data: Block, known: Block, identified: RCOEstimator, exogenous: str, measured: str,
                 input_holdoff: int | None) -> Block:
    """The data block the graph plays: ``data`` itself, or, where its exogenous input misses samples and it has no
    hold-off for it, a copy with the hold-off ``input_holdoff`` (by default ``holdoff_samples``); ``data`` keeps
    its own hold-offs. The copy shares the recorded samples (``Recorded.with_holdoff``)."""
    if not hasattr(data, "gaps") or not data.gaps(exogenous) or exogenous in data.holdoff:
        return data
    n = holdoff_samples(known, identified, exogenous, measured) if input_holdoff is None else input_holdoff
    if hasattr(data, "with_holdoff"):
        return data.with_holdoff({exogenous: n})
    played = copy.deepcopy(data)
    played.set_holdoff({exogenous: n})
    return played


def _measurement(noise, data, width: int, measured: str, y_src: str, parts: list, conns: list) -> str:
    """Add the measurement noise of a simulated physical system (``refinement``'s ``noise``) to its output ``y_src``
    in a block ``measurement``; the measured signal."""
    if noise is None:
        return y_src
    if data is not None:
        raise ConfigError("refinement: noise= is for a simulated physical system; recorded data carry "
                          "their own noise")
    if list(noise.inputs) or "out" not in noise.outputs or noise.outputs["out"] != width:
        raise PortError(f"refinement: noise block '{noise.name}' must be a source with one output 'out' "
                        f"of width {width} (the width of '{measured}'); it has inputs {list(noise.inputs)} "
                        f"and outputs {dict(noise.outputs)}")
    noise = _role_block(noise, "noise", parts)
    parts += [noise, Sum({"clean": 1, "noise": 1}, width, name="measurement")]
    conns += [(y_src, "measurement.clean"), (f"{noise.name}.out", "measurement.noise")]
    return "measurement.out"


def _feeds(known: Block, identified: RCOEstimator, feeds: Mapping[str, str], exogenous: str, w_src: str) -> list:
    """The connections into the estimator's regressor ports: as ``feeds`` maps them, else from the exogenous signal
    or the known model's output of the same name."""
    conns = []
    for port in identified.ports:
        if port in feeds:
            conns.append((feeds[port], f"{identified.name}.{port}"))
        elif port == exogenous:
            conns.append((w_src, f"{identified.name}.{port}"))
        elif port in known.outputs:
            conns.append((f"{known.name}.{port}", f"{identified.name}.{port}"))
        else:
            raise PortError(f"refinement: estimator input '{port}' has no source: the known model's outputs are "
                            f"{list(known.outputs)}; map it with feeds={{'{port}': 'block.port'}}")
    return conns


def _role_block(block: Block, name: str, taken: Sequence[Block]) -> Block:
    """The block that plays a part of the figure: the block itself under the name its user gave it, or, where it
    carries its class's default name (or one another block of the graph has), a copy under the part's name.

    Parameters
    ----------
    block : Block
        The block given.
    name : str
        The part's name (``'plant'``, ``'unknown'``, ``'excitation'``, ``'noise'``).
    taken : Sequence[Block]
        The blocks of the graph so far.

    Returns
    -------
    Block
        ``block`` itself where it is so named or named by its user uniquely; otherwise a copy of it
        (``copy.deepcopy``) with the part's name, so that ``block`` keeps its own.
    """
    own = inspect.signature(type(block).__init__).parameters.get("name")
    chosen = own is not None and block.name != own.default
    if block.name == name or (chosen and block.name not in {b.name for b in taken}):
        return block
    named = copy.deepcopy(block)
    named.name = name
    return named


def holdoff_samples(known: LTI, identified: RCOEstimator, exogenous: str = "w", measured: str = "y",
                    tol: float = 1e-3, horizon: int = 20_000) -> int:
    """Samples to hold the update after a missing input sample.

    They last until the known model's impulse response exogenous -> measured stays below ``tol`` times its
    peak (within ``horizon``), plus the estimator's window (its Markov parameters and past regressors).

    Parameters
    ----------
    known : LTI
        The known model.
    identified : RCOEstimator
        The estimator, with its Markov parameters set.
    exogenous : str, optional
        The known model's input port.
    measured : str, optional
        The known model's output port.
    tol : float, optional
        The level, relative to the peak, below which the response counts as decayed.
    horizon : int, optional
        The number of samples of the impulse response examined.

    Returns
    -------
    int
    """
    H = known.markov(exogenous, measured, horizon).abs().flatten(2).amax(2).amax(0)      # (horizon,)
    above = (H > tol * H.max()).nonzero()
    decay = int(above[-1]) + 1 if above.numel() else 0
    return decay + identified.window + identified.nc


def derive_markov(known: LTI, actuation: str, measured: str, nu: int, tol: float = 1e-12
                  ) -> tuple[torch.Tensor, int]:
    """The Markov parameters of u -> z for z = y - y_hat and the relative degree, from the known model.

    beta_i = -H_i, the known model's Markov parameters of u -> y with the sign of z, for i = d..d+nu-1, where d
    is the first index whose parameter is nonzero (above ``tol`` times the largest in a horizon of
    max(4 nu, 64) + nu).

    Parameters
    ----------
    known : LTI
        The known model (any block with a ``markov(input, output, n)`` method).
    actuation : str
        Its input port for u.
    measured : str
        Its output port y.
    nu : int
        The number of Markov parameters, >= 1.
    tol : float, optional
        The relative size below which a Markov parameter counts as zero.

    Returns
    -------
    beta : torch.Tensor
        (Bp, nu, width(y), width(u)).
    d : int
        The relative degree.

    Raises
    ------
    ConfigError
        If ``nu`` < 1, or every Markov parameter of u -> y is zero.
    """
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
