"""The native engine's front end: a graph lowered once to a program of the compiled engine, then run.

PyTorch dispatches every tensor operation from Python, and one step of a refinement graph is many small
operations, so for one member, or a few thousand, a step's time goes to dispatch rather than to arithmetic. On
the CPU, in float64, a graph whose blocks all have a native form is therefore lowered to a short list of
instructions that ``rcotorch.engine._engine`` runs for many steps per call (``csrc/lanes.h``).

Each block describes itself: ``Block.lower(b)`` receives a ``Builder`` and asks it for the slots of its
state, parameters and ports and emits its instructions (``LTI``, ``Gain``, ``Sum``, ``WhiteNoise``,
``Recorded``, ``RCOEstimator``; see each). A block without a native form, or a subclass that changes what
its parent computes without lowering itself, keeps the graph on the PyTorch engine, and the reason is
reported (``Graph.engine_reason``). The program is kept (``ProgramCache``, keyed as ``rcotorch.engine.memo``
keys) until the graph's structure, its batch size or a block's parameters change; each call binds the blocks'
current state tensors (binding records, ``kernels.BindMode``), runs, and writes the state back, so
checkpoints, ``Graph.step`` and the analysis work as before and the two engines can take turns in one run.
Signals can be recorded every step inside the engine (``advance(record=...)``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import NoReturn

import torch

from ..errors import ConfigError
from . import kernels, memo
from .kernels import BindMode

Signal = tuple[str, str]
_KIND_OF = {torch.float64: "F64", torch.bool: "BOOL", torch.int64: "I64"}


class NotLowerable(Exception):
    """The graph cannot run on the native engine; the message says why."""


class _Bind:
    """A tensor copied into consecutive slots before the steps and/or back after them (``mode``), fetched by
    ``get`` at every call: one binding record of the engine (RCO_BIND_FIELDS)."""

    __slots__ = ("get", "mode", "rows", "slot", "count", "what")

    def __init__(self, get: Callable[[], torch.Tensor], mode: BindMode, rows: int | None, slot: int, count: int,
                 what: str):
        self.get, self.mode, self.rows, self.slot, self.count, self.what = get, mode, rows, slot, count, what


class _Address:
    """An entry of the pointer table that is an address (a compiled function), with what keeps it valid."""

    __slots__ = ("address", "owner")

    def __init__(self, address: int, owner):
        self.address, self.owner = address, owner

    def data_ptr(self) -> int:
        return self.address

    def __deepcopy__(self, memo) -> _Address:
        return self


class Builder:
    """What a block's ``lower`` uses to describe itself to the native engine.

    Slots are numbered scalars of every member; ``state`` / ``param`` / ``input`` / ``output`` / ``scratch``
    return the first slot of consecutive ones. ``emit`` appends an instruction (op name from ``csrc/engine.h``,
    its fields by name) that computes an output port, or that updates the block after every output was
    computed (``port=None``)."""

    def __init__(self, graph, batch: int):
        self.graph, self.batch = graph, batch
        self.block = None
        self._top = None                              # the graph's block being lowered (owner of ``block``)
        self._inner: tuple | None = None              # inside ``inline``: (inputs, outputs, port, buffer prefix)
        self.nslots = 0
        self.outs: dict[Signal, list[list[int]]] = {}
        self.upds: list[list[int]] = []
        self.consts: list[float] = []
        self.binds: list[_Bind] = []
        self.pointers: list[torch.Tensor | _Address] = []
        self.counted: list = []                       # blocks whose step counter k the engine advances
        self.state_names: dict[str, set[str]] = {}    # block -> buffers the engine writes or does not read
        self.limits: list = []                        # (block, steps_left()) of recordings
        self.keep: list[torch.Tensor] = []            # derived parameters, held while the program lives
        self.signals = {(n, p): torch.zeros(batch, w, dtype=torch.float64)
                        for n, blk in graph.blocks.items() for p, w in blk.outputs.items()}
        self.sig_slot = {sig: self._bind(lambda t=t: t, BindMode.STORE, None, t.shape[1], f"signal {sig}")
                         for sig, t in self.signals.items()}

    # --- for blocks ---------------------------------------------------------------------------------------
    def refuse(self, why: str) -> NoReturn:
        """Stop: this block cannot run natively (``why`` is reported to the user)."""
        raise NotLowerable(f"block '{self.block.name}' ({type(self.block).__name__}): {why}")

    def alloc(self, count: int) -> int:
        slot, self.nslots = self.nslots, self.nslots + count
        return slot

    scratch = alloc

    def state(self, name: str, rows: int | None = None) -> int:
        """Slots of one of the block's state buffers, (B, ...) per member, or time-major (rows, B, ...) with
        ``rows``; loaded before the steps and stored after them."""
        blk = self.block
        t = getattr(blk, name)
        if t.dtype not in _KIND_OF:
            self.refuse(f"state '{name}' has dtype {t.dtype}")
        lead = t.shape[1] if rows is not None else t.shape[0]
        if t.dim() < 1 or lead != self.batch:
            self.refuse(f"state '{name}' has shape {tuple(t.shape)}, not reset for batch {self.batch}")
        self._written(name)
        count = rows * t[0, 0].numel() if rows is not None else t[0].numel()
        return self._bind(lambda blk=blk, name=name: _state_tensor(blk, name), BindMode.LOAD_AND_STORE, rows, count,
                          f"block '{blk.name}' state '{name}'")

    def param(self, t: torch.Tensor, first_lane: bool = False) -> int:
        """Slots of a read-only tensor, (1, ...) shared by the members or (B, ...) per member. ``first_lane``: the
        operations read only the first lane of it where it is shared (their SHARED field set), so a shared tensor
        is copied into that lane alone."""
        if t.dim() == 0 or t.shape[0] not in (1, self.batch):
            self.refuse(f"a parameter of shape {tuple(t.shape)} for a batch of {self.batch}")
        if t.dtype != torch.float64:
            self.refuse(f"a parameter of dtype {t.dtype} (the native engine is float64)")
        t = t.contiguous()
        self.keep.append(t)
        return self._bind(lambda t=t: t, BindMode.LOAD_FIRST_LANE if first_lane else BindMode.LOAD, None, t[0].numel(),
                          f"block '{self.block.name}' parameter")

    def shared(self, *tensors: torch.Tensor) -> int:
        """1 when every member shares these parameters ((1, ...) tensors, or a batch of one), else 0."""
        return int(self.batch == 1 or all(t.shape[0] == 1 for t in tensors))

    def input(self, port: str) -> int | None:
        """Slots of the signal driving an input port, or None when the port is not connected."""
        if self._inner is not None:
            return self._inner[0].get(port)
        src = self.graph.sources.get((self.block.name, port))
        return None if src is None else self.sig_slot[src]

    def output(self, port: str) -> int:
        """Slots of an output port."""
        if self._inner is not None:
            outs = self._inner[1]
            if port not in outs:
                outs[port] = self.scratch(self.block.outputs[port])
            return outs[port]
        return self.sig_slot[(self.block.name, port)]

    def counter(self) -> int:
        """The block's step counter ``k`` (advanced by the steps run): its index in the counter table."""
        if self.block not in self.counted:
            self.counted.append(self.block)
            self._written("k")
        return self.counted.index(self.block)

    def inline(self, inner, inputs: Mapping[str, int | None], outputs: Mapping[str, int], port: str) -> None:
        """Lower a block held inside the current one (a composite block): its input ports read the slots
        ``inputs``, its output ports write ``outputs`` (scratch where not given), its output instructions are
        computed as part of this block's output ``port`` and its update with this block's."""
        _check_lowerable(inner)
        prefix = next(name for name, m in self.block.named_modules() if m is inner)
        outer = (self.block, self._inner)
        top_prefix = "" if self._inner is None else self._inner[3]
        self.block, self._inner = inner, (dict(inputs), dict(outputs), port, f"{top_prefix}{prefix}.")
        try:
            inner.lower(self)
        finally:
            self.block, self._inner = outer

    def pointer(self, t: torch.Tensor) -> int:
        """A read-only float64 tensor the instruction reads directly (e.g. a recording): its table index."""
        if t.dtype != torch.float64 or not t.is_contiguous():
            self.refuse("a table that is not contiguous float64")
        self.pointers.append(t)
        return len(self.pointers) - 1

    def function(self, address: int, owner) -> int:
        """A compiled function ``void f(const double *in, double *out, int64_t lanes)`` the instruction calls
        (``CALL``): its table index. ``owner`` keeps its code alive while the program lives."""
        self.pointers.append(_Address(int(address), owner))
        return len(self.pointers) - 1

    def const(self, *values: float) -> int:
        """Constants baked into the program (e.g. a feature's parameters): index of the first."""
        self.consts += [float(v) for v in values]
        return len(self.consts) - len(values)

    def steps_left(self, fn: Callable[[], int]) -> None:
        """The block can give at most ``fn()`` more steps (a recording); a call runs no further."""
        self.limits.append((self.block, fn))

    def emit(self, op: str, args: Sequence[int] | None = None, port: str | None = None, **fields) -> None:
        """Append an instruction: ``op`` (``csrc/engine.h``, RCO_OPS) with its record given by name.

        Parameters
        ----------
        op : str
            The op, e.g. ``"GAIN"``.
        args : sequence of int, optional
            The record already encoded (its fields in the declared order, then its tables), instead of
            ``fields``; checked against the layout's length.
        port : str, optional
            The output port the instruction computes; None for an update, run after every output.
        **fields
            The fields of the op's layout (upper case, ``kernels.LAYOUT``), e.g. ``ROWS=2``, and its tables (lower
            case, ``kernels.TABLES``), each a list of entries: a mapping of the entry's fields (and tables), its
            value where the entry has a single field, or the entry already encoded. The field that counts a
            table's entries may be left out: it is the table's length.

        Raises
        ------
        ConfigError
            If a field or table is missing or unknown, a table's count disagrees with its length, or ``args``
            does not have the layout's length.
        """
        what = f"block '{self.block.name}' ({type(self.block).__name__}): instruction {op}"
        if op not in kernels.OP:
            raise ConfigError(f"{what}: no such op (the ops: {', '.join(kernels.OP)})")
        layout = kernels.OP_LAYOUT[op]
        if args is not None:
            if fields:
                raise ConfigError(f"{what}: give its record either encoded (args) or by name, not both")
            args = [int(a) for a in args]
            _check_encoded(layout, args, what)
        else:
            args = encode(layout, fields, what)
        ins = [kernels.OP[op], kernels.HEADER + len(args)] + args
        if port is None:
            self.upds.append(ins)
        else:
            outer_port = port if self._inner is None else self._inner[2]
            self.outs.setdefault((self._top.name, outer_port), []).append(ins)

    def unread(self, name: str) -> None:
        """A buffer of the block that the program does not read (kept on the Python side, e.g. rows recorded
        for the user): replacing it does not renew the program, as a changed parameter would."""
        self._written(name)

    # --- internal -----------------------------------------------------------------------------------------
    def _written(self, name: str) -> None:
        """Note a buffer the engine writes (by its name in the graph's block, e.g. 'system.x' inside one)."""
        prefix = "" if self._inner is None else self._inner[3]
        self.state_names.setdefault(self._top.name, set()).add(prefix + name)

    def _bind(self, get, mode: BindMode, rows: int | None, count: int, what: str) -> int:
        slot = self.alloc(count)
        self.binds.append(_Bind(get, mode, rows, slot, count, what))
        return slot


