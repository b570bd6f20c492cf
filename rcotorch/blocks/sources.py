"""Sources: blocks without inputs that emit excitation or recorded signals."""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Mapping, Sequence

import numpy as np
import torch

from ..data.recording import Derivation, Recording, check_sample_time, same_sample_time
from ..engine import kernels, memo, rng
from ..errors import ConfigError, DataError
from .base import DEFAULT_DTYPE, Block, first_bad


class WhiteNoise(Block):
    """Gaussian white noise ``out(k) ~ N(mean, std^2)``, one independent stream per batch member.

    Samples are a pure function of (seed, member, k, component) (see ``rcotorch.engine.rng``): with an integer
    ``seed`` member b draws the stream (seed, b); with one seed per member, member b draws (seed[b], 0), so
    a batched sweep reproduces its separate batch-of-one runs exactly. ``std`` may differ per member.

    Parameters
    ----------
    width : int, optional
        The width of the output port.
    std : float or array_like, optional
        Standard deviation, shared or one per member (B,).
    seed : int or array_like of int, optional
        One seed for the batch, or one per member (B,).
    mean : float or array_like, optional
        Mean, shared or one per member (B,).
    name : str, optional
        The block's name.
    dtype : torch.dtype, optional
        Floating-point type (float64 by default).

    Raises
    ------
    ConfigError
        If ``std`` is negative or not finite, or ``mean`` is not finite (the message names the member of a
        per-member value).

    Shape
    -----
    - Output ``out``: (B, width).
    """

    def __init__(self, width: int = 1, std=1.0, seed=0, mean=0.0, name: str = "excitation",
                 dtype=DEFAULT_DTYPE):
        super().__init__(name, {}, {"out": width})
        self.width = width
        std = torch.as_tensor(std, dtype=dtype, device="cpu").reshape(-1, 1)
        mean = torch.as_tensor(mean, dtype=dtype, device="cpu").reshape(-1, 1)
        seed = torch.as_tensor(seed, dtype=torch.int64, device="cpu").reshape(-1)
        bad = first_bad(std, torch.isfinite(std) & (std >= 0))
        if bad is not None:
            raise ConfigError(f"block '{name}': std must be finite and non-negative, got {bad}")
        bad = first_bad(mean, torch.isfinite(mean))
        if bad is not None:
            raise ConfigError(f"block '{name}': mean must be finite, got {bad}")
        self.register_buffer("std", std)
        self.register_buffer("mean", mean)
        self.register_buffer("seed", seed)
        self.register_buffer("stream", torch.zeros(0, 1, dtype=torch.int64))
        self.register_buffer("k", torch.zeros((), dtype=torch.int64))

    CHUNK = 512
    CHUNK_SAMPLES = 1 << 18

    def reset(self, batch_size: int) -> None:
        super().reset(batch_size)
        for key in ("std", "mean", "seed"):
            self.check_batch(getattr(self, key), key)
        dev = self.seed.device
        if self.seed.numel() > 1 or batch_size == 1:
            seeds, members = self.seed.expand(batch_size), torch.zeros(batch_size, dtype=torch.int64, device=dev)
        else:
            seeds, members = self.seed.expand(batch_size), torch.arange(batch_size, device=dev)
        self.stream = torch.stack([seeds, members], 1)
        self.k = torch.zeros((), dtype=torch.int64, device=self.seed.device)

    def feedthrough(self):
        return {"out": ()}

    def _chunk_at(self, k: int) -> tuple[torch.Tensor, int, int]:
        """The samples of the steps around k: (chunk (B, length, width), its first step, length)."""
        # Samples are drawn for a chunk of steps at once: CHUNK steps, fewer for a large batch so that the chunk
        # (and the hashing temporaries behind it) stays near CHUNK_SAMPLES numbers. The values do not depend on
        # the chunking: each is a function of (seed, member, step, component).
        length = max(1, min(self.CHUNK, self.CHUNK_SAMPLES // max(1, self.stream.shape[0] * self.width)))
        start = k - k % length

        # The chunk holds mean + std * N(0, 1) (the same elementwise operations as one step at a time); it is
        # drawn again when k leaves it or when the streams, std or mean changed.
        def draw() -> torch.Tensor:
            noise = _normal_grid(self.stream[:, 0], self.stream[:, 1], start, length, self.width,
                                 self.std.dtype)                                 # (B, length, width)
            return noise.mul_(self.std.unsqueeze(1)).add_(self.mean.unsqueeze(1)) \
                if noise.shape[0] == self.batch_size else self.mean.unsqueeze(1) + self.std.unsqueeze(1) * noise

        chunk = memo.derived(self, "chunk", (self.stream, self.std, self.mean, start, length), draw)
        return chunk, start, length

    def output(self, port, inputs):
        k = int(self.k)
        chunk, start, _ = self._chunk_at(k)
        return chunk[:, k - start]

    def update(self, inputs):
        self.k += 1

    def lower(self, b) -> None:
        """Describe the block to the native engine: one ``NOISE`` instruction draws ``out`` from each member's
        hashed (seed, member) key and the step counter, the same samples as the PyTorch form.

        Parameters
        ----------
        b : rcotorch.engine.lowering.Builder
            Receives the block's parameters, port, scratch and instruction.
        """
        keys = memo.derived(self, "keys", (self.stream,), lambda: rng.hash32(
            self.stream[:, 0], self.stream[:, 1]).to(torch.float64).reshape(-1, 1))   # (seed, member) prefix
        b.emit("NOISE", port="out", WIDTH=self.width, COUNTER=b.counter(), KEY=b.param(keys), STD=b.param(self.std),
               MEAN=b.param(self.mean), OUT=b.output("out"), BUFFER=b.scratch(kernels.NOISE_SLOTS * self.width))


def _normal_grid(seeds: torch.Tensor, members: torch.Tensor, start: int, length: int, width: int,
                 dtype: torch.dtype) -> torch.Tensor:
    """``rng.normal(seeds, members, steps, comp)`` on the grid (B, steps start..start+length-1, comp
    0..width-1), bit for bit: the uniforms of each pair of steps drawn once, with the hash chain's common
    prefixes computed once: (seed, member) per member, (seed, member, pair, comp) once for the four hashes
    behind a pair, not once per hash."""
    first = start // 2
    pairs = (start + length - 1) // 2 - first + 1
    fast = kernels.uniform_grid(seeds, members, first, pairs, width)
    if fast is not None:                                     # the integer hashing in C, same bits
        u1, u2 = fast
    else:
        mix, mask = rng._mix32, rng._MASK32
        dev = seeds.device

        def chain(h: torch.Tensor, key) -> torch.Tensor:     # one step of rng.hash32 after the first key
            k = torch.as_tensor(key, dtype=torch.int64, device=dev) & mask
            return mix(h ^ mix(k + 0x632BE5AB))

        h = mix((seeds.reshape(-1, 1, 1).long() & mask) ^ 0x9E3779B9)
        h = chain(h, members.reshape(-1, 1, 1).long())
        h = chain(h, torch.arange(first, first + pairs, device=dev).reshape(1, -1, 1))
        h = chain(h, torch.arange(width, device=dev).reshape(1, 1, -1))   # (B, pairs, width)

        def uniform(h: torch.Tensor) -> torch.Tensor:        # rng.uniform's last two keys and its mantissa
            hi = (chain(h, 0x1B873593) >> 5).to(torch.float64)
            lo = (chain(h, 0x5BD1E995) >> 6).to(torch.float64)
            return (hi * 67108864.0 + lo + 0.5) / 9007199254740992.0

        u1, u2 = uniform(chain(h, 1)), uniform(chain(h, 2))
    both = torch.stack(rng.box_muller(u1, u2), 2)                              # (B, pairs, 2, width)
    return both.reshape(both.shape[0], 2 * pairs, width)[:, start % 2:start % 2 + length].to(dtype)


class Recorded(Block):
    """Plays recorded signals back, one sample per step.

    Where the recording marks samples invalid (non-finite, loaded with ``on_nonfinite='skip'``), the block
    holds the last valid value and emits ``valid = 0`` on the extra output port ``valid``, so an estimator
    wired to it skips that sample. Reading past the end raises a ``DataError``; a graph checks the run length
    against it before starting.

    Parameters
    ----------
    data : Recording or array_like
        A ``Recording``, or an array (T, columns), or one per member (B, T, columns).
    outputs : Mapping[str, str or int or Sequence[str or int]]
        Port name -> column name(s) or index(es), e.g. ``{'w': 'V1', 'y': 'V2'}``.
    name : str, optional
        The block's name.
    dt : float, optional
        The sample time of ``data`` in seconds where it carries none (an array, or a recording loaded without
        ``dt``); a recording's own sample time must agree with it.
    derive : Mapping[str, Derivation], optional
        Derived signals, name -> ``rcotorch.data.recording.difference / derivative / function``, computed once from the
        whole recording when the block is built (playback stays a plain table); ``outputs`` may name them,
        e.g. ``derive={"v": derivative("x", tau=0.01)}, outputs={"y": "v", ...}``.
    holdoff : Mapping[str, int], optional
        Port -> samples; after a missing sample of that port, ``valid`` stays 0 for that many further
        samples. A missing *input* is held at its last value, so a model driven by it is wrong until its
        response to the wrong input has decayed; ``rcotorch.refinement`` plays a copy of the block with the
        input's hold-off derived from the known model (``with_holdoff``) unless one is given here.
    resample : float, optional
        Play the recording back at this sample time [s] instead of its own: each output is interpolated
        linearly onto t = k * resample (k = 0, 1, ... while t lies within the recording), without an
        anti-aliasing filter. A graph refuses recorded data whose sample time differs from that of another
        block (e.g. the known model), so another rate needs this option.
    dtype : torch.dtype, optional
        Floating-point type (float64 by default).

    Raises
    ------
    DataError
        If a column is unknown, a derivation fails, a sample is non-finite in a recording that does not mark
        invalid samples, ``dt`` disagrees with the recording's sample time, or ``resample`` is given for a
        recording without a sample time.
    ConfigError
        If a ``holdoff`` entry names no output port or is not a non-negative integer.

    Shape
    -----
    - Outputs: one per entry of ``outputs``, (B, number of columns it names).
    - Output ``valid`` (only where the recording misses samples): (B, 1), 1 for a valid sample, else 0.
    """

    def __init__(self, data, outputs: Mapping[str, str | int | Sequence[str | int]], name: str = "data",
                 dt: float | None = None, derive: Mapping[str, Derivation] | None = None,
                 holdoff: Mapping[str, int] | None = None, resample: float | None = None, dtype=DEFAULT_DTYPE):
        rec = _recording(data, name, check_sample_time(dt, f"block '{name}'"))
        if derive:
            try:
                rec = rec.derive(**derive)
            except DataError as e:
                raise DataError(f"block '{name}': {e}") from None
        values = rec.values if rec.values.ndim == 3 else rec.values[None]
        valid = np.isfinite(values) if rec.valid is None else np.broadcast_to(rec.valid, values.shape)
        cols, ports = [], {}
        for port, spec in outputs.items():
            spec = [spec] if isinstance(spec, (str, int)) else list(spec)
            try:
                idx = [rec.index(c) if isinstance(c, str) or rec.values.ndim == 2 else int(c) for c in spec]
            except DataError as e:
                raise DataError(f"block '{name}', output '{port}': {e}") from None
            ports[port] = len(idx)
            cols += idx
        values, valid = values[:, :, cols], valid[:, :, cols]
        if not valid.all() and rec.valid is None:
            b, r, c = np.argwhere(~valid)[0]
            raise DataError(f"block '{name}': data row {rec.first_row + r}, column {cols[c]} is non-finite "
                            "(load the file with on_nonfinite='skip' to skip such samples)")
        sample_time = rec.dt
        if resample is not None:
            sample_time = check_sample_time(resample, f"block '{name}': resample")
            if rec.dt is None:
                raise DataError(f"block '{name}': resample={resample!r} needs the recording's sample time; load it "
                                "with dt=... or pass dt= to the block")
            values, valid = _resample(values, valid, rec.dt, sample_time)
        held = _forward_fill(values, valid)
        self.has_gaps = not valid.all()
        super().__init__(name, {}, {**ports, **({"valid": 1} if self.has_gaps else {})})
        self.dt = sample_time
        self.source = rec.path
        self.first_row = rec.first_row
        # Each port's unit where the recording gives one, the same for all of its columns.
        self.units = {}
        at = 0
        for port, w in ports.items():
            found = {rec.units.get(rec.columns[c]) if c < len(rec.columns) else None for c in cols[at:at + w]}
            if len(found) == 1 and None not in found:
                self.units[port] = found.pop()
            at += w
        self.length = values.shape[1]
        self.register_buffer("values", torch.as_tensor(held, dtype=dtype, device="cpu"))
        self.register_buffer("k", torch.zeros((), dtype=torch.int64))
        self._slices, start = {}, 0
        for port, w in ports.items():
            self._slices[port] = slice(start, start + w)
            start += w
        self._valid, self.holdoff = valid, {}
        self.register_buffer("valid_mask", None)
        self.set_holdoff(dict(holdoff or {}))

    def gaps(self, port: str) -> bool:
        """Whether the recording misses a sample of an output port.

        Parameters
        ----------
        port : str
            The output port.

        Returns
        -------
        bool
        """
        return not self._valid[:, :, self._slices[port]].all()

    def set_holdoff(self, holdoff: Mapping[str, int]) -> None:
        """Set the samples for which ``valid`` stays 0 after a missing sample, per port.

        Parameters
        ----------
        holdoff : Mapping[str, int]
            Output port -> samples, added to (or replacing for the same port) those already set.

        Raises
        ------
        ConfigError
            If a port is not an output of the block, or a count is not a non-negative integer.
        """
        for port, n in holdoff.items():
            if port not in self._slices:
                raise ConfigError(f"block '{self.name}': holdoff names '{port}', not one of its outputs "
                                  f"{list(self._slices)}")
            if not isinstance(n, (int, np.integer)) or n < 0:
                raise ConfigError(f"block '{self.name}': holdoff for '{port}' must be a non-negative integer, "
                                  f"got {n!r}")
            self.holdoff[port] = int(n)
        ok = self._valid.all(axis=2)                                            # (B, T)
        for port, n in self.holdoff.items():
            missing = ~self._valid[:, :, self._slices[port]].all(axis=2)
            steps = np.arange(missing.shape[1])
            last = np.maximum.accumulate(np.where(missing, steps, -n - 1), axis=1)   # the last missing sample
            ok &= steps - last > n                                              # and the n samples after it
        dtype = self.values.dtype
        self.valid_mask = torch.as_tensor(ok[:, :, None], dtype=dtype, device=self.values.device)

    def with_holdoff(self, holdoff: Mapping[str, int]) -> Recorded:
        """A copy of this block with ``holdoff`` added to its hold-offs; this block keeps its own.

        The copy shares the recorded samples (``values`` and which samples are valid) with this block, so the
        recording is not held twice in memory; its hold-offs, its ``valid`` mask, its step counter and the
        module's tables (buffers, ports) are its own, so stepping, moving or changing the copy leaves this
        block as it is.

        Parameters
        ----------
        holdoff : Mapping[str, int]
            Output port -> samples, added to (or replacing for the same port) those this block has, as for
            ``set_holdoff``.

        Returns
        -------
        Recorded
            The copy, under this block's name.

        Raises
        ------
        ConfigError
            If a port is not an output of the block, or a count is not a non-negative integer.
        """
        out = copy.copy(self)
        for key, value in vars(self).items():      # the module's tables and the block's own dicts, unshared
            if isinstance(value, (dict, set, list)):
                object.__setattr__(out, key, copy.copy(value))
        out.k = self.k.clone()
        out.set_holdoff(holdoff)
        return out

    def window(self, start: int, stop: int) -> Recorded:
        """A copy that plays samples [start, stop) of this block's recording, from its first step.

        Parameters
        ----------
        start, stop : int
            The window, in samples of the (resampled) recording: 0 <= start < stop <= ``length``.

        Returns
        -------
        Recorded
            Its hold-off mask recomputed from the window's own samples, at step 0.

        Raises
        ------
        ConfigError
            If the window does not lie within the recording.
        """
        if not 0 <= start < stop <= self.length:
            raise ConfigError(f"block '{self.name}': window ({start}, {stop}) must lie within the recording's "
                              f"{self.length} samples")
        out = copy.deepcopy(self)
        out.values = self.values[:, start:stop].clone()
        out._valid = self._valid[:, start:stop]
        out.length, out.first_row = stop - start, self.first_row + start
        out.set_holdoff({})                    # the hold-off mask of the window's own samples
        out.k = torch.zeros_like(self.k)
        return out

    @property
    def max_steps(self) -> int:
        """The number of steps the block can play: the recording's length in samples."""
        return self.length

    def reset(self, batch_size: int) -> None:
        super().reset(batch_size)
        self.check_batch(self.values, "data")
        self.k = torch.zeros((), dtype=torch.int64, device=self.values.device)

    def feedthrough(self):
        return {p: () for p in self.outputs}

    def output(self, port, inputs):
        """The recorded sample of a port at time k (for ``valid``: whether it is valid).

        Parameters
        ----------
        port : str
            The output port.
        inputs : Mapping[str, torch.Tensor]
            Empty: the block has no inputs.

        Returns
        -------
        torch.Tensor
            (B, outputs[port]).

        Raises
        ------
        DataError
            If step k is past the end of the recording.
        """
        k = int(self.k)
        if k >= self.length:
            raise DataError(f"block '{self.name}': step {k} is past the end of the recording "
                            f"({self.length} samples{' from ' + self.source if self.source else ''})")
        if port == "valid":
            v = self.valid_mask[:, k]
        else:
            v = self.values[:, k, self._slices[port]]
        return v.expand(self.batch_size, -1)

    def update(self, inputs):
        self.k += 1

    def lower(self, b) -> None:
        """Describe the block to the native engine: a ``PLAYBACK`` instruction per output port reads the
        table at the step counter; the run length is bounded by the samples left.

        Parameters
        ----------
        b : rcotorch.engine.lowering.Builder
            Receives the table, the ports and the instructions.
        """
        b.steps_left(lambda: self.length - int(self.k))
        for port in self.outputs:
            t, off, w = (self.valid_mask, 0, 1) if port == "valid" else \
                (self.values, self._slices[port].start, self.outputs[port])
            b.emit("PLAYBACK", port=port, TABLE=b.pointer(t.contiguous()),
                   MSTRIDE=0 if t.shape[0] == 1 else t[0].numel(), TSTRIDE=t.shape[2], OFFSET=off, WIDTH=w,
                   COUNTER=b.counter(), OUT=b.output(port))


def _recording(data, name: str, dt: float | None) -> Recording:
    """``data`` as a Recording: itself (with ``dt`` where it has no sample time of its own), or an array
    (T, columns) or (B, T, columns) with columns '0', '1', ..."""
    if isinstance(data, Recording):
        if dt is None:
            return data
        if data.dt is None:
            return dataclasses.replace(data, dt=dt)
        if not same_sample_time(dt, data.dt):
            raise DataError(f"block '{name}': dt={dt} differs from the sample time {data.dt} of the recording"
                            f"{' ' + data.path if data.path else ''}; pass resample={dt} to play it back at {dt} s")
        return data
    arr = np.asarray(data, dtype=np.float64)
    if arr.ndim not in (2, 3) or 0 in arr.shape:
        raise DataError(f"block '{name}': data must be (T, columns) or (B, T, columns) with samples, got shape "
                        f"{arr.shape}")
    return Recording(arr, [str(i) for i in range(arr.shape[-1])], dt)


def _resample(values: np.ndarray, valid: np.ndarray, dt: float, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Samples (B, T, C) taken every ``dt`` interpolated linearly onto t = k * step (while t <= (T - 1) dt, to
    rounding); a new sample is valid where the samples it is interpolated from are."""
    T = values.shape[1]
    pos = np.arange(int(np.floor((T - 1) * dt / step * (1 + 1e-12))) + 1) * (step / dt)   # in samples of dt
    near = np.round(pos)
    pos = np.where(np.abs(pos - near) <= 1e-9 * np.maximum(near, 1), near, pos)  # grid points that coincide
    i = np.minimum(pos.astype(np.int64), T - 1)
    j = np.minimum(i + 1, T - 1)
    w = (pos - i)[None, :, None]
    known = np.where(valid, values, 0.0)
    a, b = known[:, i], known[:, j]
    return a + w * (b - a), valid[:, i] & (valid[:, j] | (w == 0))


def _forward_fill(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Replace invalid samples by the last valid one of the same column (zero before the first)."""
    if valid.all():
        return values
    out = np.where(valid, values, 0.0)
    idx = np.where(valid, np.arange(values.shape[1])[None, :, None], 0)
    np.maximum.accumulate(idx, axis=1, out=idx)
    filled = np.take_along_axis(out, idx, axis=1)
    first_ok = np.maximum.accumulate(valid, axis=1)
    return np.where(first_ok, filled, 0.0)
