"""Recorded data: loading measured signals from CSV, NPZ or MATLAB ``.mat`` files, with checks that name file,
row and column, and signals derived from them (differences, filtered derivatives, functions of columns)."""

from __future__ import annotations

import ast
import csv
import io
import math
import numbers
import re
import zipfile
import zlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from operator import itemgetter
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import DataError
from ..system import available_memory

SAMPLE_TIME_RTOL = 1e-9     # sample times closer than this (relative) are the same rate
# A sample time a file states (a stored scalar, the steps of a time column beyond the rounding of the digits
# written) agrees with another to this (relative): single precision and 7 significant digits pass.
STATED_SAMPLE_TIME_RTOL = 1e-6
# The stored scalars (names compared in lower case) that state a file's sample time in seconds.
SAMPLE_TIME_NAMES = frozenset({"ts", "dt", "t_s", "tsample", "t_sample", "sample_time", "sampletime",
                               "sampling_time", "samplingtime", "sample_period", "sampling_period"})
# A column holding the time of each row: t, time (any case) or T with a unit, the unit of time in [] or ().
TIME_COLUMN = re.compile(r"(t|time)\s*(?:\[\s*([^\[\]]*?)\s*\]|\(\s*([^()]*?)\s*\))?", re.IGNORECASE)
TIME_UNITS = {"": 1.0, "s": 1.0, "sec": 1.0, "ms": 1e-3, "us": 1e-6, "\u00b5s": 1e-6, "\u03bcs": 1e-6,
              "ns": 1e-9, "min": 60.0}
MAX_MAGNITUDE = 1e150       # larger measurements overflow float64 when squared (sums of squares, least squares)
NPY_HEADER_MAX = 10000      # bytes of an .npy header read at most (numpy's own limit)
CSV_CHUNK_ROWS = 8192       # CSV rows parsed per batch: the strings held at once


class SampleTimeConflict(DataError):
    """The sample time given for a file (``given`` s) contradicts the one the file states (``stated`` s,
    ``where``: its scalar or time column)."""

    def __init__(self, path, given: float, stated: float, where: str):
        super().__init__(f"{path}: dt={given:.10g} contradicts the sample time the file states, {stated:.10g} s "
                         f"({where}); pass dt={stated:.10g}, or no dt to use the file's own, or correct the file")
        self.path, self.given, self.stated, self.where = str(path), given, stated, where


def check_sample_time(dt, where: str) -> float | None:
    """``dt`` as a float (None stays None); a ``DataError`` naming ``where`` unless it is a finite number > 0."""
    if dt is None:
        return None
    if isinstance(dt, bool) or not isinstance(dt, numbers.Real) or not (math.isfinite(dt) and dt > 0):
        raise DataError(f"{where}: the sample time dt must be a finite number of seconds > 0, got {dt!r}")
    return float(dt)


def same_sample_time(a: float, b: float) -> bool:
    """Whether two sample times agree to rounding (``SAMPLE_TIME_RTOL``)."""
    return abs(a - b) <= SAMPLE_TIME_RTOL * max(abs(a), abs(b))


