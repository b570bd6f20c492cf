"""Native CPU kernels and the fused engine: a graph lowered to C and run for many steps per call.

PyTorch dispatches every tensor operation from Python (a few microseconds each), and one step of a
refinement graph is about a hundred small operations; for one member, or a few thousand, that dispatch is
most of the time. On the CPU, in float64, a graph made only of the blocks below is therefore lowered to a
short list of instructions that ``csrc/fused.c`` runs for many steps per call: members are cut into chunks,
each chunk runs every step on its own (a thread per chunk), so nothing is synchronized between steps.

Lowered blocks (exact types): ``LTI``, ``Gain``, ``Sum``, ``WhiteNoise``, ``Recorded`` and ``RCOEstimator``
with one z channel and no ``features`` (the others, user functions, step hooks, CUDA and float32 run on the
PyTorch engine). The native engine updates the blocks' own buffers, so checkpoints, ``Graph.step`` and the
analysis work as before and the two engines can take turns in one run. Results agree with the PyTorch
engine to rounding (sums are taken in another order); a member's arithmetic does not depend on the batch
it runs in, the chunking or the thread count, so a sweep member equals its separate run bit for bit.

The C source is compiled once per machine with the system C compiler (``cc``, or ``$CC``) into a cache
directory (``$RCOTORCH_CACHE``, else ``$XDG_CACHE_HOME/rcotorch`` or ``~/.cache/rcotorch``). Without a
compiler everything runs on the PyTorch engine. ``RCOTORCH_ENGINE=torch`` turns the native engine off;
``Graph.engine`` chooses per graph (``'auto'``, ``'native'``, ``'torch'``).
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
import threading
import warnings
from pathlib import Path

import torch

_SRC = Path(__file__).resolve().parent / "csrc" / "fused.c"
_LOCK = threading.Lock()
_STATE: dict = {"lib": None, "tried": False, "why": None}

NI, NP = 200, 4
OP_SEQ, OP_LTI_OUT, OP_LTI_UPD, OP_GAIN, OP_SUM, OP_ACC_SQ, OP_RCO_OUT, OP_RCO_UPD = range(1, 9)
MIN_STEPS = 64  # steps of noise drawn at once for one call, at least
E_VAR = 40    # estimator instructions: fixed fields, then phi sources and free-entry maps (csrc/fused.c)


class Instr(ctypes.Structure):
    _fields_ = [("op", ctypes.c_int64), ("i", ctypes.c_int64 * NI), ("d", ctypes.c_double * 4),
                ("p", ctypes.c_void_p * NP)]


class Bind(ctypes.Structure):
    """A tensor copied into slots before the steps (mode 1), back after them (mode 2), or both (3)."""
    _fields_ = [("ptr", ctypes.c_void_p), ("kind", ctypes.c_int64), ("mstride", ctypes.c_int64),
                ("inner", ctypes.c_int64), ("ostride", ctypes.c_int64), ("count", ctypes.c_int64),
                ("slot", ctypes.c_int64), ("mode", ctypes.c_int64)]


# --- building and loading ---------------------------------------------------------------------------------
def _cache_dir() -> Path:
    if os.environ.get("RCOTORCH_CACHE"):
        return Path(os.environ["RCOTORCH_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "rcotorch"


def _cpu_flags() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith(("flags", "Features")):
                return line
    except OSError:
        pass
    return platform.processor()


_FLAGS = [
    ["-O3", "-march=native", "-ffp-contract=off", "-fno-math-errno", "-fno-tree-loop-distribute-patterns",
     "-fopenmp"],
    ["-O3", "-ffp-contract=off", "-fno-math-errno", "-fno-tree-loop-distribute-patterns", "-fopenmp"],
    ["-O3", "-ffp-contract=off", "-fno-math-errno"],
]


def _build() -> ctypes.CDLL:
    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")
    if not cc:
        raise OSError("no C compiler found (cc, gcc or clang; or set CC)")
    src = _SRC.read_bytes()
    try:
        version = subprocess.run([cc, "--version"], capture_output=True, text=True, timeout=30).stdout
    except (OSError, subprocess.SubprocessError) as e:
        raise OSError(f"C compiler {cc} does not run: {e}") from None
    errors = []
    for flags in _FLAGS:
        key = hashlib.sha256(src + version.encode() + " ".join(flags).encode() + _cpu_flags().encode() +
                             platform.machine().encode()).hexdigest()[:16]
        path = _cache_dir() / f"fused-{key}.so"
        if not path.is_file():
            path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(suffix=".so", dir=path.parent)
            os.close(fd)
            cmd = [cc, *flags, "-fPIC", "-shared", "-o", tmp, str(_SRC), "-lm"]
            res = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
            if res.returncode != 0:
                os.unlink(tmp)
                errors.append(f"{' '.join(flags)}: {res.stderr.strip()[-300:]}")
                continue
            os.replace(tmp, path)   # atomic: concurrent builders agree
        try:
            lib = ctypes.CDLL(str(path))
        except OSError as e:
            errors.append(f"{' '.join(flags)}: {e}")
            continue
        _declare(lib)
        if lib.rco_instr_size() != ctypes.sizeof(Instr) or lib.rco_bind_size() != ctypes.sizeof(Bind):
            raise OSError("native library layout does not match (instruction size)")
        return lib
    raise OSError("could not compile rcotorch/csrc/fused.c: " + " | ".join(errors))


def _declare(lib: ctypes.CDLL) -> None:
    i64, vp, dbl, ci = ctypes.c_int64, ctypes.c_void_p, ctypes.c_double, ctypes.c_int
    lib.rco_instr_size.restype = i64
    lib.rco_bind_size.restype = i64
    lib.rco_rls1.argtypes = [i64, i64, vp, vp, vp, vp, vp, i64, ci, dbl, vp, vp, ci]
    lib.rco_rls1.restype = ci
    lib.rco_uniform_grid.argtypes = [i64, vp, vp, i64, i64, i64, vp, vp, ci]
    lib.rco_uniform_grid.restype = None
    lib.rco_run.argtypes = [vp, i64, vp, i64, i64, i64, i64, ci]
    lib.rco_run.restype = ci


def library() -> ctypes.CDLL | None:
    """The compiled kernels, or None (``why_unavailable()`` says why)."""
    if _STATE["tried"]:
        return _STATE["lib"]
    with _LOCK:
        if not _STATE["tried"]:
            if os.environ.get("RCOTORCH_ENGINE", "auto") == "torch":
                _STATE["why"] = "RCOTORCH_ENGINE=torch"
            else:
                try:
                    _STATE["lib"] = _build()
                except Exception as e:  # no compiler, a failed build: the PyTorch engine does the work
                    _STATE["why"] = str(e)
                    warnings.warn(f"rcotorch: native kernels unavailable, using PyTorch only ({e})", stacklevel=2)
            _STATE["tried"] = True
    return _STATE["lib"]


def available() -> bool:
    return library() is not None


def why_unavailable() -> str | None:
    library()
    return _STATE["why"]


def _ptr(t: torch.Tensor | None) -> int | None:
    return None if t is None else t.data_ptr()


def _threads() -> int:
    return max(1, torch.get_num_threads())


# --- single kernels -----------------------------------------------------------------------------------------
def rls1_(theta: torch.Tensor, P: torch.Tensor, psi: torch.Tensor, z_r: torch.Tensor, lam, r: float,
          active: torch.Tensor | None) -> torch.Tensor | None:
    """``rls_update`` for l = 1 in one pass over P, in place (theta (B, n), P (B, n, n), psi (B, n, 1),
    z_r (B, 1)); returns ok (B,), or None when the kernel does not apply (the caller falls back)."""
    lib = library()
    B, n = theta.shape
    if (lib is None or theta.device.type != "cpu" or theta.dtype != torch.float64 or n > 64
            or not (theta.is_contiguous() and P.is_contiguous())):
        return None
    psi = psi.reshape(B, n).contiguous()
    z_r = z_r.reshape(B).contiguous()
    if isinstance(lam, torch.Tensor):
        lam_t = lam.reshape(-1).to(torch.float64).contiguous()
        lam_one = 0
    else:
        lam_t = torch.tensor([float(lam)], dtype=torch.float64)
        lam_one = int(float(lam) == 1.0)
    if lam_t.numel() not in (1, B):
        return None
    act = None if active is None else active.reshape(B).to(torch.uint8).contiguous()
    ok = torch.empty(B, dtype=torch.uint8)
    lib.rco_rls1(B, n, theta.data_ptr(), P.data_ptr(), psi.data_ptr(), z_r.data_ptr(), lam_t.data_ptr(),
                 1 if lam_t.numel() > 1 else 0, lam_one, float(r), _ptr(act), ok.data_ptr(), _threads())
    _bump(theta, P)
    return ok.bool()


def uniform_grid(seeds: torch.Tensor, members: torch.Tensor, start: int, length: int, width: int
                 ) -> tuple[torch.Tensor, torch.Tensor] | None:
    """The two uniforms behind ``rng.normal(seed, member, step, comp)`` on the grid (B, length, width), bit
    for bit, or None without the native library (or off the CPU)."""
    lib = library()
    if lib is None or seeds.device.type != "cpu":
        return None
    seeds = seeds.reshape(-1).long().contiguous()
    members = members.reshape(-1).long().contiguous()
    B = seeds.numel()
    u1 = torch.empty(B, length, width, dtype=torch.float64)
    u2 = torch.empty_like(u1)
    lib.rco_uniform_grid(B, seeds.data_ptr(), members.data_ptr(), int(start), int(length), int(width),
                         u1.data_ptr(), u2.data_ptr(), _threads())
    return u1, u2


def _bump(*tensors: torch.Tensor) -> None:
    """Tell PyTorch (and the blocks' caches keyed on ``_version``) that C code wrote these tensors."""
    for t in tensors:
        torch.autograd.graph.increment_version(t)


# --- lowering ---------------------------------------------------------------------------------------------
class _NotLowerable(Exception):
    pass


_KINDS = {torch.float64: 0, torch.bool: 1, torch.int64: 2}


class _Lowering:
    """The instructions and bindings of one call, and the tensors they point into (held until it returns).

    Every value a step touches lives in slots (one scalar of each member of a chunk); ``bind`` maps a
    batch-first tensor to consecutive slots, loaded before the steps and/or stored after them."""

    def __init__(self, graph, steps: int):
        self.graph, self.B = graph, graph.batch_size
        self.limit = steps                   # steps this call may run (noise chunks may shorten it)
        self.outs: dict = {}                 # signal -> its instructions (placed in evaluation order)
        self.upds: list[Instr] = []
        self.binds: list[Bind] = []
        self.nslots = 0
        self.keep: list[torch.Tensor] = []
        self.written: list[torch.Tensor] = []
        self.counted: list = []              # blocks whose step counter k advances
        self.estimators: list = []
        self.kbase = {name: int(blk.k) for name, blk in graph.blocks.items() if "k" in blk._buffers}
        self.signals = _signal_buffers(graph, self.B)
        self.srcs = graph.sources
        self.sig_slot = {}
        for sig, buf in self.signals.items():      # every signal: slots, stored after the steps (graph.last)
            self.sig_slot[sig] = self.bind(buf, mode=2)

    def alloc(self, count: int) -> int:
        slot, self.nslots = self.nslots, self.nslots + count
        return slot

    def bind(self, t: torch.Tensor, mode: int = 1, rows: int | None = None) -> int:
        """Slots for a per-member tensor (B, ...) or a shared one (1, ...) (mode 1 only). ``rows``: the tensor
        is time-major (rows, B, inner), as the estimator's window."""
        if t.dtype not in _KINDS:
            raise _NotLowerable(f"a tensor of dtype {t.dtype}")
        if not t.is_contiguous():
            raise _NotLowerable("a tensor that is not contiguous")
        bd = Bind()
        bd.ptr, bd.kind, bd.mode = t.data_ptr(), _KINDS[t.dtype], mode
        if rows is not None:
            inner = t[0, 0].numel()
            bd.mstride, bd.inner, bd.ostride, bd.count = inner, inner, t.shape[1] * inner, rows * inner
        else:
            if t.dim() == 0 or t.shape[0] not in (1, self.B):
                raise _NotLowerable(f"a tensor of shape {tuple(t.shape)} for a batch of {self.B}")
            per = t[0].numel()
            shared = t.shape[0] == 1 and self.B > 1
            if shared and mode != 1:
                raise _NotLowerable("a shared tensor that is written")
            bd.mstride, bd.inner, bd.ostride, bd.count = (0 if shared else per), max(per, 1), 0, per
        bd.slot = self.alloc(bd.count)
        self.binds.append(bd)
        self.keep.append(t)
        if mode & 2:
            self.written.append(t)
        return bd.slot

    def const(self, t: torch.Tensor) -> int:
        """Slots holding a parameter: (1, ...) shared or (B, ...) per member."""
        return self.bind(t.contiguous())

    def sig(self, block: str, port: str) -> int:
        return self.sig_slot[(block, port)]

    def src(self, block: str, port: str) -> int:
        """The slots of the signal that drives an input port."""
        return self.sig_slot[self.srcs[(block, port)]]

    def instr(self, op: int, ints=(), ptrs=(), dbls=(), signal=None) -> Instr:
        """An instruction computing ``signal`` (an output), or an update when ``signal`` is None."""
        if len(ints) > NI or len(ptrs) > NP:
            raise _NotLowerable("too many ports for one native instruction")
        ins = Instr()
        ins.op = op
        for j, v in enumerate(ints):
            ins.i[j] = int(v)
        for j, v in enumerate(dbls):
            ins.d[j] = float(v)
        for j, t in enumerate(ptrs):
            if t is not None:
                self.keep.append(t)
                ins.p[j] = t.data_ptr()
        if signal is None:
            self.upds.append(ins)
        else:
            self.outs.setdefault(signal, []).append(ins)
        return ins

    def state(self, blk, key: str, dtype=None, rows: int | None = None) -> int:
        """Slots for a block's state buffer, loaded before the steps and stored after them."""
        t = getattr(blk, key)
        if dtype is not None and t.dtype != dtype:
            raise _NotLowerable(f"block '{blk.name}': {key} has dtype {t.dtype}")
        if not t.is_contiguous() or (0 in t.stride() and t.numel() > 1):
            t = t.contiguous().clone()
            blk.set_state(**{key: t})
        if rows is None and t.shape[0] != self.B:
            raise _NotLowerable(f"block '{blk.name}': {key} is not reset for batch {self.B}")
        return self.bind(t, mode=3, rows=rows)


def _lower_lti(L: _Lowering, blk) -> None:
    n = blk.n_states
    if n > 64 or sum(blk.inputs.values()) > 64:
        raise _NotLowerable(f"block '{blk.name}' is too large for the native engine")
    x = L.state(blk, "x", torch.float64)
    A, Bm, C = L.const(blk.A), L.const(blk.B), L.const(blk.C)
    D = None
    m_total = blk.B.shape[2]
    for port, rows in blk._out_slices.items():
        ft = [p for p in blk._feedthrough[port] if (blk.name, p) in L.srcs]
        if ft and D is None:
            D = L.const(blk.D)
        ints = [n, rows.stop - rows.start, C + rows.start * n, x, L.sig(blk.name, port), len(ft), m_total,
                (D if ft else 0) + rows.start * m_total]
        for p in ft:
            cs = blk._in_slices[p]
            ints += [cs.start, cs.stop - cs.start, L.src(blk.name, p)]
        L.instr(OP_LTI_OUT, ints, signal=(blk.name, port))
    ports = list(blk._in_slices)
    ints = [n, m_total, A, Bm, x, len(ports)]
    for p in ports:
        ints += [L.src(blk.name, p), blk._in_slices[p].stop - blk._in_slices[p].start]
    L.instr(OP_LTI_UPD, ints)


def _lower_gain(L: _Lowering, blk) -> None:
    K = blk.K
    L.instr(OP_GAIN, [K.shape[1], K.shape[2], L.const(K), L.src(blk.name, "in"), L.sig(blk.name, "out")],
            signal=(blk.name, "out"))


def _lower_sum(L: _Lowering, blk) -> None:
    ints = [blk.outputs["out"], len(blk.signs), L.sig(blk.name, "out")]
    for p, sign in blk.signs.items():
        ints += [L.src(blk.name, p), int(sign)]
    L.instr(OP_SUM, ints, signal=(blk.name, "out"))


def _lower_noise(L: _Lowering, blk) -> None:
    k = L.kbase[blk.name]
    chunk, start, length = blk._chunk_at(k, MIN_STEPS)  # (B, length, width): mean + std N(0, 1), steps start..
    chunk = chunk.contiguous()
    if chunk.shape[0] != L.B:
        raise _NotLowerable(f"block '{blk.name}': noise for {chunk.shape[0]} members")
    L.limit = min(L.limit, start + length - k)
    w = blk.width
    L.instr(OP_SEQ, [length * w, w, 0, w, k - start, L.sig(blk.name, "out")], [chunk], signal=(blk.name, "out"))
    L.counted.append(blk)


def _lower_recorded(L: _Lowering, blk) -> None:
    k = L.kbase[blk.name]
    L.limit = min(L.limit, blk.length - k)
    if L.limit < 1:
        return blk.output(next(iter(blk.outputs)), {})   # raises the DataError of reading past the end
    vals, valid = blk.values.contiguous(), blk.valid_mask.contiguous()
    for port in blk.outputs:
        t, off, w = (valid, 0, 1) if port == "valid" else (vals, blk._slices[port].start, blk.outputs[port])
        ms = 0 if t.shape[0] == 1 else t[0].numel()
        L.instr(OP_SEQ, [ms, t.shape[2], off, w, k, L.sig(blk.name, port)], [t], signal=(blk.name, port))
    L.counted.append(blk)


def _lower_estimator(L: _Lowering, blk) -> None:
    B = L.B
    if blk.features is not None:
        raise _NotLowerable(f"block '{blk.name}' uses features (Python functions)")
    if blk.tied:
        raise _NotLowerable(f"block '{blk.name}' ties entries of theta (the native engine takes masks only)")
    if blk.n_z != 1:
        raise _NotLowerable(f"block '{blk.name}' has {blk.n_z} z channels (the native engine takes 1)")
    W = blk.window
    if W == 0 or blk.win.shape[0] != 2 * W or blk.win.shape[1] != B:
        raise _NotLowerable(f"block '{blk.name}' has no Markov parameters or was not reset")
    nc1 = max(blk.nc, 1)
    m = blk.n_phi + blk.n_u
    if blk.n_theta > 64 or m > 64 or blk.n_u * m > 128 or E_VAR + blk.n_phi + 2 * blk.n_theta > NI:
        raise _NotLowerable(f"block '{blk.name}' is too large for the native engine")
    if blk.alive.dtype != torch.bool:
        raise _NotLowerable(f"block '{blk.name}': alive is not boolean")
    st = {key: L.state(blk, key, torch.float64) for key in ("theta", "past", "past_u", "phi_now", "u_now", "P",
                                                            "z_r")}
    st["win"] = L.state(blk, "win", torch.float64, rows=2 * W)
    st["alive"] = L.state(blk, "alive")
    st["div"] = L.state(blk, "diverged_at", torch.int64)
    beta = L.const(blk._beta_rev())                      # (Bp, n_z * n_u, nu), oldest first
    lam = blk.lam.to(torch.float64).reshape(-1, 1)
    lam_one = not isinstance(blk._lam_arg(), torch.Tensor)
    lam = L.const(lam)

    def bound(lo, hi, width):
        if lo is None:
            return -1, -1
        lo, hi = (v.to(torch.float64).reshape(-1).expand(width).reshape(1, width) for v in (lo, hi))
        return L.const(lo), L.const(hi)

    ulo, uhi = bound(blk.u_low, blk.u_high, blk.n_u)
    tlo, thi = bound(blk.theta_low, blk.theta_high, blk.n_u * blk.n_phi)
    valid = L.src(blk.name, "valid") if (blk.name, "valid") in L.srcs else -1
    # The regressor signals s(k) in port order, contiguous: copy them next to each other.
    ports = list(blk.ports)
    cur = L.alloc(blk.n_sig)
    cur_srcs = [(L.src(blk.name, p), blk.ports[p]) for p in ports]
    # phi's entries: [s(k) | past s | past u] gathered (estimator._phi_gather)
    flat = list(range(cur, cur + blk.n_sig)) + list(range(st["past"], st["past"] + nc1 * blk.n_sig)) + \
        list(range(st["past_u"], st["past_u"] + nc1 * blk.n_u))
    phi_src = [flat[j] for j in blk._gather.tolist()]
    fi = blk.free_idx.tolist()
    free_prod = [(e // blk.n_phi) * m + e % blk.n_phi for e in fi]
    ints = [0] * E_VAR
    fields = dict(NU=blk.n_u, NPHI=blk.n_phi, NTHETA=blk.n_theta, W=W, NUM=W - blk.first_delay, NC=blk.nc,
                  NC1=nc1, NSIG=blk.n_sig, LAM_ONE=int(lam_one), KBASE=L.kbase[blk.name], THETA=st["theta"],
                  P=st["P"], WIN=st["win"], PHI=st["phi_now"], UNOW=st["u_now"], BETA=beta,
                  Z=L.src(blk.name, "z"), VALID=valid, ALIVE=st["alive"], DIV=st["div"], ZR=st["z_r"], LAM=lam,
                  TLO=tlo, THI=thi, PAST=st["past"], PASTU=st["past_u"], UOUT=L.sig(blk.name, "u"), ULO=ulo,
                  UHI=uhi, CUR=cur)
    for j, key in enumerate(_E_FIELDS):
        ints[j] = fields[key]
    ints += phi_src + fi + free_prod
    r = float(blk.r_inv.reshape(-1)[0])
    # s(k) -> contiguous slots (a one-input Sum per port): before u when phi holds s(k) (then u waits for it
    # in the evaluation order), and before the update, which shifts s(k) into the history.
    for signal in ([(blk.name, "u")] if blk.proper else []) + [None]:
        at = cur
        for src, w in cur_srcs:
            L.instr(OP_SUM, [w, 1, at, src, 1], signal=signal)
            at += w
    L.instr(OP_RCO_OUT, ints, signal=(blk.name, "u"))
    L.instr(OP_RCO_UPD, ints, dbls=(r,))
    L.counted.append(blk)
    L.estimators.append(blk)


_E_FIELDS = ("NU", "NPHI", "NTHETA", "W", "NUM", "NC", "NC1", "NSIG", "LAM_ONE", "KBASE", "THETA", "P", "WIN",
             "PHI", "UNOW", "BETA", "Z", "VALID", "ALIVE", "DIV", "ZR", "LAM", "TLO", "THI", "PAST", "PASTU",
             "UOUT", "ULO", "UHI", "CUR")


def _lowerings() -> dict:
    from .blocks import Gain, Sum
    from .estimator import RCOEstimator
    from .lti import LTI
    from .sources import Recorded, WhiteNoise
    return {LTI: _lower_lti, Gain: _lower_gain, Sum: _lower_sum, WhiteNoise: _lower_noise,
            Recorded: _lower_recorded, RCOEstimator: _lower_estimator}


def _signal_buffers(graph, B: int) -> dict:
    cache = graph.__dict__.get("_native_signals")
    if cache is None or cache[0] != B:
        bufs = {(b, p): torch.zeros(B, w, dtype=torch.float64)
                for b, blk in graph.blocks.items() for p, w in blk.outputs.items()}
        cache = graph.__dict__["_native_signals"] = (B, bufs)
    return cache[1]


def _static_reason(graph) -> str | None:
    if library() is None:
        return f"native kernels unavailable ({_STATE['why']})"
    if graph.hooks:
        return "the graph has step hooks (they run after every step)"
    low = _lowerings()
    for name, blk in graph.blocks.items():
        if type(blk) not in low:
            return f"block '{name}' ({type(blk).__name__}) has no native form"
        for t in blk.buffers():
            if t.device.type != "cpu":
                return "the graph is not on the CPU"
            if t.is_floating_point() and t.dtype != torch.float64:
                return f"block '{name}' is {t.dtype} (the native engine is float64)"
    return None


def unsupported(graph) -> str | None:
    """Why ``graph`` cannot run on the native engine, or None when it can."""
    why = _static_reason(graph)
    if why is not None:
        return why
    try:
        _program(graph, 1, None)
    except _NotLowerable as e:
        return str(e)
    return None


def _program(graph, steps: int, accumulate) -> tuple[_Lowering, list[Instr]]:
    L = _Lowering(graph, steps)
    low = _lowerings()
    for blk in graph.blocks.values():
        low[type(blk)](L, blk)
    prog = [ins for sig in graph.order for ins in L.outs.get(sig, ())]   # outputs in evaluation order
    for sig, acc in (accumulate or {}).items():
        if acc.dtype != torch.float64 or not acc.is_contiguous() or tuple(acc.shape) != (L.B,):
            raise _NotLowerable("accumulators must be contiguous float64 (B,) tensors")
        L.instr(OP_ACC_SQ, [graph.blocks[sig[0]].outputs[sig[1]], L.sig(*sig), L.bind(acc, mode=3)],
                signal=("", "acc"))
        prog += L.outs.pop(("", "acc"))
    return L, prog + L.upds                                              # then every block's update


def advance(graph, steps: int, accumulate: dict | None = None) -> bool:
    """Run ``steps`` steps of ``graph`` natively; False (and nothing done) when it cannot be lowered.
    ``accumulate``: {signal: (B,) float64 tensor} to which sum_c signal[b, c]^2 of every step is added."""
    if _static_reason(graph) is not None:
        return False
    done = 0
    lib = library()
    while done < steps:
        try:
            L, prog = _program(graph, steps - done, accumulate)
        except _NotLowerable:
            if done:
                raise
            return False
        T = max(1, min(steps - done, L.limit))
        arr = (Instr * len(prog))(*prog)
        binds = (Bind * len(L.binds))(*L.binds)
        if lib.rco_run(ctypes.addressof(arr), len(prog), ctypes.addressof(binds), len(L.binds), L.nslots, T,
                       L.B, _threads()) != 0:
            raise MemoryError("native engine: could not allocate its scratch slots")
        _bump(*L.written)
        for blk in L.counted:
            blk.k += T
        for blk in L.estimators:
            blk._k_cache = (blk.k, blk.k._version, L.kbase[blk.name] + T)
        for blk in graph.blocks.values():
            blk.__dict__.pop("_cx", None)        # LTI's cached C x: x was written here
        graph.k += T
        done += T
    graph.last = {sig: L.signals[sig].clone() for sig in graph.order}
    return True
