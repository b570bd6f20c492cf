"""Recorded data: loading measured signals from CSV, NPZ or MATLAB ``.mat`` files, with checks that name file,
row and column, and signals derived from them (differences, filtered derivatives, functions of columns)."""

from __future__ import annotations

import csv
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .errors import DataError


@dataclass
class Recording:
    """Measured signals: ``values[row, column]`` sampled every ``dt`` seconds.

    ``valid[row, column]`` is False where a sample was missing or non-finite (only when loaded with
    ``on_nonfinite='skip'``; loading fails otherwise). ``first_row`` is the file's data-row index of
    ``values[0]`` (0-based, header excluded), so errors and splits refer to rows of the file. ``metadata``
    holds what the file stores beside the signals (a ``.mat`` file's scalars and strings, an ``.npz`` file's
    scalars, e.g. a sample time or a gain), by variable name.
    """

    values: np.ndarray
    columns: list[str]
    dt: float | None = None
    path: str | None = None
    first_row: int = 0
    valid: np.ndarray | None = None
    units: dict[str, str] = field(default_factory=dict)
    metadata: dict[str, Any] = field(default_factory=dict)

    def unit(self, name: str | int) -> str | None:
        """The unit of a column (from ``units=`` or a CSV header such as ``force [N]``), or None."""
        return self.units.get(self.columns[self.index(name)])

    def column(self, name: str) -> np.ndarray:
        return self.values[:, self.index(name)]

    def index(self, name: str | int) -> int:
        if isinstance(name, int):
            if not 0 <= name < len(self.columns):
                raise DataError(f"{self.path or 'recording'}: column index {name} out of range "
                                f"(it has {len(self.columns)} columns: {self.columns})")
            return name
        if name not in self.columns:
            raise DataError(f"{self.path or 'recording'}: no column {name!r}; columns are {self.columns}")
        return self.columns.index(name)

    def rows(self, start: int, stop: int) -> Recording:
        """The file rows [start, stop) (0-based data rows), as a new recording."""
        lo, hi = start - self.first_row, stop - self.first_row
        if not (0 <= lo < hi <= len(self.values)):
            raise DataError(f"{self.path or 'recording'}: rows [{start}, {stop}) are outside the loaded rows "
                            f"[{self.first_row}, {self.first_row + len(self.values)})")
        return Recording(self.values[lo:hi], list(self.columns), self.dt, self.path, start,
                         None if self.valid is None else self.valid[lo:hi], dict(self.units), dict(self.metadata))

    def derive(self, **signals: Derivation) -> Recording:
        """A new recording with derived columns appended, each computed from the whole recording at once
        (e.g. ``rec.derive(velocity=derivative("position", tau=0.005))``). Derive before selecting rows, so that a
        filter's start-up lies outside the rows used. Columns with missing samples cannot be derived from."""
        values, columns, units = self.values, list(self.columns), dict(self.units)
        for name, how in signals.items():
            if name in columns:
                raise DataError(f"{self.path or 'recording'}: derived column {name!r} already exists; columns are "
                                f"{columns}")
            if not isinstance(how, Derivation):
                raise DataError(f"{self.path or 'recording'}: derived column {name!r} needs a derivation "
                                f"(difference, derivative or function from rcotorch.data), got {how!r}")
            current = Recording(values, columns, self.dt, self.path, self.first_row, self.valid, units)
            column = how.compute(current)
            values = np.concatenate([values, column[..., None]], axis=-1)
            columns.append(name)
            unit = how.unit(current)
            if unit:
                units[name] = unit
        valid = None if self.valid is None else np.concatenate(
            [self.valid, np.ones(self.valid.shape[:-1] + (len(signals),), dtype=bool)], axis=-1)
        return Recording(values, columns, self.dt, self.path, self.first_row, valid, units, dict(self.metadata))


class Derivation:
    """A signal computed from the columns of a recording (see ``difference``, ``derivative``, ``function``)."""

    def __init__(self, sources: Sequence[str | int]):
        self.sources = list(sources)

    def inputs(self, rec: Recording) -> list[np.ndarray]:
        """The source columns, each (T,) or (B, T) for per-member data; their samples must all be valid."""
        out = []
        for src in self.sources:
            i = rec.index(src)
            if rec.valid is not None and not rec.valid[..., i].all():
                raise DataError(f"{rec.path or 'recording'}: column {rec.columns[i]!r} has missing samples; a "
                                "signal cannot be derived from it (fill or interpolate the gaps first)")
            out.append(rec.values[..., i])
        return out

    def compute(self, rec: Recording) -> np.ndarray:
        raise NotImplementedError

    def unit(self, rec: Recording) -> str | None:
        return None