def encode(layout: str, fields: Mapping, what: str) -> list[int]:
    """A record of ``layout`` (``kernels.LAYOUT``) as the engine reads it: its fields in the declared order, then
    its tables (``kernels.TABLES``), from ``fields`` by name (see ``Builder.emit``); ``what`` names the record in
    errors."""
    names, tables = kernels.LAYOUT[layout], kernels.TABLES[layout]
    given = dict(fields)
    table_keys = [table.lower() for table, _, _ in tables]
    unknown = [k for k in given if k not in names and k not in table_keys]
    missing = [k for k in table_keys if k not in given]
    tail: list[int] = []
    for (_table, count, entry), key in zip(tables, table_keys):
        entries = list(given.pop(key, ()))
        if count in given and int(given[count]) != len(entries):
            raise ConfigError(f"{what}: {count} = {given[count]}, but the table {key} has {len(entries)} entries")
        given[count] = len(entries)
        for i, e in enumerate(entries):
            tail += _entry(entry, e, f"{what}, {key}[{i}]")
    missing = [k for k in names if k not in given] + missing
    if missing or unknown:
        parts = [f"missing {', '.join(missing)}"] * bool(missing) + [f"unknown {', '.join(unknown)}"] * bool(unknown)
        listed = ", ".join(names + tuple(table_keys))
        raise ConfigError(f"{what}: {'; '.join(parts)} (the fields of {layout}: {listed})")
    return [int(given[k]) for k in names] + tail


