"""Graphs of blocks wired by port name.

A ``Graph`` is checked when it is built: every name resolves (with a suggestion when it does not), every
required input is driven exactly once, widths agree, direct-feedthrough paths have no cycle (an
algebraic loop), and recorded data is played at the sample time of every block that has one. Each step
evaluates the output ports in an order that respects feedthrough, then advances every block. ``print(graph)``
shows the blocks and the connection table.

A graph may declare *roles*: which block is the estimator, which the known model, which signal the model
error z, and so on. Tools that work on any refinement (the runner, the monitor, figures) find these parts
through the roles, not through block names. ``rcotorch.refinement`` declares them for the seed paper's
Figure 1.
"""

from __future__ import annotations

import copy
import difflib
import logging
import math
import numbers
import operator
import os
import warnings
from collections.abc import Callable, Iterable, Mapping, Sequence

import torch
from torch import nn

from .blocks.base import DEFAULT_DTYPE, Block
from .blocks.sources import Recorded
from .data.recording import same_sample_time
from .engine import compiled, kernels, lowering, memo
from .errors import AlgebraicLoopError, ConfigError, DataError, DimensionError, PortError

Signal = tuple[str, str]
ENGINES = ("auto", "native", "torch")
logger = logging.getLogger("rcotorch")
_TOLD: set[str] = set()              # reasons for the PyTorch engine already logged in this process
# Roles a refinement declares: a block name (``estimator``, ``known``, ``physical``, ``excitation``) or a
# signal 'block.port' (``error``: z = y - y_hat, ``measured``: y, ``prediction``: y_hat).
BLOCK_ROLES = ("estimator", "known", "physical", "excitation")
SIGNAL_ROLES = ("error", "measured", "prediction", "exogenous")


def _step_count(steps) -> int:
    """``steps`` as an int: a non-negative integer (a Python, NumPy or 0-d torch integer)."""
    try:
        n = operator.index(steps)
    except TypeError:
        n = None
    if n is None or n < 0:
        raise ConfigError(f"graph: steps must be a non-negative integer, got {steps!r}")
    return n


def _split(ref: str) -> Signal:
    if not isinstance(ref, str) or ref.count(".") != 1:
        raise PortError(f"signal reference {ref!r} must read 'block.port'")
    b, p = ref.split(".")
    return b.strip(), p.strip()


def _has_sample_time(blk: Block) -> bool:
    """Whether a block has a sample time: an attribute ``dt`` holding a finite number > 0."""
    dt = getattr(blk, "dt", None)
    return isinstance(dt, numbers.Real) and not isinstance(dt, bool) and math.isfinite(dt) and dt > 0


def _suggest(name: str, choices: Iterable[str]) -> str:
    close = difflib.get_close_matches(name, list(choices), n=1)
    return f" (did you mean '{close[0]}'?)" if close else ""