class _Difference(Derivation):
    def __init__(self, column, per_second: bool):
        super().__init__([column])
        self.per_second = per_second

    def compute(self, rec):
        (x,) = self.inputs(rec)
        d = np.diff(x, axis=-1, prepend=x[..., :1])                  # x(k) - x(k-1), 0 at the first sample
        return d / _sample_time(rec, "difference(per_second=True)") if self.per_second else d

    def unit(self, rec):
        base = rec.unit(self.sources[0])
        return (f"{base}/s" if self.per_second else base) if base else None


class _Derivative(Derivation):
    def __init__(self, column, tau: float):
        if not tau >= 0:
            raise DataError(f"derivative of {column!r}: tau must be >= 0 seconds, got {tau}")
        super().__init__([column])
        self.tau = float(tau)

    def compute(self, rec):
        import scipy.signal
        (x,) = self.inputs(rec)
        dt = _sample_time(rec, "derivative")
        # s / (tau s + 1) by backward Euler, s -> (1 - q^-1) / dt:
        #   (tau + dt) y(k) - tau y(k-1) = x(k) - x(k-1),   x(-1) = x(0), y(-1) = 0.
        d = np.diff(x, axis=-1, prepend=x[..., :1])
        return scipy.signal.lfilter([1.0], [self.tau + dt, -self.tau], d, axis=-1)

    def unit(self, rec):
        base = rec.unit(self.sources[0])
        return f"{base}/s" if base else None


class _Function(Derivation):
    def __init__(self, fn: Callable[..., np.ndarray], columns: Sequence[str | int], unit: str | None):
        super().__init__(columns)
        self.fn, self._unit = fn, unit

    def compute(self, rec):
        cols = self.inputs(rec)
        out = np.asarray(self.fn(*cols), dtype=np.float64)
        if out.shape != cols[0].shape:
            raise DataError(f"{rec.path or 'recording'}: the function of {self.sources} returned shape {out.shape}, "
                            f"expected {cols[0].shape} (one value per sample)")
        return out

    def unit(self, rec):
        return self._unit


def difference(column: str | int, per_second: bool = False) -> Derivation:
    """x(k) - x(k-1) of a column (0 at the first sample); divided by the sample time with ``per_second``."""
    return _Difference(column, per_second)


def derivative(column: str | int, tau: float = 0.0) -> Derivation:
    """Filtered derivative of a column, s / (tau s + 1) discretized by backward Euler:

        (tau + dt) y(k) - tau y(k-1) = x(k) - x(k-1),   x(-1) = x(0), y(-1) = 0.

    ``tau`` [s] is the filter's time constant (0: the backward difference over dt). The recording needs ``dt``.
    """
    return _Derivative(column, tau)


def function(fn: Callable[..., np.ndarray], *columns: str | int, unit: str | None = None) -> Derivation:
    """``fn(column_1, column_2, ...)`` of the named columns, each an array of samples; it returns one value per
    sample, e.g. ``function(lambda v, i: v * i, "V", "I", unit="W")``."""
    if not callable(fn):
        raise DataError(f"function(): the first argument must be callable, got {fn!r}")
    if not columns:
        raise DataError("function(): name at least one column")
    return _Function(fn, columns, unit)


def _sample_time(rec: Recording, what: str) -> float:
    if not rec.dt or not rec.dt > 0:
        raise DataError(f"{rec.path or 'recording'}: {what} needs the sample time; load it with dt=...")
    return float(rec.dt)


def _check_finite(values: np.ndarray, columns: list[str], path: str, first_row: int, on_nonfinite: str):
    bad = ~np.isfinite(values)
    if not bad.any():
        return None
    if on_nonfinite == "error":
        r, c = np.argwhere(bad)[0]
        raise DataError(f"{path}: row {first_row + r} (0-based data row), column {columns[c]!r}: value is "
                        f"{'missing' if np.isnan(values[r, c]) else values[r, c]} ({int(bad.sum())} non-finite "
                        "value(s) in all; pass on_nonfinite='skip' to skip such samples)")
    if on_nonfinite != "skip":
        raise DataError(f"on_nonfinite must be 'error' or 'skip', got {on_nonfinite!r}")
    return ~bad


