"""Sources: blocks without inputs that emit excitation or recorded signals."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import torch

from . import rng
from .blocks import DEFAULT_DTYPE, Block
from .data import Recording
from .errors import ConfigError, DataError


class WhiteNoise(Block):
    """Gaussian white noise ``out(k) ~ N(mean, std^2)``, one independent stream per batch member.

    Samples are a pure function of (seed, member, k, component) (see ``rcotorch.rng``): with an integer
    ``seed`` member b draws the stream (seed, b); with one seed per member, member b draws (seed[b], 0), so
    a batched sweep reproduces its separate batch-of-one runs exactly. ``std`` may differ per member.
    """

    def __init__(self, width: int = 1, std=1.0, seed=0, mean=0.0, name: str = "excitation",
                 dtype=DEFAULT_DTYPE):
        super().__init__(name, {}, {"out": width})
        self.width = width
        std = torch.as_tensor(std, dtype=dtype).reshape(-1, 1)
        mean = torch.as_tensor(mean, dtype=dtype).reshape(-1, 1)
        seed = torch.as_tensor(seed, dtype=torch.int64).reshape(-1)
        if bool((std < 0).any()):
            raise ConfigError(f"block '{name}': std must be non-negative")
        self.register_buffer("std", std)
        self.register_buffer("mean", mean)
        self.register_buffer("seed", seed)
        self.register_buffer("stream", torch.zeros(0, 1, dtype=torch.int64))
        self.register_buffer("k", torch.zeros((), dtype=torch.int64))
        self._chunk: torch.Tensor | None = None  # samples of steps [_chunk_start, _chunk_start + CHUNK)
        self._chunk_start = -1

    CHUNK = 512

    def reset(self, batch_size: int) -> None:
        super().reset(batch_size)
        for key in ("std", "mean", "seed"):
            self.check_batch(getattr(self, key), key)
        if self.seed.numel() > 1 or batch_size == 1:
            seeds, members = self.seed.expand(batch_size), torch.zeros(batch_size, dtype=torch.int64)
        else:
            seeds, members = self.seed.expand(batch_size), torch.arange(batch_size)
        self.stream = torch.stack([seeds, members], 1).to(self.seed.device)
        self.k = torch.zeros((), dtype=torch.int64, device=self.seed.device)
        self._chunk = None

    def feedthrough(self):
        return {"out": ()}

    def _load_from_state_dict(self, *args, **kwargs):
        super()._load_from_state_dict(*args, **kwargs)
        self._chunk = None  # cached samples belong to the old streams

    def output(self, port, inputs):
        k = int(self.k)
        start = k - k % self.CHUNK
        if self._chunk is None or start != self._chunk_start or self._chunk.dtype != self.std.dtype:
            dev = self.stream.device
            steps = torch.arange(start, start + self.CHUNK, device=dev).reshape(1, -1, 1)
            comp = torch.arange(self.width, device=dev).reshape(1, 1, -1)
            seeds, members = self.stream[:, 0].reshape(-1, 1, 1), self.stream[:, 1].reshape(-1, 1, 1)
            self._chunk = rng.normal(seeds, members, steps, comp, dtype=self.std.dtype)  # (B, CHUNK, width)
            self._chunk_start = start
        return self.mean + self.std * self._chunk[:, k - start]

    def update(self, inputs):
        self.k += 1


class Recorded(Block):
    """Plays recorded signals back, one sample per step.

    Args:
        data: a ``Recording`` or an array (T, columns), or one per member (B, T, columns).
        outputs: port name -> column name(s) or index(es), e.g. ``{'w': 'V1', 'y': 'V2'}``.
        valid: where the recording marks samples invalid (non-finite, loaded with ``on_nonfinite='skip'``),
            the block holds the last valid value and emits ``valid = 0`` on the extra output port ``valid``,
            so an estimator wired to it skips that sample.

    Reading past the end raises a ``DataError``; a graph checks the run length against it before starting.
    """

    def __init__(self, data, outputs: Mapping[str, str | int | Sequence[str | int]], name: str = "data",
                 dt: float | None = None, dtype=DEFAULT_DTYPE):
        if isinstance(data, Recording):
            rec = data
        else:
            arr = np.asarray(data, dtype=np.float64)
            if arr.ndim not in (2, 3):
                raise DataError(f"block '{name}': data must be (T, columns) or (B, T, columns), got shape "
                                f"{arr.shape}")
            rec = Recording(arr, [str(i) for i in range(arr.shape[-1])], dt)
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
        held = _forward_fill(values, valid)
        self.has_gaps = not valid.all()
        super().__init__(name, {}, {**ports, **({"valid": 1} if self.has_gaps else {})})
        self.dt = rec.dt if dt is None else dt
        self.source = rec.path
        self.first_row = rec.first_row
        self.length = values.shape[1]
        self.register_buffer("values", torch.as_tensor(held, dtype=dtype))
        self.register_buffer("valid_mask", torch.as_tensor(valid.all(axis=2, keepdims=True), dtype=dtype))
        self.register_buffer("k", torch.zeros((), dtype=torch.int64))
        self._slices, start = {}, 0
        for port, w in ports.items():
            self._slices[port] = slice(start, start + w)
            start += w

    @property
    def max_steps(self) -> int:
        return self.length

    def reset(self, batch_size: int) -> None:
        super().reset(batch_size)
        self.check_batch(self.values, "data")
        self.k = torch.zeros((), dtype=torch.int64, device=self.values.device)

    def feedthrough(self):
        return {p: () for p in self.outputs}

    def output(self, port, inputs):
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