class Graph(nn.Module):
    """Blocks wired by port name.

    The graph is checked when it is built (see the module docstring) and reset for ``batch_size`` members.

    Parameters
    ----------
    blocks : Sequence[Block]
        The blocks (names must be unique).
    connections : Iterable
        Pairs ``("src_block.out_port", "dst_block.in_port")`` or strings ``"src.out -> dst.in"``.
    batch_size : int, optional
        Number of parallel members B.
    dtype : torch.dtype, optional
        One floating-point type for every block: float64 (the default) or float32.
    device : str or torch.device, optional
        One device for every block.
    engine : {'auto', 'native', 'torch'}, optional
        How ``advance`` and ``run`` step: ``'native'`` (the graph lowered to the compiled engine, many steps
        per call; CPU, float64, blocks with a native form; raises with the reason where it does not apply),
        ``'torch'`` (``step`` after ``step``, PyTorch operations only, no compiled code), or ``'auto'`` (native
        where it applies, else torch; the default, or ``$RCOTORCH_ENGINE``). ``auto`` logs once which engine
        runs and why it fell back; ``ran_engine`` and ``engine_reason`` keep it. ``step`` always uses PyTorch;
        both engines update the same state.
    roles : Mapping[str, str], optional
        What the parts of a refinement are, e.g. ``{'estimator': 'refine', 'known': 'model',
        'error': 'err.out'}`` (see ``BLOCK_ROLES`` and ``SIGNAL_ROLES``); ``role()`` and ``role_signal()`` look
        them up.

    Raises
    ------
    ConfigError
        If ``dtype`` or ``engine`` is not one of those allowed, an entry of ``blocks`` is not a block, two
        blocks share a name, or a role is unknown.
    PortError
        If a connection is malformed, names an unknown block or port, drives an input twice, or a required
        input is left unconnected.
    DimensionError
        If a connection joins ports of different widths.
    AlgebraicLoopError
        If direct-feedthrough paths form a cycle.
    DataError
        If recorded data is played at another sample time than a block that has one.

    Shape
    -----
    Every signal ``(block, port)`` is (B, width of the port); a trace of ``run`` is (T, B, width).
    """

    def __init__(self, blocks: Sequence[Block], connections: Iterable, batch_size: int = 1,
                 dtype: torch.dtype = DEFAULT_DTYPE, device: str | torch.device = "cpu",
                 engine: str | None = None, roles: Mapping[str, str] | None = None):
        super().__init__()
        if dtype not in (torch.float64, torch.float32):
            raise ConfigError(f"dtype must be torch.float64 or torch.float32, got {dtype}")
        self.engine = engine or os.environ.get("RCOTORCH_ENGINE", "auto")
        self.blocks = nn.ModuleDict()
        for blk in blocks:
            if not isinstance(blk, Block):
                raise ConfigError(f"graph: {blk!r} is not a rcotorch Block")
            if blk.name in self.blocks:
                raise ConfigError(f"graph: two blocks are named '{blk.name}'")
            if hasattr(self.blocks, blk.name) or "." in blk.name or not blk.name:
                raise ConfigError(f"graph: block '{blk.name}' ({type(blk).__name__}) cannot be named so: the name "
                                  f"is empty, holds a '.' or is taken by torch's module container (such as "
                                  f"'to', 'float', 'update', 'keys'); choose another name=")
            self.blocks[blk.name] = blk
        self.sources: dict[Signal, Signal] = {}
        for conn in connections:
            src, dst = self._parse(conn)
            self._connect(src, dst)
        for name, blk in self.blocks.items():
            for port in blk.inputs:
                if (name, port) not in self.sources and port not in blk.optional_inputs:
                    raise PortError(f"graph: input '{name}.{port}' is not connected")
        self._check_sample_times()
        self.order = self._schedule()
        self.roles = self._check_roles(dict(roles or {}))
        # how the physics the estimator stands for acts: 'sampled' (as the refined model applies it) or
        # 'continuous' (rcotorch.verdict.sampling measures the bias of sampling it; rcotorch.refinement sets it)
        self.feedback = "sampled"
        self.register_buffer("k", torch.zeros((), dtype=torch.int64))
        self.to(device=device, dtype=dtype)
        self.reset(batch_size)
        self._last: dict[Signal, torch.Tensor] = {}
        self._last_native: tuple | None = None      # (signals, order) a native call left, copied when read
        # the native engine's program of this graph, kept while it stands for the graph (rcotorch.engine.lowering:
        # program, refilled, invalidate)
        self._program_cache = lowering.ProgramCache()
        self.hooks: list[Callable[[Graph], object]] = []
        self.ran_engine: str | None = None     # the engine of the last ``advance``
        self.engine_reason: str | None = None  # why it was not the native engine (None when it was)
        self._told: tuple | None = None

    # --- building -------------------------------------------------------------------------------------
    @staticmethod
    def _parse(conn) -> tuple[Signal, Signal]:
        if isinstance(conn, str):
            if "->" not in conn:
                raise PortError(f"connection {conn!r} must read 'src.port -> dst.port'")
            a, b = conn.split("->")
            return _split(a), _split(b)
        try:
            a, b = conn
        except (TypeError, ValueError):
            raise PortError(f"connection {conn!r} must be a pair ('src.port', 'dst.port')") from None
        return _split(a), _split(b)

    def _port(self, sig: Signal, kind: str) -> int:
        b, p = sig
        if b not in self.blocks:
            raise PortError(f"graph: no block '{b}'{_suggest(b, self.blocks)}; blocks are {list(self.blocks)}")
        ports = self.blocks[b].inputs if kind == "input" else self.blocks[b].outputs
        if p not in ports:
            raise PortError(f"graph: block '{b}' has no {kind} port '{p}'{_suggest(p, ports)}; its {kind}s "
                            f"are {list(ports)}")
        return ports[p]

    def _connect(self, src: Signal, dst: Signal) -> None:
        w_out, w_in = self._port(src, "output"), self._port(dst, "input")
        if dst in self.sources:
            s = self.sources[dst]
            raise PortError(f"graph: input '{dst[0]}.{dst[1]}' is driven twice (by '{s[0]}.{s[1]}' and "
                            f"'{src[0]}.{src[1]}')")
        if w_out != w_in:
            raise DimensionError(f"graph: '{src[0]}.{src[1]}' has width {w_out} but '{dst[0]}.{dst[1]}' "
                                 f"expects width {w_in}")
        self.sources[dst] = src

    def _check_sample_times(self) -> None:
        """Recorded data must be played at the sample time of every block that has one (to rounding)."""
        timed = {name: float(blk.dt) for name, blk in self.blocks.items() if _has_sample_time(blk)}
        for name, blk in self.blocks.items():
            if not isinstance(blk, Recorded) or name not in timed:
                continue
            for other, dt in timed.items():
                if other != name and not same_sample_time(timed[name], dt):
                    origin = f" from {blk.source}" if blk.source else ""
                    raise DataError(f"graph: block '{name}' plays recorded data{origin} sampled every {timed[name]} s, "
                                    f"but block '{other}' has the sample time {dt} s; "
                                    f"give the recording its true dt, or pass resample={dt} to the Recorded block to "
                                    "interpolate it onto that grid")

    def _check_roles(self, roles: dict[str, str]) -> dict[str, str]:
        for role, ref in roles.items():
            if role in BLOCK_ROLES:
                if ref not in self.blocks:
                    raise PortError(f"graph: role '{role}' names no block '{ref}'{_suggest(ref, self.blocks)}")
            elif role in SIGNAL_ROLES:
                self._port(_split(ref), "output")
            else:
                raise ConfigError(f"graph: unknown role '{role}'{_suggest(role, BLOCK_ROLES + SIGNAL_ROLES)}; "
                                  f"roles are {BLOCK_ROLES + SIGNAL_ROLES}")
        return roles

    def role(self, role: str) -> Block:
        """The block that plays a role.

        Parameters
        ----------
        role : str
            One of ``BLOCK_ROLES``, e.g. ``'estimator'``, ``'known'``.

        Returns
        -------
        Block

        Raises
        ------
        ConfigError
            If no block has the role.
        """
        if role not in self.roles:
            raise ConfigError(f"graph: no block has the role '{role}' (declared roles: {sorted(self.roles)}); "
                              "build the graph with rcotorch.refinement or pass roles= to Graph")
        return self.blocks[self.roles[role]]

    def known_sample_time(self) -> float | None:
        """The sample time of the block in the ``'known'`` role.

        Returns
        -------
        float or None
            Seconds; None where no block has the role or it has no sample time (times are then counted in
            steps).
        """
        known = self.blocks[self.roles["known"]] if "known" in self.roles else None
        dt = getattr(known, "dt", None)
        return float(dt) if dt else None

    def role_signal(self, role: str) -> Signal:
        """The signal that plays a role.

        Parameters
        ----------
        role : str
            One of ``SIGNAL_ROLES``, e.g. ``'error'`` (z).

        Returns
        -------
        tuple of (str, str)
            (block, port).

        Raises
        ------
        ConfigError
            If no signal has the role.
        """
        if role not in self.roles:
            raise ConfigError(f"graph: no signal has the role '{role}' (declared roles: {sorted(self.roles)}); "
                              "build the graph with rcotorch.refinement or pass roles= to Graph")
        return _split(self.roles[role])

    def _schedule(self) -> list[Signal]:
        """Order the output ports so each is computed after the inputs it feeds through (Kahn's algorithm)."""
        deps: dict[Signal, list[Signal]] = {}
        self._feedthrough = {name: blk.feedthrough() for name, blk in self.blocks.items()}
        for name, blk in self.blocks.items():
            ft = self._feedthrough[name]
            for port in blk.outputs:
                deps[(name, port)] = [self.sources[(name, p)] for p in ft.get(port, ()) if (name, p) in self.sources]
        order, state = [], {}

        def visit(node: Signal, path: list[Signal]):
            if state.get(node) == 2:
                return
            if state.get(node) == 1:
                cycle = path[path.index(node):] + [node]
                raise AlgebraicLoopError("graph: algebraic loop through direct-feedthrough ports: " +
                                         " -> ".join(f"{b}.{p}" for b, p in cycle))
            state[node] = 1
            for dep in deps[node]:
                visit(dep, path + [node])
            state[node] = 2
            order.append(node)

        for node in deps:
            visit(node, [])
        return order

    # --- running --------------------------------------------------------------------------------------
    @property
    def batch_size(self) -> int:
        """B, the number of members the blocks are reset for."""
        return next(iter(self.blocks.values())).batch_size

    def reset(self, batch_size: int | None = None) -> None:
        """Reset every block's state and the step counter.

        Parameters
        ----------
        batch_size : int, optional
            The number of members; by default the present one.
        """
        B = batch_size or self.batch_size
        for blk in self.blocks.values():
            blk.reset(B)
        self.k.zero_()
        self._warn_shared_streams()

    def _warn_shared_streams(self) -> None:
        """Warn where two random sources draw the same stream for a member: their samples are the same numbers
        (scaled), so a measurement noise drawn so is the excitation itself, not independent of it."""
        sources = [(name, blk.stream) for name, blk in self.blocks.items()
                   if isinstance(getattr(blk, "stream", None), torch.Tensor) and blk.stream.dim() == 2]
        for i, (a, sa) in enumerate(sources):
            for b, sb in sources[i + 1:]:
                same = (sa == sb).all(1) if sa.shape == sb.shape else torch.zeros(1, dtype=torch.bool)
                if bool(same.any()):
                    member = int(same.nonzero()[0, 0])
                    more = " and others" if int(same.sum()) > 1 else ""
                    warnings.warn(f"graph: blocks '{a}' and '{b}' draw the same random stream (seed "
                                  f"{int(sa[member, 0])} for member {member}{more}): their samples are the same "
                                  "numbers scaled, not independent; give each its own seed", stacklevel=3)

    @property
    def max_steps(self) -> int | None:
        """The most steps the sources can deliver (recorded data), or None."""
        limits = [blk.max_steps for blk in self.blocks.values() if getattr(blk, "max_steps", None) is not None]
        return min(limits) if limits else None

    def _inputs(self, name: str, ports: Iterable[str], signals) -> dict[str, torch.Tensor]:
        return {p: signals[self.sources[(name, p)]] for p in ports if (name, p) in self.sources}

    def _plan(self) -> tuple[list, list]:
        """For each output port (in evaluation order) and each block: where its inputs come from."""
        def make():
            outs = [(sig, self.blocks[sig[0]], sig[1],
                     [(p, self.sources[(sig[0], p)]) for p in self._feedthrough[sig[0]][sig[1]]
                      if (sig[0], p) in self.sources]) for sig in self.order]
            upds = [(name, blk, [(p, self.sources[(name, p)]) for p in blk.inputs if (name, p) in self.sources])
                    for name, blk in self.blocks.items()]
            return outs, upds
        # keyed by the blocks themselves too: a block replaced under its name gets a new plan
        return memo.derived(self, "plan", (tuple(self.order), tuple(self.sources.items()),
                                           tuple((n, id(b)) for n, b in self.blocks.items())), make)

    def step(self, overrides: Mapping[Signal, torch.Tensor] | None = None,
             frozen: Iterable[str] = ()) -> dict[Signal, torch.Tensor]:
        """Advance every block one step on PyTorch and return all output signals at time k.

        With ``engine='torch'`` no compiled code runs. The hooks are called after the step.

        Parameters
        ----------
        overrides : Mapping[tuple of (str, str), torch.Tensor], optional
            (block, port) -> a value, (B, width), that replaces that output port this step.
        frozen : Iterable[str], optional
            Blocks that are not advanced (used to probe the graph, e.g. for Markov parameters).

        Returns
        -------
        dict[tuple of (str, str), torch.Tensor]
            (block, port) -> its value at time k, (B, width); also kept in ``last``.
        """
        if self.engine == "torch":
            with kernels.disabled():
                return self._step(overrides, frozen)
        return self._step(overrides, frozen)

    def _step(self, overrides, frozen) -> dict[Signal, torch.Tensor]:
        outs, upds = self._plan()
        signals: dict[Signal, torch.Tensor] = {}
        for sig, blk, port, feeds in outs:
            if overrides and sig in overrides:
                signals[sig] = overrides[sig]
                continue
            signals[sig] = blk.output(port, {p: signals[src] for p, src in feeds})
        for name, blk, feeds in upds:
            if name not in frozen:
                blk.update({p: signals[src] for p, src in feeds})
        self.k += 1
        self.last = signals
        for hook in self.hooks:
            hook(self)
        return signals

    @property
    def last(self) -> dict[Signal, torch.Tensor]:
        """The signals of the last step, {(block, port): (B, width)}."""
        if self._last_native is not None:
            signals, order = self._last_native
            self._last, self._last_native = {sig: signals[sig].clone() for sig in order}, None
        return self._last

    @last.setter
    def last(self, value: dict[Signal, torch.Tensor]) -> None:
        self._last, self._last_native = value, None

    @property
    def engine(self) -> str:
        """The engine ``advance`` and ``run`` use: 'auto', 'native' or 'torch'; setting another value raises a
        ``ConfigError``."""
        return self._engine

    @engine.setter
    def engine(self, value: str) -> None:
        if value not in ENGINES:
            raise ConfigError(f"graph: engine must be one of {ENGINES}, got {value!r}")
        self._engine = value

    def native_status(self) -> str | None:
        """Whether ``advance`` runs on the native engine.

        Returns
        -------
        str or None
            None when it does, else why it runs on PyTorch.
        """
        if self.engine == "torch":
            return "engine='torch'"
        return lowering.unsupported(self)

    def advance(self, steps: int, accumulate: Mapping[Signal, torch.Tensor] | None = None,
                record: Mapping[Signal, torch.Tensor] | None = None, every: int = 1) -> None:
        """Advance ``steps`` steps on the engine chosen by ``engine``.

        Afterwards ``last`` holds the signals of the last step.

        Parameters
        ----------
        steps : int
            The number of steps, >= 0.
        accumulate : Mapping[tuple of (str, str), torch.Tensor], optional
            Signal -> a (B,) float64 tensor that gets sum_c signal[b, c]^2 of every step added (e.g. for an
            rms of z).
        record : Mapping[tuple of (str, str), torch.Tensor], optional
            Signal -> a (steps // every, B, width) tensor that receives the signal after every ``every``-th
            step (inside the native engine: no Python per step).
        every : int, optional
            The recording interval in steps.

        Raises
        ------
        ConfigError
            If ``steps`` is not a non-negative integer; if ``engine='native'`` and the graph cannot run natively
            (the reason is in the message); or if a block's compiled function raised in the native engine (the
            message names the block; the state after those steps is not valid).
        """
        steps = _step_count(steps)
        if steps == 0:
            return
        if self.engine == "torch":
            why = "engine='torch'"
        else:
            try:
                prog, why = lowering.program(self), None
            except lowering.NotLowerable as e:
                why = str(e)
        if why is None:
            start = int(self.k)
            with compiled.raised_in_compiled() as raised:
                lowering.advance(self, prog, steps, accumulate, record, every)
            self._ran("native", None)
            if raised:
                raise self._compiled_fault(raised, start, int(self.k)) from raised.first
            return
        if self.engine == "native":
            raise ConfigError(f"graph: engine='native', but {why}")
        self._ran("torch", why)
        for i in range(steps):
            signals = self.step()
            for sig, acc in (accumulate or {}).items():
                z = signals[sig].to(torch.float64)
                acc += (z * z).sum(1)
            if record and (i + 1) % every == 0:
                for sig, buf in record.items():
                    buf[(i + 1) // every - 1] = signals[sig]

    def _compiled_fault(self, raised: compiled.Raised, start: int, end: int) -> ConfigError:
        """The error for an exception that a compiled user function raised in the native engine between steps
        ``start`` and ``end``: it names the block whose function (``Block._user_functions``) is on the
        exception's traceback, where one is."""
        e = raised.first
        what = f"raised {type(e).__name__}: {e} in the native engine (steps {start} to {end}); the graph's state " \
               "after them is not valid"
        for blk in self.blocks.values():
            for fn in blk._user_functions().values():
                name = getattr(getattr(fn, "__code__", None), "co_name", None) or getattr(fn, "__name__", None)
                if name and name in raised.functions:
                    return ConfigError(f"block '{blk.name}': its function {name} {what}")
        return ConfigError(f"graph: a compiled function ({' -> '.join(raised.functions) or 'unknown'}) {what}")

    def _ran(self, engine: str, reason: str | None) -> None:
        """Keep which engine ran and why; with ``engine='auto'`` say it in the log once per graph, and a
        reason for the PyTorch engine once per process (the copies a run makes for its intervals and
        validation fall back for the same reason)."""
        self.ran_engine, self.engine_reason = engine, reason
        if self.engine == "auto" and self._told != (engine, reason):
            self._told = (engine, reason)
            if reason is None:
                logger.info("graph: running on the native engine")
            elif reason not in _TOLD:
                _TOLD.add(reason)
                logger.warning("graph: running on the PyTorch engine: %s", reason)

    def extend(self, blocks: Sequence[Block], sources: Mapping[Signal, Signal]) -> None:
        """Add ``blocks`` to the graph as they are (their state kept, nothing reset), with their inputs wired by
        ``sources`` {(block, input port): (block, output port)}; the graph's own blocks, wiring and step counter
        stay as they were.

        Parameters
        ----------
        blocks : Sequence[Block]
            New blocks, each reset for this graph's batch size, with this graph's dtype and device, and named
            apart from the graph's blocks.
        sources : Mapping[tuple of (str, str), tuple of (str, str)]
            Every input of the new blocks that is not optional -> the output port that drives it (of a new
            block or of one of the graph's).

        Raises
        ------
        ConfigError
            If a block is named as one of the graph's or cannot be named so, or was reset for another batch
            size.
        PortError, DimensionError, AlgebraicLoopError
            As for the constructor, for the new blocks' wiring.
        """
        B = self.batch_size
        for blk in blocks:
            if blk.name in self.blocks or hasattr(self.blocks, blk.name) or "." in blk.name or not blk.name:
                raise ConfigError(f"graph: cannot add block '{blk.name}': the name is taken or not allowed")
            if blk.batch_size != B:
                raise ConfigError(f"graph: block '{blk.name}' is reset for {blk.batch_size} members, the graph "
                                  f"for {B}")
        before = dict(self.sources)
        try:
            for blk in blocks:
                self.blocks[blk.name] = blk
            for dst, src in sources.items():
                self._connect(src, dst)
            for blk in blocks:
                for port in blk.inputs:
                    if (blk.name, port) not in self.sources and port not in blk.optional_inputs:
                        raise PortError(f"graph: input '{blk.name}.{port}' is not connected")
            self._check_sample_times()
            self.order = self._schedule()
        except Exception:                      # refused: the graph as it was
            for blk in blocks:
                if blk.name in self.blocks:
                    del self.blocks[blk.name]
            self.sources = before
            raise
        self._program_cache.invalidate()
        self._last, self._last_native = {}, None

    def add_hook(self, hook: Callable[[Graph], object]) -> Callable:
        """Call ``hook(graph)`` after every step (e.g. a ``MarkovRefresh``).

        A hook with an integer attribute ``every`` promises to act only after steps k with k % every == 0: it
        is called only there on the native engine, which runs the steps in between.

        A hook with an attribute ``acts_on`` (block names) promises to change nothing but those blocks, and one
        with ``keeps_theta = True`` as well never to change an estimator's theta (it may change its P, forgetting
        factors or Markov parameters, which a held estimator's output does not depend on). The end of a run
        then replays its intervals' copies inside one graph where no copy needs its own copy of a block a hook
        changes (``rcotorch.verdict.intervals``); without them every copy is a whole graph of its own.

        Parameters
        ----------
        hook : Callable[[Graph], object]
            Called with the graph.

        Returns
        -------
        Callable
            ``hook`` itself.

        Raises
        ------
        ConfigError
            If the hook's ``acts_on`` names a block the graph does not have.
        """
        unknown = sorted(set(getattr(hook, "acts_on", None) or ()) - set(self.blocks))
        if unknown:
            raise ConfigError(f"add_hook: {type(hook).__name__}'s acts_on names {unknown}, which the graph does not "
                              f"have (its blocks: {sorted(self.blocks)})")
        self.hooks.append(hook)
        return hook

    def run(self, steps: int, record: Mapping[str, str | Callable] | None = None, every: int = 1,
            progress: bool = False) -> dict[str, torch.Tensor]:
        """Run ``steps`` steps and return traces of the recorded signals.

        Signals are recorded inside the native engine; a callable needs Python after every ``every`` steps.

        Parameters
        ----------
        steps : int
            The number of steps.
        record : Mapping[str, str or Callable], optional
            Trace name -> a signal 'block.port', or a callable of the graph returning a tensor.
        every : int, optional
            Take the traces every ``every`` steps, after the step.
        progress : bool, optional
            Show a progress bar (tqdm).

        Returns
        -------
        dict[str, torch.Tensor]
            Name -> (T, B, width) with T = steps // every (a callable's values stacked along T).

        Raises
        ------
        ConfigError
            If ``steps`` is not a non-negative integer, the recorded data gives fewer samples than the run needs,
            or ``every`` is not positive.
        PortError
            If a recorded signal is not an output port of the graph.
        """
        steps = _step_count(steps)
        self.check_steps(steps)
        if every < 1:
            raise ConfigError(f"graph: every must be a positive number of steps, got {every!r}")
        record = dict(record or {})
        signals = {key: _split(ref) for key, ref in record.items() if not callable(ref)}
        for sig in signals.values():
            self._port(sig, "output")
        getters = {key: ref for key, ref in record.items() if callable(ref)}
        bufs = {sig: kernels.empty((steps // every, self.batch_size, self.blocks[sig[0]].outputs[sig[1]]),
                                   _dtype(self), self.k.device) for sig in set(signals.values())}
        traces: dict[str, list] = {key: [] for key in getters}
        bar = None
        if progress:
            from tqdm import tqdm
            bar = tqdm(total=steps, desc="steps", unit="step", mininterval=0.5)
        chunk = every if getters else max(every, steps // 100 // every * every) if bar is not None else steps
        done = 0
        while done < steps:
            m = min(chunk, steps - done)
            self.advance(m, record={sig: buf[done // every:] for sig, buf in bufs.items()}, every=every)
            done += m
            if getters and m == every:
                for key, get in getters.items():
                    traces[key].append(get(self).detach().clone())
            if bar is not None:
                bar.update(m)
        if bar is not None:
            bar.close()
        return {key: bufs[signals[key]] if key in signals else
                torch.stack(traces[key]) if traces[key] else torch.empty(0) for key in record}

    def check_steps(self, steps: int) -> None:
        """Check that the sources (recorded data) can deliver ``steps`` more steps.

        Parameters
        ----------
        steps : int
            The steps to run from the present one.

        Raises
        ------
        ConfigError
            If the recorded data gives fewer samples.
        """
        limit = self.max_steps
        if limit is not None and int(self.k) + steps > limit:
            raise ConfigError(f"graph: {int(self.k) + steps} steps asked for, but the recorded data gives "
                              f"{limit} samples")

    def markov(self, src: str, dst: str, n: int, eps: float = 1.0) -> torch.Tensor:
        """Markov parameters of the map from one output port to another, by probing a copy of the graph.

        Impulses of size ``eps`` in each channel of ``src`` are run against a baseline run, with the block
        owning ``src`` frozen: H_i = (dst with impulse - dst of the baseline)(i) / eps. Exact for linear paths.

        Parameters
        ----------
        src : str
            The output port 'block.port' the impulses replace.
        dst : str
            The output port 'block.port' whose response is read.
        n : int
            The number of Markov parameters (steps of each run).
        eps : float, optional
            The size of the impulses.

        Returns
        -------
        torch.Tensor
            (B, n, width(dst), width(src)).

        Raises
        ------
        PortError
            If ``src`` or ``dst`` is not an output port of the graph.
        """
        s, d = _split(src), _split(dst)
        w_in = self._port(s, "output")
        self._port(d, "output")
        B = self.batch_size
        probe = copy.deepcopy(self)
        probe.hooks = []
        runs = []
        for j in range(-1, w_in):
            probe.reset(B)
            trace = []
            for i in range(n):
                u = torch.zeros(B, w_in, dtype=_dtype(probe), device=self.k.device)
                if i == 0 and j >= 0:
                    u[:, j] = eps
                trace.append(probe.step(overrides={s: u}, frozen=(s[0],))[d])
            runs.append(torch.stack(trace, dim=1))                       # (B, n, w_out)
        base = runs[0]
        H = torch.stack([(r - base) / eps for r in runs[1:]], dim=-1)    # (B, n, w_out, w_in)
        return H

    # --- display --------------------------------------------------------------------------------------
    def table(self) -> str:
        """The blocks with their ports, the connections, the unconnected outputs and the evaluation order.

        Returns
        -------
        str
            The text ``print(graph)`` shows.
        """
        lines = [f"Graph: {len(self.blocks)} blocks, batch {self.batch_size}, {_dtype(self)}"]
        for name, blk in self.blocks.items():
            ins = ", ".join(f"{p}[{w}]" for p, w in blk.inputs.items()) or "-"
            outs = ", ".join(f"{p}[{w}]" for p, w in blk.outputs.items()) or "-"
            lines.append(f"  {name:<12} {type(blk).__name__:<14} in: {ins:<28} out: {outs}")
        lines.append("Connections (source -> destination, width):")
        used = set(self.sources.values())
        for (db, dp), (sb, sp) in self.sources.items():
            lines.append(f"  {sb + '.' + sp:<22} -> {db + '.' + dp:<22} {self.blocks[db].inputs[dp]}")
        unused = [f"{n}.{p}" for n, b in self.blocks.items() for p in b.outputs if (n, p) not in used]
        if unused:
            lines.append("Unconnected outputs: " + ", ".join(unused))
        lines.append("Evaluation order: " + ", ".join(f"{b}.{p}" for b, p in self.order))
        return "\n".join(lines)

    def __str__(self) -> str:
        return self.table()


def _dtype(g: nn.Module) -> torch.dtype:
    for t in g.buffers():
        if t.is_floating_point():
            return t.dtype
    return DEFAULT_DTYPE