def load(path, columns=None, rows: tuple[int, int] | None = None, dt: float | str | None = None,
         on_nonfinite: str = "error", units: dict[str, str] | None = None) -> Recording:
    """Load measured signals from a ``.csv`` (header row of names; trailing commas and empty fields
    allowed), ``.npz`` (one array per name, or a 2-D array) or MATLAB ``.mat`` file (v4 to v7; its numeric
    vectors and matrices become columns, see ``_read_mat``).

    Args:
        columns: names (or indices) to keep, in this order; all by default.
        rows: 0-based data rows [start, stop) to keep.
        dt: sample time in seconds, or the name of a scalar stored in the file (``dt="Ts"``).
        on_nonfinite: 'error' raises naming file, row and column; 'skip' keeps the sample, marked invalid.
        units: column name -> unit (e.g. ``{'V1': 'V'}``), kept in ``Recording.units``. A CSV header
            ``name [unit]`` gives column ``name`` with that unit; ``units=`` overrides it.

    The scalars and strings of a ``.mat`` file and the scalars of an ``.npz`` file are kept in
    ``Recording.metadata``.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: no such file")
    suffix = path.suffix.lower()
    file_units: dict[str, str] = {}
    skipped: list[str] = []
    metadata: dict[str, Any] = {}
    if suffix == ".csv":
        names, values = _read_csv(path)
        names, file_units = _split_units(names)
    elif suffix == ".npz":
        names, values, metadata = _read_npz(path)
    elif suffix == ".mat":
        names, values, metadata, skipped = _read_mat(path)
    else:
        raise DataError(f"{path}: unsupported file type {suffix!r} (expected .csv, .npz or .mat)")
    unknown = [k for k in (units or {}) if k not in names]
    if unknown:
        raise DataError(f"{path}: units given for unknown column(s) {unknown}; columns are {names}")
    all_units = {**file_units, **{k: str(v) for k, v in (units or {}).items()}}
    dt = _stored_sample_time(path, dt, metadata)
    rec = Recording(values, names, dt, str(path), 0, units=all_units, metadata=metadata)
    if columns is not None:
        try:
            idx = [rec.index(c) for c in columns]
        except DataError as e:
            if skipped:
                raise DataError(f"{e} (variables that are not signals were left out: {'; '.join(skipped)})") from None
            raise
        kept = [names[i] for i in idx]
        rec = Recording(values[:, idx], kept, dt, str(path), 0,
                        units={k: v for k, v in all_units.items() if k in kept}, metadata=metadata)
    if rows is not None:
        rec = rec.rows(*rows)
    rec.valid = _check_finite(rec.values, rec.columns, rec.path, rec.first_row, on_nonfinite)
    return rec


def _stored_sample_time(path: Path, dt: float | str | None, metadata: Mapping[str, Any]) -> float | None:
    """``dt`` itself, or the file's scalar named by it."""
    if not isinstance(dt, str):
        return dt
    scalars = {k: v for k, v in metadata.items() if isinstance(v, (int, float))}
    if dt not in scalars:
        raise DataError(f"{path}: dt={dt!r} names no scalar stored in the file; its scalars are {sorted(scalars)}")
    if not scalars[dt] > 0:
        raise DataError(f"{path}: the sample time {dt} = {scalars[dt]} is not positive")
    return float(scalars[dt])


def _split_units(names: list[str]) -> tuple[list[str], dict[str, str]]:
    """Header names ``'force [N]'`` -> column ``'force'`` with unit ``'N'``; other names are kept as they are
    (and all of them when splitting would make two names equal)."""
    out, units = [], {}
    for n in names:
        if n.endswith("]") and "[" in n and not n.startswith("["):
            base, unit = n[:-1].rsplit("[", 1)
            base, unit = base.strip(), unit.strip()
            if base and unit:
                out.append(base)
                units[base] = unit
                continue
        out.append(n)
    if len(set(out)) < len(set(names)):  # 'x [m]' next to 'x [mm]': keep the headers as they are
        return list(names), {}
    return out, units


def _read_csv(path: Path) -> tuple[list[str], np.ndarray]:
    with open(path, newline="") as f:
        reader = csv.reader(f)
        try:
            header = next(reader)
        except StopIteration:
            raise DataError(f"{path}: the file is empty") from None
        while header and header[-1].strip() == "":  # trailing comma
            header = header[:-1]
        names = [h.strip() for h in header]
        if not names or any(n == "" for n in names):
            raise DataError(f"{path}: header row has empty column names: {header}")
        n = len(names)
        rows = []
        for line in reader:
            if len(line) > n and all(s.strip() == "" for s in line[n:]):
                line = line[:n]
            if not line:
                continue
            r = len(rows)  # 0-based data row, blank lines not counted
            if len(line) != n:
                raise DataError(f"{path}: row {r} (0-based data row) has {len(line)} fields, the header has {n}")
            vals = []
            for c, s in enumerate(line):
                s = s.strip()
                if s == "":
                    vals.append(math.nan)
                    continue
                try:
                    vals.append(float(s))
                except ValueError:
                    raise DataError(f"{path}: row {r} (0-based data row), column {names[c]!r}: "
                                    f"{s!r} is not a number") from None
            rows.append(vals)
    if not rows:
        raise DataError(f"{path}: no data rows")
    return names, np.asarray(rows, dtype=np.float64)