def _entry(layout: str, entry, what: str) -> list[int]:
    """One entry of a table: a mapping by name, the value of a one-field entry, or a record already encoded."""
    if isinstance(entry, Mapping):
        return encode(layout, entry, what)
    if isinstance(entry, (list, tuple)):
        ints = [int(v) for v in entry]
        _check_encoded(layout, ints, what)
        return ints
    if len(kernels.LAYOUT[layout]) != 1 or kernels.TABLES[layout]:
        raise ConfigError(f"{what}: a single value for an entry of {layout}, whose fields are "
                          f"{', '.join(kernels.LAYOUT[layout])}")
    return [int(entry)]


def _check_encoded(layout: str, ints: list[int], what: str) -> None:
    """Raise unless ``ints`` is one record of ``layout``: as many ints as its fields and tables hold."""
    def end(layout: str, at: int) -> int:
        names = kernels.LAYOUT[layout]
        stop = at + len(names)
        if stop > len(ints):
            raise ConfigError(f"{what}: {len(ints)} ints are too few for the fields of {layout} ({', '.join(names)}) "
                              "and its tables")
        for _table, count, entry in kernels.TABLES[layout]:
            for _ in range(ints[at + names.index(count)]):
                stop = end(entry, stop)
        return stop
    if end(layout, 0) != len(ints):
        raise ConfigError(f"{what}: {len(ints)} ints, but the fields of {layout} ({', '.join(kernels.LAYOUT[layout])}) "
                          f"and its tables make {end(layout, 0)}")