@dataclass
class Recording:
    """Measured signals: ``values[row, column]`` sampled every ``dt`` seconds.

    ``valid[row, column]`` is False where a sample was missing or non-finite (only when loaded with
    ``on_nonfinite='skip'``; loading fails otherwise). ``first_row`` is the file's data-row index of
    ``values[0]`` (0-based, header excluded), so errors and splits refer to rows of the file. ``metadata``
    holds what the file stores beside the signals (a ``.mat`` file's scalars and strings, an ``.npz`` file's
    scalars, e.g. a sample time or a gain), by variable name.

    Parameters
    ----------
    values : numpy.ndarray
        The samples, (T, columns), or one recording per member (B, T, columns).
    columns : list of str
        The column names, in the order of the last axis of ``values``.
    dt : float, optional
        The sample time [s]; None where it is not known.
    path : str, optional
        The file the signals were read from (named in errors).
    first_row : int, optional
        The file's 0-based data-row index of ``values[0]``.
    valid : numpy.ndarray of bool, optional
        Same shape as ``values``: False where a sample is missing; None where all are valid.
    units : dict[str, str], optional
        Column name -> unit.
    metadata : dict[str, Any], optional
        Variable name -> a scalar or string stored in the file beside the signals.

    Raises
    ------
    DataError
        If ``values`` are not numbers of 2 or 3 dimensions, ``columns`` are not one distinct name per entry of
        its last axis, ``dt`` is given and is not a finite number > 0, ``first_row`` is not an integer >= 0, or
        ``valid`` has another shape than ``values``.
    """

    values: np.ndarray
    columns: list[str]
    dt: float | None = None
    path: str | None = None
    first_row: int = 0
    valid: np.ndarray | None = None
    units: dict[str, str] = field(default_factory=dict)
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        where = self.path or "recording"
        if not isinstance(self.values, np.ndarray):
            self.values = np.asarray(self.values)
        shape = self.values.shape
        if self.values.dtype.kind not in "biuf":
            raise DataError(f"{where}: values must be numbers, got dtype {self.values.dtype}")
        if self.values.ndim not in (2, 3):
            raise DataError(f"{where}: values must be (rows, columns) or (members, rows, columns), got shape {shape}")
        try:
            if isinstance(self.columns, str):
                raise TypeError
            self.columns = list(self.columns)
        except TypeError:
            raise DataError(f"{where}: columns must be a list of names, got {self.columns!r}") from None
        if not all(isinstance(c, str) for c in self.columns):
            raise DataError(f"{where}: column names must be strings, got {self.columns}")
        if len(self.columns) != shape[-1]:
            raise DataError(f"{where}: {len(self.columns)} column names {self.columns} for the {shape[-1]} columns "
                            f"of values of shape {shape}; name each entry of the last axis once")
        if len(set(self.columns)) < len(self.columns):
            seen: set[str] = set()
            twice = next(c for c in self.columns if c in seen or seen.add(c))
            raise DataError(f"{where}: columns {self.columns} names the column {twice!r} twice")
        self.dt = check_sample_time(self.dt, where)
        if isinstance(self.first_row, bool) or not isinstance(self.first_row, numbers.Integral) \
                or self.first_row < 0:
            raise DataError(f"{where}: first_row must be an integer >= 0, got {self.first_row!r}")
        self.first_row = int(self.first_row)
        if self.valid is not None:
            self.valid = np.asarray(self.valid, dtype=bool)
            if self.valid.shape != shape:
                raise DataError(f"{where}: valid has shape {self.valid.shape}, values {shape}; it must mark each "
                                "sample")

    def __repr__(self) -> str:
        """What a recording holds, in one line: its source, rows, columns with their units, sample time and
        missing samples (the samples themselves are ``values``)."""
        cols = ", ".join(f"{c} [{self.units[c]}]" if self.units.get(c) else c for c in self.columns)
        shape = self.values.shape
        size = f"{shape[-2]} rows" + (f" x {shape[0]} members" if len(shape) == 3 else "")
        rows = f" (file rows {self.first_row}..{self.first_row + shape[-2] - 1})" if self.path else ""
        where = f"{self.path!r}, " if self.path else ""
        dt = "dt unknown" if self.dt is None else f"dt={self.dt:g} s"
        missing = "" if self.valid is None else f", {int((~self.valid).sum())} samples missing"
        extra = f", metadata {sorted(self.metadata)}" if self.metadata else ""
        return f"Recording({where}{size}{rows}, columns {cols}, {dt}{missing}{extra})"

    def unit(self, name: str | int) -> str | None:
        """The unit of a column (from ``units=`` or a CSV header such as ``force [N]``).

        Parameters
        ----------
        name : str or int
            The column's name or index.

        Returns
        -------
        str or None
            None where the column has no unit.

        Raises
        ------
        DataError
            If there is no such column.
        """
        return self.units.get(self.columns[self.index(name)])

    def column(self, name: str) -> np.ndarray:
        """The samples of one column.

        Parameters
        ----------
        name : str
            The column's name (or index).

        Returns
        -------
        numpy.ndarray
            (T,) for a recording of shape (T, columns).

        Raises
        ------
        DataError
            If there is no such column.
        """
        return self.values[:, self.index(name)]

    def index(self, name: str | int) -> int:
        """The index of a column.

        Parameters
        ----------
        name : str or int
            The column's name, or an index (checked to be in range).

        Returns
        -------
        int

        Raises
        ------
        DataError
            If there is no such column, or the index is out of range.
        """
        return _column_index(self.path or "recording", self.columns, name)

    def rows(self, start: int, stop: int) -> Recording:
        """The file rows [start, stop) (0-based data rows), as a new recording.

        Parameters
        ----------
        start, stop : int
            The rows, as numbered in the file (``first_row`` is the first loaded one).

        Returns
        -------
        Recording
            Its ``first_row`` is ``start``.

        Raises
        ------
        DataError
            If the rows are empty or lie outside the loaded ones.
        """
        lo, hi = start - self.first_row, stop - self.first_row
        if not (0 <= lo < hi <= len(self.values)):
            raise DataError(f"{self.path or 'recording'}: rows [{start}, {stop}) are outside the loaded rows "
                            f"[{self.first_row}, {self.first_row + len(self.values)})")
        return Recording(self.values[lo:hi], list(self.columns), self.dt, self.path, start,
                         None if self.valid is None else self.valid[lo:hi], dict(self.units), dict(self.metadata))

    def derive(self, **signals: Derivation) -> Recording:
        """A new recording with derived columns appended, each computed from the whole recording at once.

        For example ``rec.derive(velocity=derivative("position", tau=0.005))``. Derive before selecting rows, so
        that a filter's start-up lies outside the rows used. Columns with missing samples cannot be derived
        from.

        Parameters
        ----------
        **signals : Derivation
            New column name -> ``rcotorch.data.recording.difference / derivative / function``, computed in this order
            (a derivation may use the columns derived before it).

        Returns
        -------
        Recording
            The columns of this one followed by the derived ones, with their units.

        Raises
        ------
        DataError
            If a name is already a column, a value is not a derivation, or a derivation fails (a missing
            column, missing samples, no sample time, a function of the wrong shape).
        """
        values, columns, units, valid = self.values, list(self.columns), dict(self.units), self.valid
        for name, how in signals.items():
            if name in columns:
                raise DataError(f"{self.path or 'recording'}: derived column {name!r} already exists; columns are "
                                f"{columns}")
            if not isinstance(how, Derivation):
                raise DataError(f"{self.path or 'recording'}: derived column {name!r} needs a derivation "
                                f"(difference, derivative or function from rcotorch.data.recording), got {how!r}")
            current = Recording(values, columns, self.dt, self.path, self.first_row, valid, units)
            column = how.compute(current)
            values = np.concatenate([values, column[..., None]], axis=-1)
            if valid is not None:                                   # a derived column is complete
                valid = np.concatenate([valid, np.ones(valid.shape[:-1] + (1,), dtype=bool)], axis=-1)
            columns.append(name)
            unit = how.unit(current)
            if unit:
                units[name] = unit
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


