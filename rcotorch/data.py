"""Recorded data: loading measured signals from CSV or NPZ files, with checks that name file, row and column."""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import DataError


@dataclass
class Recording:
    """Measured signals: ``values[row, column]`` sampled every ``dt`` seconds.

    ``valid[row, column]`` is False where a sample was missing or non-finite (only when loaded with
    ``on_nonfinite='skip'``; loading fails otherwise). ``first_row`` is the file's data-row index of
    ``values[0]`` (0-based, header excluded), so errors and splits refer to rows of the file.
    """

    values: np.ndarray
    columns: list[str]
    dt: float | None = None
    path: str | None = None
    first_row: int = 0
    valid: np.ndarray | None = None
    units: dict[str, str] = field(default_factory=dict)

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
                         None if self.valid is None else self.valid[lo:hi], dict(self.units))


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


def load(path, columns=None, rows: tuple[int, int] | None = None, dt: float | None = None,
         on_nonfinite: str = "error", units: dict[str, str] | None = None) -> Recording:
    """Load measured signals from a ``.csv`` (header row of names; trailing commas and empty fields
    allowed) or ``.npz`` (one array per name, or a 2-D array) file.

    Args:
        columns: names (or indices) to keep, in this order; all by default.
        rows: 0-based data rows [start, stop) to keep.
        dt: sample time in seconds.
        on_nonfinite: 'error' raises naming file, row and column; 'skip' keeps the sample, marked invalid.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if suffix == ".csv":
        names, values = _read_csv(path)
    elif suffix == ".npz":
        names, values = _read_npz(path)
    else:
        raise DataError(f"{path}: unsupported file type {suffix!r} (expected .csv or .npz)")
    rec = Recording(values, names, dt, str(path), 0, units=dict(units or {}))
    if columns is not None:
        idx = [rec.index(c) for c in columns]
        rec = Recording(values[:, idx], [names[i] for i in idx], dt, str(path), 0, units=rec.units)
    if rows is not None:
        rec = rec.rows(*rows)
    rec.valid = _check_finite(rec.values, rec.columns, rec.path, rec.first_row, on_nonfinite)
    return rec


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


def _read_npz(path: Path) -> tuple[list[str], np.ndarray]:
    with np.load(path) as z:
        keys = list(z.keys())
        if len(keys) == 1 and z[keys[0]].ndim == 2:
            arr = np.asarray(z[keys[0]], dtype=np.float64)
            return [f"{keys[0]}[{i}]" for i in range(arr.shape[1])], arr
        cols = []
        for k in keys:
            a = np.asarray(z[k], dtype=np.float64)
            if a.ndim != 1:
                raise DataError(f"{path}: array {k!r} has shape {a.shape}; expected one 1-D array per "
                                "signal, or a single 2-D array")
            cols.append(a)
        if len({len(a) for a in cols}) > 1:
            raise DataError(f"{path}: arrays have different lengths: {dict(zip(keys, map(len, cols)))}")
        return keys, np.stack(cols, axis=1)