def _state_tensor(blk, name: str) -> torch.Tensor:
    """A block's state buffer, made contiguous (in the block) if a PyTorch step left it otherwise."""
    t = getattr(blk, name)
    if not t.is_contiguous() or (t.numel() > 1 and 0 in t.stride()):
        t = t.contiguous().clone()
        blk.set_state(**{name: t})
    return t


def _check_lowerable(blk) -> None:
    """Raise ``NotLowerable`` where a block has no native form. A subclass that changes ``output``, ``update`` or
    ``reset`` without its own ``lower`` has none (its parent's lowering would compute something else)."""
    cls = type(blk)
    owner = next((c for c in cls.__mro__ if "lower" in c.__dict__), None)
    if owner is None or owner.__dict__["lower"] is None:
        raise NotLowerable(f"block '{blk.name}' ({cls.__name__}) has no native form")
    for attr in ("output", "update"):
        defined = next(c for c in cls.__mro__ if attr in c.__dict__)
        if defined is not owner and owner in defined.__mro__:
            raise NotLowerable(f"block '{blk.name}' ({cls.__name__}) overrides {attr}() of {owner.__name__} and has "
                               "no native form")
    for t in blk.buffers():
        if t.device.type != "cpu":
            raise NotLowerable("the graph is not on the CPU")
        if t.is_floating_point() and t.dtype != torch.float64:
            raise NotLowerable(f"block '{blk.name}' is {t.dtype} (the native engine is float64)")