def _read_npz(path: Path) -> tuple[list[str], np.ndarray, dict[str, Any]]:
    with np.load(path) as z:
        arrays = {k: np.asarray(z[k]) for k in z.keys()}
    metadata = {k: a.item() for k, a in arrays.items() if a.ndim == 0 and a.dtype.kind in "biufU"}
    keys = [k for k in arrays if k not in metadata]
    if len(keys) == 1 and arrays[keys[0]].ndim == 2:
        arr = np.asarray(arrays[keys[0]], dtype=np.float64)
        return [f"{keys[0]}[{i}]" for i in range(arr.shape[1])], arr, metadata
    cols = []
    for k in keys:
        a = np.asarray(arrays[k], dtype=np.float64)
        if a.ndim != 1:
            raise DataError(f"{path}: array {k!r} has shape {a.shape}; expected one 1-D array per "
                            "signal, or a single 2-D array")
        cols.append(a)
    if not cols:
        raise DataError(f"{path}: no arrays to use as signals (only the scalars {sorted(metadata)})")
    if len({len(a) for a in cols}) > 1:
        raise DataError(f"{path}: arrays have different lengths: {dict(zip(keys, map(len, cols)))}")
    return keys, np.stack(cols, axis=1), metadata


def _read_mat(path: Path) -> tuple[list[str], np.ndarray, dict[str, Any], list[str]]:
    """Columns from the numeric variables of a MATLAB file, in file order, and its metadata.

    A vector (N, 1), (1, N) or (N,) becomes one column named after the variable; a matrix becomes one column
    per channel, ``name[0]``, ``name[1]``, ... with samples along its longer dimension (signals stored as
    rows, as MATLAB users often do, are transposed). Real scalars and strings (a sample time, a gain, a
    description) become metadata (int or float, str). Structs, cells, complex and 3-D or larger arrays are
    left out and listed in the error when a column is missing. All signals must have the same length.
    """
    try:
        from scipy.io import loadmat
        from scipy.io.matlab import MatReadError
    except ImportError:  # pragma: no cover - scipy is a dependency
        raise DataError(f"{path}: reading .mat files needs scipy") from None
    try:
        contents = loadmat(str(path), squeeze_me=False, struct_as_record=True)
    except NotImplementedError:
        raise DataError(f"{path}: MATLAB v7.3 (HDF5) files are not supported; save it with "
                        "save(..., '-v7') or export the signals to CSV") from None
    except (MatReadError, ValueError, TypeError, OSError) as e:
        raise DataError(f"{path}: not a readable MATLAB file ({e})") from None
    names, cols, skipped, metadata = [], [], [], {}
    for key, a in contents.items():
        if key.startswith("__"):
            continue
        if hasattr(a, "toarray"):  # a scipy sparse matrix
            skipped.append(f"{key} (sparse matrix)")
            continue
        a = np.asarray(a)
        if a.dtype.kind == "U" and a.size == 1:
            metadata[key] = str(a.reshape(-1)[0])
            continue
        if a.dtype.kind in "biuf" and a.size == 1:
            metadata[key] = a.reshape(-1)[0].item()
            continue
        if a.dtype.kind not in "biuf":
            kinds = {"U": "string", "S": "string", "O": "cell", "V": "struct", "c": "complex"}
            skipped.append(f"{key} ({kinds.get(a.dtype.kind, str(a.dtype))})")
            continue
        if a.size == 0:
            skipped.append(f"{key} (empty)")
            continue
        if a.ndim > 2 and sum(d > 1 for d in a.shape) > 1:
            skipped.append(f"{key} ({a.ndim}-D array of shape {a.shape})")
            continue
        a = a.astype(np.float64)
        if sum(d > 1 for d in a.shape) == 1:
            names.append(key)
            cols.append(a.reshape(-1, 1))
            continue
        if a.shape[0] < a.shape[1]:
            a = a.T
        names += [f"{key}[{i}]" for i in range(a.shape[1])]
        cols.append(a)
    if not cols:
        found = [f"{k} (scalar)" if not isinstance(v, str) else f"{k} (string)" for k, v in metadata.items()]
        raise DataError(f"{path}: no numeric vector or matrix variables to use as signals"
                        + (f" (found: {'; '.join(found + skipped)})" if found or skipped else
                           " (the file has no variables)"))
    if len({len(c) for c in cols}) > 1:
        sizes, i = {}, 0
        for c in cols:
            sizes[names[i] if c.shape[1] == 1 else names[i][:-3]] = len(c)
            i += c.shape[1]
        raise DataError(f"{path}: variables have different lengths (samples): {sizes}")
    return names, np.concatenate(cols, axis=1), metadata, skipped