def _check_magnitude(values: np.ndarray, columns: list[str], path: str, first_row: int) -> None:
    """A ``DataError`` naming row and column of the first finite value larger than ``MAX_MAGNITUDE``."""
    big = np.abs(values) > MAX_MAGNITUDE                # False for nan; inf is left to _check_finite
    big &= np.isfinite(values)
    if big.any():
        r, c = np.argwhere(big)[0]
        count = int(big.sum())
        raise DataError(f"{path}: row {first_row + r} (0-based data row), column {columns[c]!r}: "
                        f"{float(values[r, c])!r} is not a finite measurement that float64 arithmetic can square "
                        f"(|value| > {MAX_MAGNITUDE:g}; "
                        f"{count} such value{'s' if count > 1 else ''} in all); check the column and its unit")


def load(path, columns=None, rows: tuple[int, int] | None = None, dt: float | str | None = None,
         on_nonfinite: str = "error", units: dict[str, str] | None = None) -> Recording:
    """Load measured signals from a ``.csv``, ``.npz`` or MATLAB ``.mat`` file.

    A ``.csv`` file is UTF-8 with a header row of names (trailing commas and empty fields allowed); an ``.npz``
    file holds one array per name, or a 2-D array; of a MATLAB file (v4 to v7) the numeric vectors and matrices
    become columns (see ``_read_mat``).

    Parameters
    ----------
    path : str or os.PathLike
        The file.
    columns : sequence of str or int, optional
        Names (or indices) to keep, in this order, each once; all by default. Of a CSV file only these columns
        are parsed and stored.
    rows : tuple of (int, int), optional
        0-based data rows [start, stop) to keep.
    dt : float or str, optional
        Sample time in seconds (finite, > 0), or the name of a scalar stored in the file (``dt="Ts"``).
    on_nonfinite : {'error', 'skip'}, optional
        'error' raises naming file, row and column; 'skip' keeps the sample, marked invalid.
    units : dict[str, str], optional
        Column name -> unit (e.g. ``{'V1': 'V'}``), kept in ``Recording.units``. A CSV header ``name [unit]``
        gives column ``name`` with that unit; ``units=`` overrides it.

    Returns
    -------
    Recording
        values (rows, columns kept), with the file's path, first row, units and metadata.

    Raises
    ------
    DataError
        For every fault in the file or the arguments, naming the file and, where they apply, row and column.
    SampleTimeConflict
        A ``DataError``: ``dt`` contradicts the sample time the file states.

    Notes
    -----
    Files are read strictly: a CSV that is not UTF-8 (a leading byte-order mark is dropped), two header
    names that give the same column (``x`` twice, or ``x`` and ``x [m]``), a field that is not a decimal
    number (``1e-3``, ``-0.5``, ``+2`` and ``.5`` are; ``1_000`` is not; ``nan`` and ``inf`` are non-finite
    samples, see ``on_nonfinite``), a value larger than ``MAX_MAGNITUDE`` (its square overflows float64), an
    ``.npz`` file that is not a zip of ``.npy`` arrays or holds complex, object or empty arrays, an ``.npz``
    array whose header declares more or fewer bytes than its member of the archive holds, or more than the
    memory available, and a file without samples are each a ``DataError`` naming the file and, where they
    apply, array, row and column.

    A file that states its sample time is believed: a stored scalar named like ``Ts`` or ``dt`` (see
    ``SAMPLE_TIME_NAMES``) and a time column (``t``, ``time``, ``time [s]``, ``time (ms)``, ...: the mean
    step over the rows loaded) each state one. Each must agree with ``dt`` (to ``STATED_SAMPLE_TIME_RTOL``
    and the rounding of the digits written), else a ``SampleTimeConflict`` names the file, both values and
    where the file states its own; without ``dt`` the file's is used. A time column must step uniformly
    (to the same tolerance, at most half a sample time), else the error names its first row whose step
    differs. A time column that is not asked for is read too, unless its first field is not a number (a
    clock time).

    The scalars and strings of a ``.mat`` file and the scalars of an ``.npz`` file are kept in
    ``Recording.metadata``.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: no such file")
    if not isinstance(dt, str):
        dt = check_sample_time(dt, str(path))
    suffix = path.suffix.lower()
    file_units: dict[str, str] = {}
    metadata: dict[str, Any] = {}
    if suffix == ".csv":
        names, file_units, idx, values, times = _read_csv(path, columns)
    elif suffix in (".npz", ".mat"):
        names, values, metadata, skipped = _read_npz(path) if suffix == ".npz" else _read_mat(path)
        times = [(name, _time_scale(name), values[:, j].copy()) for j, name in enumerate(names)
                 if _time_scale(name) is not None]
        idx = None if columns is None else _column_indices(path, names, columns, skipped)
        if idx is not None:
            values = values[:, idx]
    else:
        raise DataError(f"{path}: unsupported file type {suffix!r} (expected .csv, .npz or .mat)")
    unknown = [k for k in (units or {}) if k not in names]
    if unknown:
        raise DataError(f"{path}: units given for unknown column(s) {unknown}; columns are {names}")
    all_units = {**file_units, **{k: str(v) for k, v in (units or {}).items()}}
    named = dt if isinstance(dt, str) else None
    if named is not None:
        dt = _stored_sample_time(path, dt, metadata)
    kept = names if idx is None else [names[i] for i in idx]
    rec = Recording(values, kept, dt, str(path), 0, units={k: v for k, v in all_units.items() if k in kept},
                    metadata=metadata)
    if rows is not None:
        rec = rec.rows(*rows)
    stop = rec.first_row + rec.values.shape[-2]
    rec.dt = _settle_sample_time(path, rec.dt, named, metadata,
                                 [(label, scale, t[rec.first_row:stop]) for label, scale, t in times], rec.first_row)
    rec.valid = _check_finite(rec.values, rec.columns, rec.path, rec.first_row, on_nonfinite)
    _check_magnitude(rec.values, rec.columns, rec.path, rec.first_row)
    return rec


def _settle_sample_time(path: Path, dt: float | None, named: str | None, metadata: Mapping[str, Any],
                        times: list[tuple[str, float, np.ndarray]], row0: int) -> float | None:
    """The sample time of a recording: ``dt`` (given, or the scalar ``named`` in the file), checked against
    each one the file states (its scalars in ``SAMPLE_TIME_NAMES``, its time columns ``times``: label, factor
    to seconds, the times of the rows loaded, the first of them file row ``row0``); the file's own where
    ``dt`` is None. A contradiction is a ``SampleTimeConflict`` (dt given) or a ``DataError`` (two of the
    file's own)."""
    stated: list[tuple[float, str, float]] = []          # (seconds, where, absolute uncertainty)
    for name, v in metadata.items():
        if name.lower() not in SAMPLE_TIME_NAMES or isinstance(v, bool) or not isinstance(v, numbers.Real):
            continue
        if not (math.isfinite(v) and v > 0):
            raise DataError(f"{path}: the file states the sample time {name} = {v}, which is not "
                            f"{'positive' if math.isfinite(v) else 'finite'}; correct the file")
        stated.append((_single_precision_decimal(float(v)), f"its scalar {name!r}", 0.0))
    for label, scale, t in times:
        found = _time_column_step(path, label, scale, t, row0)
        if found is not None:
            stated.append(found)
    ref = None if dt is None else (dt, None if named is None else f"its scalar {named!r}", 0.0)
    for value, where, unc in stated:
        if ref is None:
            ref = (value, where, unc)
        elif abs(value - ref[0]) > STATED_SAMPLE_TIME_RTOL * max(value, ref[0]) + unc + ref[2]:
            if ref[1] is None:
                raise SampleTimeConflict(path, ref[0], value, where)
            raise DataError(f"{path}: the file states two sample times, {ref[0]:.10g} s ({ref[1]}) and "
                            f"{value:.10g} s ({where}); correct the file")
    return None if ref is None else ref[0]


def _single_precision_decimal(v: float) -> float:
    """``v``, or the shortest decimal of its single-precision value where ``v`` is one (0.01 stored as float32
    is 0.01)."""
    v32 = np.float32(v)
    return float(str(v32)) if float(v32) == v else v


def _time_scale(name: str) -> float | None:
    """The factor to seconds of a column named as holding the time of each row (``TIME_COLUMN`` with a unit
    of ``TIME_UNITS``); None for other columns. A bare ``T`` is left out (a temperature, a torque)."""
    m = TIME_COLUMN.fullmatch(name.strip())
    if m is None:
        return None
    unit = m.group(2) if m.group(2) is not None else (m.group(3) or "")
    if m.group(1) == "T" and not unit:
        return None
    return TIME_UNITS.get(unit)


def _time_column_step(path: Path, label: str, scale: float, t: np.ndarray,
                      row0: int) -> tuple[float, str, float] | None:
    """The sample time a time column states: its mean step over the rows ``t`` (file rows from ``row0``),
    where it steps uniformly; None for fewer than two rows. Returns (seconds, where, uncertainty of the mean
    step from the rounding of the end values)."""
    n = len(t)
    if n < 2:
        return None
    bad = ~np.isfinite(t)
    if bad.any():
        r = int(np.argmax(bad))
        raise DataError(f"{path}: row {row0 + r} (0-based data row), time column {label!r}: the time is "
                        f"{'missing' if np.isnan(t[r]) else t[r]}; a time column must give the time of every row")
    with np.errstate(over="ignore", invalid="ignore"):        # values beyond float32, or too large to scale
        eps = np.finfo(np.float32 if np.array_equal(t.astype(np.float32), t) else np.float64).eps
        seconds = t * scale
        half = (_half_last_digit(t) + eps * np.abs(t)) * scale + 2 * np.finfo(np.float64).eps * np.abs(seconds)
    span = seconds[-1] - seconds[0]
    if not span > 0:
        raise DataError(f"{path}: time column {label!r} does not increase: {seconds[0]:.10g} s at row {row0}, "
                        f"{seconds[-1]:.10g} s at row {row0 + n - 1}; a time column must give the time of each row")
    step = span / (n - 1)
    unc = (half[0] + half[-1]) / (n - 1)
    steps = np.diff(seconds)
    tol = np.minimum(STATED_SAMPLE_TIME_RTOL * step + unc + half[:-1] + half[1:], step / 2)
    off = np.abs(steps - step) > tol
    where = f"its time column {label!r}, mean step over rows {row0} to {row0 + n - 1}"
    if off.any():
        k = int(np.argmax(off))
        raise DataError(f"{path}: row {row0 + k + 1} (0-based data row), time column {label!r}: the time steps by "
                        f"{steps[k]:.6g} s from the row before ({seconds[k]:.10g} s to {seconds[k + 1]:.10g} s), "
                        f"but the sample time is {step:.10g} s ({where}); a time column must step uniformly (here "
                        f"to {tol[k]:.2g} s, the rounding of its digits); resample the recording onto a uniform grid "
                        "or correct the file")
    return _shortest_decimal(step, unc + 4 * np.finfo(np.float64).eps * step), where, unc


def _half_last_digit(t: np.ndarray) -> np.ndarray:
    """Per value, half the last decimal place it is written to: the coarser of the finest decimal place and
    the finest significant digit written in the column (values written with fixed decimals and with
    significant digits both come out right); 0 for values that need more than 22 decimals."""
    places = np.full(t.shape, 23)                   # decimals needed to write each value; 23: more than 22
    todo = np.arange(t.size)
    for d in range(23):
        scale = 10.0 ** d
        x = t[todo]
        done = np.round(x * scale) / scale == x
        places[todo[done]] = d
        todo = todo[~done]
        if not todo.size:
            break
    if places.max() >= 23:
        return np.zeros(t.shape)
    nonzero = t != 0
    exponent = np.zeros(t.shape)                    # of the leading digit
    exponent[nonzero] = np.floor(np.log10(np.abs(t[nonzero])))
    digits = int((places + exponent + 1)[nonzero].max()) if nonzero.any() else 0    # significant digits
    return 0.5 * np.maximum(10.0 ** -float(places.max()), np.where(nonzero, 10.0 ** (exponent - digits + 1), 0.0))


def _shortest_decimal(v: float, tol: float) -> float:
    """The decimal of fewest significant digits within ``tol`` of ``v`` (``v`` where none of up to 17 is)."""
    for digits in range(1, 18):
        c = float(f"{v:.{digits}g}")
        if abs(c - v) <= tol:
            return c
    return v


def _stored_sample_time(path: Path, dt: str, metadata: Mapping[str, Any]) -> float:
    """The file's scalar named ``dt``, which must be a finite number of seconds > 0."""
    scalars = {k: v for k, v in metadata.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
    if dt not in scalars:
        raise DataError(f"{path}: dt={dt!r} names no scalar stored in the file; its scalars are {sorted(scalars)}")
    v = scalars[dt]
    if not (math.isfinite(v) and v > 0):
        raise DataError(f"{path}: the sample time {dt} = {v} is not {'positive' if math.isfinite(v) else 'finite'}")
    return float(v)


def _column_index(where: str, columns: list[str], name: str | int) -> int:
    if isinstance(name, int):
        if not 0 <= name < len(columns):
            raise DataError(f"{where}: column index {name} out of range (it has {len(columns)} columns: {columns})")
        return name
    if name not in columns:
        raise DataError(f"{where}: no column {name!r}; columns are {columns}")
    return columns.index(name)


def _column_indices(path: Path, names: list[str], columns, skipped: Sequence[str] = ()) -> list[int]:
    """The indices of the columns asked for (names or indices), each asked for once."""
    try:
        idx = [_column_index(str(path), names, c) for c in columns]
    except DataError as e:
        if skipped:
            raise DataError(f"{e} (variables that are not signals were left out: {'; '.join(skipped)})") from None
        raise
    if not idx:
        raise DataError(f"{path}: columns= names no column; columns are {names}")
    twice = sorted({names[i] for i in idx if idx.count(i) > 1})
    if twice:
        raise DataError(f"{path}: columns= asks for the column(s) {twice} more than once")
    return idx


def _split_units(path: Path, names: list[str]) -> tuple[list[str], dict[str, str]]:
    """Header names ``'force [N]'`` -> column ``'force'`` with unit ``'N'``; other names are kept as they are
    (and all of them when splitting would make two names equal: ``'x [m]'`` next to ``'x [mm]'``). The same
    name twice, or a name next to the same name with a unit (``'x'`` and ``'x [m]'``), is a ``DataError``."""
    first: dict[str, int] = {}
    for i, name in enumerate(names):
        if name in first:
            raise DataError(f"{path}: the header names the column {name!r} twice (columns {first[name]} and {i}, "
                            "0-based); rename one of them")
        first[name] = i
    out, units = [], {}
    for i, name in enumerate(names):
        if name.endswith("]") and "[" in name and not name.startswith("["):
            base, unit = (part.strip() for part in name[:-1].rsplit("[", 1))
            if base and unit:
                if base in first:
                    raise DataError(f"{path}: header columns {first[base]} and {i} (0-based), {base!r} and {name!r}, "
                                    f"both name the column {base!r}; rename one of them")
                out.append(base)
                units[base] = unit
                continue
        out.append(name)
    if len(set(out)) < len(out):
        return list(names), {}
    return out, units


def _read_csv(path: Path, columns) -> tuple[list[str], dict[str, str], list[int] | None, np.ndarray,
                                          list[tuple[str, float, np.ndarray]]]:
    """The header's column names and units, the indices of the columns asked for (None: all), their values
    (rows, columns asked for) and the time columns (header name, factor to seconds, values as written). Rows
    are parsed ``CSV_CHUNK_ROWS`` at a time into an array sized from the file's line ends, so that memory
    holds the asked-for columns and the time columns as float64 and one batch of their fields."""
    fast = _read_plain_csv(path, columns)
    if fast is not None:
        return fast
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            reader = csv.reader(f)
            try:
                return _parse_csv(path, reader, columns, _record_bound(path))
            except csv.Error as e:
                raise DataError(f"{path}: line {reader.line_num} (1-based, header included) is not valid CSV: "
                                f"{e}") from None
    except UnicodeDecodeError:
        raise DataError(f"{path}: not UTF-8 text ({_undecodable(path)}); save the file as UTF-8 CSV") from None


def _csv_header(path: Path, header: list[str] | None, columns):
    """The header row's raw names, names, units, the indices asked for (None: all), the columns read (those asked
    for) and the time columns, checked."""
    if header is None:
        raise DataError(f"{path}: the file is empty")
    while header and header[-1].strip() == "":  # trailing comma
        header = header[:-1]
    if not header or any(h.strip() == "" for h in header):
        raise DataError(f"{path}: header row has empty column names: {header}")
    raw = [h.strip() for h in header]
    names, units = _split_units(path, raw)
    idx = None if columns is None else _column_indices(path, names, columns)
    picked = list(range(len(names))) if idx is None else idx
    timed = [i for i in range(len(names)) if _time_scale(raw[i]) is not None]
    return raw, names, units, idx, picked, timed


def _csv_result(raw, names, units, idx, picked, parsed, timed, values):
    """``_read_csv``'s result from the parsed columns' values (rows, ``parsed``)."""
    times = [(raw[i], _time_scale(raw[i]), values[:, parsed.index(i)].copy()) for i in timed if i in parsed]
    table = values if len(parsed) == len(picked) else np.ascontiguousarray(values[:, :len(picked)])
    return names, units, idx, table, times


# A CSV file of plain numbers (digits, signs, points, exponents, commas, spaces) up to this size is parsed in
# one pass by numpy (``_read_plain_csv``), which holds the file's text about three times over while it does;
# larger ones, and any a fast pass doubts, row by row in batches (``_parse_csv``), whose memory is the columns
# asked for.
PLAIN_CSV_BYTES = 1 << 25
_PLAIN = b"0123456789+-.eE, \t\r\n"


def _read_plain_csv(path: Path, columns):
    """``_read_csv``'s result for a file whose data rows hold plain numbers only, every row as many fields as the
    header (or one more, empty: a trailing comma), by ``numpy.loadtxt`` in one pass: the same values as the row by
    row parser (both convert with Python's correctly rounded conversion). None where anything else appears (a
    quote, nan, an empty field, a blank line, another field count, text that is not ASCII): the row by row parser
    then reads the file and names what it finds."""
    try:
        if path.stat().st_size > PLAIN_CSV_BYTES:
            return None
        data = path.read_bytes()
    except OSError:
        return None
    data = data.removeprefix(b"\xef\xbb\xbf")
    end = data.find(b"\n")
    body = data[end + 1:].rstrip(b"\r\n") if end >= 0 else b""        # blank lines at the end are no rows
    if not body or body.translate(None, _PLAIN):
        return None
    try:
        head = next(csv.reader([data[:end].decode("utf-8").rstrip("\r")]), None)
    except UnicodeDecodeError:
        return None
    raw, names, units, idx, picked, timed = _csv_header(path, head, columns)
    n = len(names)
    buf = np.frombuffer(body + b"\n", np.uint8)
    ends = np.flatnonzero(buf == ord("\n"))                # each line's end
    stops = ends - (buf[np.maximum(ends - 1, 0)] == ord("\r"))          # past its last character ("\r\n")
    starts = np.r_[0, ends[:-1] + 1]
    if np.any(stops <= starts):
        return None                                       # a blank line
    commas = np.diff(np.searchsorted(np.flatnonzero(buf == ord(",")), ends), prepend=0)
    trailing = buf[stops - 1] == ord(",")
    if not np.all((commas == n - 1) | ((commas == n) & trailing)):
        return None
    first = body[:stops[0]].decode("ascii").split(",")
    parsed = picked + [i for i in timed if i not in picked and _is_number(first[i])]
    try:
        values = np.loadtxt(io.StringIO(body.decode("ascii")), delimiter=",", comments=None, usecols=parsed,
                            ndmin=2, dtype=np.float64)
    except ValueError:
        return None
    if values.shape != (len(ends), len(parsed)):
        return None
    return _csv_result(raw, names, units, idx, picked, parsed, timed, values)


def _parse_csv(path: Path, reader, columns, capacity: int):
    """``_read_csv`` on an open ``csv.reader``; ``capacity`` is at least the number of data rows."""
    raw, names, units, idx, picked, timed = _csv_header(path, next(reader, None), columns)
    n = len(names)
    parsed, kept, get, values = picked, [], None, np.empty((0, 0))
    batch: list = []
    done = 0
    for line in reader:
        if len(line) != n:
            if len(line) > n and all(s.strip() == "" for s in line[n:]):
                line = line[:n]
            elif not line:
                continue
            else:  # 0-based data row, blank lines not counted
                raise DataError(f"{path}: row {done + len(batch)} (0-based data row) has {len(line)} fields, the "
                                f"header has {n}")
        if get is None:  # the first data row: time columns not asked for are read as well, unless their first
            # field is no number (a clock time)
            parsed = picked + [i for i in timed if i not in picked and _is_number(line[i])]
            kept = [names[i] for i in parsed]
            get = itemgetter(*parsed)           # the fields of a row to parse (one field: a string)
            values = np.empty((capacity, len(parsed)))
        batch.append(get(line))
        if len(batch) == CSV_CHUNK_ROWS:
            done = _parse_rows(path, kept, batch, values, done)
            batch.clear()
    if get is None:
        raise DataError(f"{path}: no data rows")
    done = _parse_rows(path, kept, batch, values, done)
    return _csv_result(raw, names, units, idx, picked, parsed, timed, values[:done])


def _is_number(field: str) -> bool:
    """Whether a CSV field is a number as ``_number`` reads it (nan and inf included), not empty."""
    s = field.strip()
    if not s or "_" in s or not s.isascii():
        return False
    try:
        float(s)
    except ValueError:
        return False
    return True


def _record_bound(path: Path) -> int:
    """At least the number of CSV records in the file: its line ends ('\\n', '\\r\\n' or '\\r') plus one."""
    bound = 1
    with open(path, "rb") as f:
        while block := f.read(1 << 20):
            cr = block.count(b"\r")
            bound += block.count(b"\n") + (cr and cr - block.count(b"\r\n"))
    return bound


def _parse_rows(path: Path, names: list[str], batch: list, out: np.ndarray, row0: int) -> int:
    """Parse a batch of rows (the asked-for fields of each) into ``out[row0:]``; returns the rows filled."""
    m = len(batch)
    for j, col in enumerate(zip(*batch) if len(names) > 1 else (batch,)):
        text = "".join(col)
        try:
            if "_" in text or not text.isascii():
                raise ValueError(text)
            out[row0:row0 + m, j] = np.fromiter(map(float, col), np.float64, m)
        except ValueError:  # empty fields, or a field to name in the error
            out[row0:row0 + m, j] = [_number(path, s, row0 + i, names[j]) for i, s in enumerate(col)]
    return row0 + m


def _number(path: Path, field: str, row: int, column: str) -> float:
    """One CSV field: a decimal number, nan or inf (any case), or empty (a missing sample, NaN)."""
    s = field.strip()
    if s == "":
        return math.nan
    if "_" not in s and s.isascii():
        try:
            return float(s)
        except ValueError:
            pass
    raise DataError(f"{path}: row {row} (0-based data row), column {column!r}: {s!r} is not a number (decimal "
                    "digits with an optional sign, point and exponent, or nan / inf)")


def _undecodable(path: Path) -> str:
    """Where a file first fails to decode as UTF-8: the header or a data row (blank lines not counted)."""
    row = -1
    with open(path, "rb") as f:
        for line in f:
            try:
                text = line.decode("utf-8")
            except UnicodeDecodeError as e:
                where = "the header" if row < 0 else f"row {row} (0-based data row)"
                return f"{where}: byte {line[e.start:e.start + 1]!r} at position {e.start} of the line"
            if row < 0 or text.strip("\r\n"):
                row += 1
    return "it ends inside a character"


def _read_npz(path: Path) -> tuple[list[str], np.ndarray, dict[str, Any], list[str]]:
    """Columns from an ``.npz`` file: one 1-D array per signal, or a single 2-D array (samples along its rows);
    its 0-d numbers and strings become metadata. Arrays are read without unpickling, so object arrays are
    refused, as are complex, non-numeric and empty ones."""
    if not zipfile.is_zipfile(path):
        raise DataError(f"{path}: not an .npz file (a zip archive of .npy arrays, as numpy.savez writes it)")
    _check_npz_sizes(path)
    arrays = {}
    try:
        with np.load(path, allow_pickle=False) as z:
            for k in z.files:
                try:
                    arrays[k] = np.asarray(z[k])
                except ValueError as e:
                    why = "holds Python objects (dtype object), which are never unpickled" if "pickle" in str(e) \
                        else f"cannot be read ({e})"
                    raise DataError(f"{path}: array {k!r} {why}; store numeric arrays") from None
    except DataError:
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as e:
        raise DataError(f"{path}: not a readable .npz file ({e})") from None
    metadata = {k: a.item() for k, a in arrays.items() if a.ndim == 0 and a.dtype.kind in "biufU"}
    keys = [k for k in arrays if k not in metadata]
    for k in keys:
        a = arrays[k]
        if a.dtype.kind == "c":
            raise DataError(f"{path}: array {k!r} is complex ({a.dtype}); store its real and imaginary parts as two "
                            "real arrays")
        if a.dtype.kind not in "biuf":
            raise DataError(f"{path}: array {k!r} has dtype {a.dtype}, not numbers")
        if a.size == 0:
            raise DataError(f"{path}: array {k!r} is empty (shape {a.shape}): no samples")
    if len(keys) == 1 and arrays[keys[0]].ndim == 2:
        arr = np.asarray(arrays[keys[0]], dtype=np.float64)
        return [f"{keys[0]}[{i}]" for i in range(arr.shape[1])], arr, metadata, []
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
    return keys, np.stack(cols, axis=1), metadata, []


def _check_npz_sizes(path: Path) -> None:
    """Before any array of an ``.npz`` file is read: each ``.npy`` member's header must declare as many bytes
    as the member holds (uncompressed, by the archive's directory), and the arrays, with their float64 copies,
    must fit in the memory available (``rcotorch.system.available_memory``); else a ``DataError`` naming the array, its
    declared shape, dtype and size, and why."""
    found = available_memory()
    avail = found[0] if found else None
    need = 0
    try:
        with zipfile.ZipFile(path) as z:
            for info in z.infolist():
                if info.is_dir():
                    continue
                name = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
                with z.open(info) as f:
                    try:
                        header = _npy_header(f)
                    except ValueError as e:
                        raise DataError(f"{path}: array {name!r} has a malformed .npy header ({e})") from None
                before = need
                if header is None:                  # not an .npy member: read as bytes
                    need += info.file_size
                    what = f"member {info.filename!r} holds {_bytes(info.file_size)}"
                else:
                    shape, dtype, offset = header
                    count = math.prod(shape)
                    nbytes = count * dtype.itemsize
                    declared = f"declares shape {shape} of {dtype}"
                    if dtype.hasobject:             # refused unread (never unpickled) by _read_npz
                        continue
                    if offset + nbytes != info.file_size:
                        raise DataError(f"{path}: array {name!r} {declared} ({_bytes(nbytes)}), but its member of "
                                        f"the archive holds {_bytes(max(info.file_size - offset, 0))} of data: the "
                                        "header does not describe the data; the file is damaged or was not "
                                        "written by numpy.savez")
                    need += nbytes + 16 * count     # the array, its float64 column and the stacked table
                    what = f"array {name!r} {declared}: {_bytes(nbytes)} uncompressed"
                if avail is not None and need > avail:
                    raise DataError(f"{path}: {what}, from {_bytes(info.compress_size)} in the file; loading "
                                    f"{'it' if before == 0 else 'the arrays up to it'} needs about {_bytes(need)}, "
                                    f"more than the {_bytes(avail)} of memory available")
    except DataError:
        raise
    except (OSError, EOFError, RuntimeError, NotImplementedError, zipfile.BadZipFile, zlib.error) as e:
        raise DataError(f"{path}: not a readable .npz file ({e})") from None


def _npy_header(f) -> tuple[tuple[int, ...], np.dtype, int] | None:
    """The shape, dtype and data offset an ``.npy`` stream's header declares, read without the data; None
    where the stream does not start like an ``.npy`` file. A malformed header is a ValueError."""
    magic = f.read(8)
    if len(magic) < 8 or magic[:6] != b"\x93NUMPY":
        return None
    major, minor = magic[6], magic[7]
    if major not in (1, 2, 3):
        raise ValueError(f"unknown .npy format version {major}.{minor}")
    width = 2 if major == 1 else 4
    size = int.from_bytes(f.read(width), "little")
    if size > NPY_HEADER_MAX:
        raise ValueError(f"the header is {size} bytes long, more than {NPY_HEADER_MAX}")
    text = f.read(size)
    if len(text) < size:
        raise ValueError("the header is cut short")
    try:
        d = ast.literal_eval(text.decode("utf-8" if major == 3 else "latin1"))
        shape, dtype = d["shape"], np.lib.format.descr_to_dtype(d["descr"])
    except (SyntaxError, ValueError, TypeError, KeyError, UnicodeDecodeError, MemoryError, RecursionError) as e:
        raise ValueError(f"{type(e).__name__}: {e}") from None
    if not isinstance(shape, tuple) or not all(isinstance(x, int) and x >= 0 for x in shape):
        raise ValueError(f"the shape {shape!r} is not a tuple of integers >= 0")
    return shape, dtype, 8 + width + size


def _bytes(n: int) -> str:
    """A size in bytes, in words: '80 GB', '16 MB', '15.6 kB', '128 bytes'."""
    for unit, size in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= size:
            return f"{n / size:.3g} {unit}"
    return f"{n} bytes"


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