class Program:
    """A lowered graph: instructions in evaluation order, then every block's update; the tables of one call
    are made from the blocks' current tensors by ``bindings``."""

    def __init__(self, graph, b: Builder):
        code = [i for sig in graph.order for ins in b.outs.get(sig, ()) for i in ins]
        code += [i for ins in b.upds for i in ins]
        self.code = torch.tensor(code, dtype=torch.int64)
        self.consts = torch.tensor(b.consts + [0.0], dtype=torch.float64)
        self.nslots, self.batch = b.nslots, b.batch
        self.binds, self.pointers, self.counted, self.limits = b.binds, b.pointers, b.counted, b.limits
        self.signals, self.sig_slot, self.keep = b.signals, b.sig_slot, b.keep
        self.state_names = b.state_names
        self._last: tuple | None = None   # (tensors, binding table, written tensors) of the last call

    def bindings(self) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """The binding table for the blocks' current tensors (reused while they are the same tensors), and the
        tensors the steps write."""
        tensors = [bd.get() for bd in self.binds]
        if self._last is not None and all(a is b for a, b in zip(self._last[0], tensors)):
            return self._last[1], self._last[2]
        rows, written = [], []
        fields = kernels.BIND_FIELD
        for bd, t in zip(self.binds, tensors):
            if bd.rows is not None:
                inner = t[0, 0].numel()
                layout = dict(MSTRIDE=inner, INNER=inner, OSTRIDE=t.shape[1] * inner)
            else:
                per = t[0].numel() if t.dim() else 1
                shared = t.shape[0] == 1 and self.batch > 1
                layout = dict(MSTRIDE=0 if shared else per, INNER=max(per, 1), OSTRIDE=0)
            rec = dict(PTR=t.data_ptr(), KIND=kernels.KIND[_KIND_OF[t.dtype]], COUNT=bd.count, SLOT=bd.slot,
                       MODE=int(bd.mode), **layout)
            rows += [rec[k] for k in fields]
            if bd.mode & BindMode.STORE:
                written.append(t)
        table = torch.tensor(rows, dtype=torch.int64)
        self._last = (tensors, table, written)
        return table, written

    def steps_left(self, steps: int) -> int:
        """How many of ``steps`` this call may run; raises (the block's own error) at a recording's end."""
        for blk, fn in self.limits:
            left = fn()
            if left < 1:
                blk.output(next(iter(blk.outputs)), {})   # the block's error for reading past the end
            steps = min(steps, left)
        return steps


def _structure(graph) -> tuple:
    return (graph.batch_size, tuple(graph.order), tuple(graph.sources.items()),
            tuple((n, id(b), getattr(b, "held", None)) for n, b in graph.blocks.items()), tuple(map(id, graph.hooks)))


def _param_places(graph, state_names: Mapping[str, set[str]]) -> list[tuple[dict, tuple[str, ...], int]]:
    """Where the program's parameters are: every buffer the engine does not write, as each module's buffer
    dictionary, the names in it that count and how many buffers it holds, so that a check reads them without
    walking the modules again. The program stays valid while none of them changes."""
    places = []
    for name, blk in graph.blocks.items():
        skip = state_names.get(name, ())
        for prefix, mod in blk.named_modules():
            keys = tuple(k for k, t in mod._buffers.items()
                         if t is not None and (f"{prefix}.{k}" if prefix else k) not in skip)
            places.append((mod._buffers, keys, len(mod._buffers)))
    return places


def _unchanged(places: list[tuple[dict, tuple[str, ...], int]], key: tuple) -> bool:
    """Whether the buffers at ``places`` are still the tensors of ``key`` (``memo.key``), unmodified, and no
    buffer was added or removed there."""
    i = 0
    for buffers, keys, count in places:
        if len(buffers) != count:
            return False
        for k in keys:
            t = buffers.get(k)
            if i >= len(key) or t is not key[i][0] or t._version != key[i][1]:
                return False
            i += 1
    return i == len(key)


