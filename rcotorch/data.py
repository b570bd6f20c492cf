"""Recorded data: loading measured signals from CSV, NPZ or MATLAB ``.mat`` files, with checks that name file,
row and column."""

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
    allowed), ``.npz`` (one array per name, or a 2-D array) or MATLAB ``.mat`` file (v4 to v7; its numeric
    vectors and matrices become columns, see ``_read_mat``).

    Args:
        columns: names (or indices) to keep, in this order; all by default.
        rows: 0-based data rows [start, stop) to keep.
        dt: sample time in seconds.
        on_nonfinite: 'error' raises naming file, row and column; 'skip' keeps the sample, marked invalid.
        units: column name -> unit (e.g. ``{'V1': 'V'}``), kept in ``Recording.units``. A CSV header
            ``name [unit]`` gives column ``name`` with that unit; ``units=`` overrides it.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: no such file")
    suffix = path.suffix.lower()
    file_units: dict[str, str] = {}
    skipped: list[str] = []
    if suffix == ".csv":
        names, values = _read_csv(path)
        names, file_units = _split_units(names)
    elif suffix == ".npz":
        names, values = _read_npz(path)
    elif suffix == ".mat":
        names, values, skipped = _read_mat(path)
    else:
        raise DataError(f"{path}: unsupported file type {suffix!r} (expected .csv, .npz or .mat)")
    unknown = [k for k in (units or {}) if k not in names]
    if unknown:
        raise DataError(f"{path}: units given for unknown column(s) {unknown}; columns are {names}")
    all_units = {**file_units, **{k: str(v) for k, v in (units or {}).items()}}
    rec = Recording(values, names, dt, str(path), 0, units=all_units)
    if columns is not None:
        try:
            idx = [rec.index(c) for c in columns]
        except DataError as e:
            if skipped:
                raise DataError(f"{e} (variables that are not signals were left out: {'; '.join(skipped)})") from None
            raise
        kept = [names[i] for i in idx]
        rec = Recording(values[:, idx], kept, dt, str(path), 0,
                        units={k: v for k, v in all_units.items() if k in kept})
    if rows is not None:
        rec = rec.rows(*rows)
    rec.valid = _check_finite(rec.values, rec.columns, rec.path, rec.first_row, on_nonfinite)
    return rec


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


def _read_mat(path: Path) -> tuple[list[str], np.ndarray, list[str]]:
    """Columns from the numeric variables of a MATLAB file, in file order.

    A vector (N, 1), (1, N) or (N,) becomes one column named after the variable; a matrix becomes one column
    per channel, ``name[0]``, ``name[1]``, ... with samples along its longer dimension (signals stored as
    rows, as MATLAB users often do, are transposed). Scalars and strings (metadata such as a sample time),
    structs, cells, complex and 3-D or larger arrays are left out and listed in the error when a column
    is missing. All signals must have the same length.
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
    names, cols, skipped = [], [], []
    for key, a in contents.items():
        if key.startswith("__"):
            continue
        if hasattr(a, "toarray"):  # a scipy sparse matrix
            skipped.append(f"{key} (sparse matrix)")
            continue
        a = np.asarray(a)
        if a.dtype.kind not in "biuf":
            kinds = {"U": "string", "S": "string", "O": "cell", "V": "struct", "c": "complex"}
            skipped.append(f"{key} ({kinds.get(a.dtype.kind, str(a.dtype))})")
            continue
        if a.size <= 1:
            skipped.append(f"{key} (scalar)" if a.size == 1 else f"{key} (empty)")
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
        raise DataError(f"{path}: no numeric vector or matrix variables to use as signals"
                        + (f" (found: {'; '.join(skipped)})" if skipped else " (the file has no variables)"))
    if len({len(c) for c in cols}) > 1:
        sizes, i = {}, 0
        for c in cols:
            sizes[names[i] if c.shape[1] == 1 else names[i][:-3]] = len(c)
            i += c.shape[1]
        raise DataError(f"{path}: variables have different lengths (samples): {sizes}")
    return names, np.concatenate(cols, axis=1), skipped