def _lower(graph) -> Program:
    """The program of ``graph``; raises ``NotLowerable`` (why it has none)."""
    if not kernels.available():
        raise NotLowerable(f"the native engine is unavailable ({kernels.why_unavailable()})")
    for hook in graph.hooks:
        if not periodic(hook):
            raise NotLowerable(f"the graph has a step hook ({describe_hook(hook)}) that runs after every step; a "
                               "hook with an integer attribute 'every' runs natively between its calls")
    for blk in graph.blocks.values():
        _check_lowerable(blk)
    b = Builder(graph, graph.batch_size)
    for blk in graph.blocks.values():
        b.block = b._top = blk
        blk.lower(b)
    return Program(graph, b)


class ProgramCache:
    """The lowered program of one graph, or why it has none, with what it stays valid for: lowering's one cache,
    held by the graph (``Graph._program_cache``, declared there) and reached through ``program``, ``refilled``
    and ``invalidate``.

    An entry stands for the graph's structure (``_structure``: batch size, evaluation order, connections, the
    blocks and hooks themselves, whether an estimator is held) and for every parameter the program was made
    with: each buffer of the blocks that the engine neither writes nor leaves unread (``Builder.state``,
    ``Builder.unread``), by identity and PyTorch's version counter (``memo.key``). A buffer replaced
    (``set_markov`` with another shape, ``Module.to``) or modified in place (``est.lam.fill_(0.99)``), a buffer
    added or removed, or a change of structure (``Graph.reset`` to another batch size, another hook, ``hold``)
    lowers the graph again at the next ``get``.
    ``refilled`` keeps the entry through a change that the program itself already reads (the estimator's
    ``NativeCopy``, refilled in place). A refusal is kept likewise, as its reason. A copy of the graph
    (``copy.deepcopy``) starts empty: its blocks are other objects, for which no entry is valid.
    """

    __slots__ = ("structure", "key", "outcome", "places")

    def __init__(self) -> None:
        self.invalidate()

    def get(self, graph) -> Program:
        """The graph's program, made again where the entry no longer stands for the graph; raises
        ``NotLowerable`` (why it has none), a new one each time while nothing changed."""
        if self.outcome is not None and self.structure == _structure(graph) and _unchanged(self.places, self.key):
            if isinstance(self.outcome, NotLowerable):
                raise NotLowerable(*self.outcome.args)
            return self.outcome
        try:
            prog = _lower(graph)
        except NotLowerable as e:
            self._keep(graph, NotLowerable(*e.args), {})
            raise
        self._keep(graph, prog, prog.state_names)
        return prog

    def invalidate(self) -> None:
        """Drop the entry: the next ``get`` lowers the graph again."""
        self.structure = self.key = self.outcome = self.places = None

    def refilled(self, *tensors: torch.Tensor) -> None:
        """Keep the entry valid after ``tensors``, parameters it was made with, were changed in place together
        with what the program itself reads of them (an estimator's beta and its ``NativeCopy``): their present
        versions become the ones the entry stands for. Tensors it was not made with are ignored."""
        if self.key is None:
            return
        ids = {id(t) for t in tensors}
        self.key = tuple((t, t._version) if t is not None and id(t) in ids else (t, v) for t, v in self.key)

    def _keep(self, graph, outcome: Program | NotLowerable, state_names: Mapping[str, set[str]]) -> None:
        """Keep ``outcome`` (the program, or a refusal without its traceback) with what it stays valid for."""
        places = _param_places(graph, state_names)
        params = [buffers[k] for buffers, keys, _ in places for k in keys]
        self.structure, self.key, self.outcome, self.places = _structure(graph), memo.key(params), outcome, places

    def __deepcopy__(self, memo_) -> ProgramCache:
        return ProgramCache()


def program(graph) -> Program:
    """The graph's program, kept (``ProgramCache``) until its structure or a parameter changes (a buffer modified
    in place or replaced by another tensor); raises ``NotLowerable`` (why it has none). A refusal is kept
    likewise, as its reason, and raised again as a new ``NotLowerable`` while nothing changed."""
    return graph._program_cache.get(graph)


def refilled(graph, *tensors: torch.Tensor) -> None:
    """Keep the graph's program valid after ``tensors``, parameters it was made with, were changed in place
    together with what the program itself reads of them (an estimator's Markov parameters and the engine's copy,
    ``RCOEstimator.set_markov(..., members=)``, or the tracking hook's refill): ``ProgramCache.refilled``."""
    graph._program_cache.refilled(*tensors)


def invalidate(graph) -> None:
    """Drop the graph's program (``ProgramCache.invalidate``): the next call lowers the graph again."""
    graph._program_cache.invalidate()


def unsupported(graph) -> str | None:
    """Why ``graph`` cannot run on the native engine (the message of ``program``'s ``NotLowerable``), or None
    when it can."""
    try:
        program(graph)
    except NotLowerable as e:
        return str(e)
    return None


def _observers(prog: Program, accumulate, record, done: int, every: int) -> tuple[torch.Tensor, list]:
    rows, f = [], kernels.OBS_FIELD
    for sig, acc in (accumulate or {}).items():
        if acc.dtype != torch.float64 or not acc.is_contiguous() or tuple(acc.shape) != (prog.batch,):
            raise NotLowerable("accumulators must be contiguous float64 (B,) tensors")
        rec = dict(KIND=kernels.OBSERVER["SUMSQ"], SLOT=prog.sig_slot[sig], WIDTH=prog.signals[sig].shape[1],
                   PTR=acc.data_ptr(), EVERY=1, PHASE=0)
        rows += [rec[k] for k in f]
    for sig, buf in (record or {}).items():
        w = prog.signals[sig].shape[1]
        base = buf.data_ptr() + (done // every) * prog.batch * w * 8
        rec = dict(KIND=kernels.OBSERVER["RECORD"], SLOT=prog.sig_slot[sig], WIDTH=w, PTR=base, EVERY=every,
                   PHASE=done % every)
        rows += [rec[k] for k in f]
    return torch.tensor(rows, dtype=torch.int64), list((accumulate or {}).values())


def periodic(hook) -> int | None:
    """The period of a hook that acts only at steps k with k % every == 0, or None."""
    every = getattr(hook, "every", None)
    return every if isinstance(every, int) and not isinstance(every, bool) and every >= 1 else None


def describe_hook(hook) -> str:
    return getattr(hook, "__qualname__", None) or type(hook).__name__


def advance(graph, prog: Program, steps: int, accumulate: Mapping[Signal, torch.Tensor] | None = None,
            record: Mapping[Signal, torch.Tensor] | None = None, every: int = 1) -> None:
    """Run ``steps`` steps of ``graph`` with its program. ``accumulate``: {signal: (B,) float64} gets
    sum_c signal^2 of every step added; ``record``: {signal: (steps // every, B, width) float64} receives the
    signal after every ``every``-th step. The graph's periodic hooks run at their steps (the engine stops
    there, and its program is renewed when a hook changed a parameter)."""
    for buf in (record or {}).values():
        if buf.dtype != torch.float64 or not buf.is_contiguous() or buf.shape[0] < steps // every:
            raise NotLowerable("record buffers must be contiguous float64 (steps // every, B, width)")
    periods = [periodic(h) for h in graph.hooks]
    done = 0
    while done < steps:
        T = prog.steps_left(steps - done)
        if periods:
            T = min(T, *(p - int(graph.k) % p for p in periods))
        binds, written = prog.bindings()
        counters = torch.tensor([int(blk.k) for blk in prog.counted] or [0], dtype=torch.int64)
        ptrs = torch.tensor([t.data_ptr() for t in prog.pointers] or [0], dtype=torch.int64)
        obs, acc = _observers(prog, accumulate, record, done, every)
        kernels.run(prog.code, prog.consts, binds, ptrs, counters, obs, prog.nslots, T, prog.batch)
        kernels.bump(*written, *acc)
        for blk in prog.counted:
            blk.k += T
        graph.k += T
        done += T
        graph._last_native = (prog.signals, graph.order)    # of the program that ran, copied when read
        if periods and any(int(graph.k) % p == 0 for p in periods):
            for hook in graph.hooks:
                hook(graph)
            if done < steps:                   # a hook may have changed a parameter: the program follows
                try:
                    prog = program(graph)
                except NotLowerable as e:
                    raise NotLowerable(f"after a step hook, {e}") from None
