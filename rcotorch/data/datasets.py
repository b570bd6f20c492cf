"""Measured data sets: downloaded once from their official source, verified by SHA-256, cached.

Each data set is obtained the way the scientific Python stack does it (``pooch``, as ``scipy.datasets``): the
first call downloads the official archive into a cache folder, extracts the files it needs and checks each one
against its published SHA-256; later calls read the cache. No data file is part of the package.

Where the files come from, in this order:

1. a local folder given as ``path=`` (or the data set's environment variable, e.g. ``RCOTORCH_SILVERBOX``) that
   holds the files themselves, e.g. an unpacked copy of the official archive; they are checked the same way;
2. the cache, ``$RCOTORCH_DATA/<name>/`` (default: the user's cache folder, ``~/.cache/rcotorch/datasets`` on
   Linux), filled by an earlier download;
3. a download from the official source (one URL after the other until one answers).

A missing file, a hash mismatch or a failed download raises ``DataError`` saying what to do.
"""

from __future__ import annotations

import hashlib
import logging
import os
import shutil
import sys
import tempfile
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import DataError
from .recording import Recording, load


@dataclass(frozen=True)
class Dataset:
    """A data set: its ``files`` (name -> SHA-256), the ``archive`` holding them and where it is served.

    Parameters
    ----------
    name : str
        The data set's name, also its cache folder's.
    archive : str
        The file name of the archive that holds the files.
    urls : tuple of str
        Where the archive is served, tried in order.
    files : dict[str, str]
        File name -> its published SHA-256 (hex).
    env : str
        Environment variable naming a local folder with the files.
    size : int, optional
        The archive's size in bytes, where known.
    citation : str, optional
        What to cite.
    page : str, optional
        The data set's web page.
    splits : dict[str, tuple of (int, int)], optional
        Name -> 0-based data rows [start, stop) of a part the benchmark defines.
    """

    name: str
    archive: str
    urls: tuple[str, ...]
    files: dict[str, str]
    env: str
    size: int | None = None
    citation: str = ""
    page: str = ""
    splits: dict[str, tuple[int, int]] = field(default_factory=dict)


SILVERBOX = Dataset(
    name="silverbox",
    archive="SilverboxFiles.zip",
    # The benchmark site serves the archive from Google Drive; the older direct link is kept as a fallback.
    urls=("https://drive.google.com/uc?export=download&id=17iS-6oBUUgrmiAcrZoG9S5sOaljZnDSy",
          "http://www.nonlinearbenchmark.org/FILES/BENCHMARKS/SILVERBOX/SilverboxFiles.zip"),
    files={"SNLS80mV.csv": "ae62d5a91230c10f76e6dd02c8a4fac3c9d4d8a95fbf50e87cb0c4885003e0f1",
           "Schroeder80mV.csv": "b22cbcba9c59d9b4b1b379967b669dc32959e515b24784da3254505f8563e36c"},
    env="RCOTORCH_SILVERBOX",
    size=5_793_999,
    citation=("T. Wigren and J. Schoukens, \"Three free data sets for development and benchmarking in nonlinear "
              "system identification\", European Control Conference 2013, pp. 2933-2938"),
    page="https://www.nonlinearbenchmark.org/benchmarks/silverbox",
    # 0-based data rows [start, stop) of SNLS80mV.csv, from the benchmark's description.
    splits={"arrow": (100, 40575), "estimation": (40650, 105712), "validation": (105712, 127400)},
)

SILVERBOX_TS = 2 ** 14 / 1e7          # sample time [s]: fs = 1e7 / 2^14 = 610.35 Hz


def cache_dir() -> Path:
    """The folder data sets are cached in: ``$RCOTORCH_DATA`` or the user's cache folder.

    Returns
    -------
    pathlib.Path
    """
    env = os.environ.get("RCOTORCH_DATA")
    if env:
        return Path(env).expanduser()
    import pooch
    return Path(pooch.os_cache("rcotorch")) / "datasets"


def sha256(path: str | Path) -> str:
    """SHA-256 of a file, as hex (remembered while the file's size and modification time stay the same).

    Parameters
    ----------
    path : str or pathlib.Path
        The file.

    Returns
    -------
    str
        64 hexadecimal digits.
    """
    stat = os.stat(path)
    key = (str(Path(path).resolve()), stat.st_size, stat.st_mtime_ns)
    if key not in _HASHES:
        _HASHES[key] = _sha256(path)
    return _HASHES[key]


_HASHES: dict[tuple, str] = {}


def _sha256(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def fetch(ds: Dataset, path: str | Path | None = None, urls: Sequence[str] | None = None,
          cache: str | Path | None = None, progress: bool | None = None) -> dict[str, Path]:
    """The verified files of a data set.

    They come from ``path`` (or ``$<ds.env>``) if given, else from the cache, which a download of the archive
    from ``urls`` fills on first use.

    Parameters
    ----------
    ds : Dataset
        The data set.
    path : str or pathlib.Path, optional
        A local folder holding the files.
    urls : Sequence[str], optional
        Where to download the archive from (default: ``ds.urls``, the official ones).
    cache : str or pathlib.Path, optional
        The cache folder for this data set (default: ``cache_dir() / ds.name``).
    progress : bool, optional
        Show a download progress bar (default: when stderr is a terminal).

    Returns
    -------
    dict[str, pathlib.Path]
        File name -> path of the verified file.

    Raises
    ------
    DataError
        If the local folder lacks a file, a file's SHA-256 differs from the published one, or every download
        fails (the message says what to do).
    """
    local = path if path is not None else os.environ.get(ds.env) or None
    if local is not None:
        return _local(ds, Path(local).expanduser(), "path=" if path is not None else f"${ds.env}")
    folder = Path(cache).expanduser() if cache is not None else cache_dir() / ds.name
    if all((folder / name).is_file() for name in ds.files):
        hint = f"delete {folder} and call again to download it anew"
        return {name: _verified(ds, folder / name, hint) for name in ds.files}
    archive = _download(ds, list(urls or ds.urls), folder, sys.stderr.isatty() if progress is None else progress)
    try:
        return _extract(ds, archive, folder)
    finally:
        archive.unlink(missing_ok=True)


def _local(ds: Dataset, folder: Path, given: str) -> dict[str, Path]:
    if not folder.is_dir():
        raise DataError(f"{ds.name}: the local folder {folder} ({given}) does not exist; point it at a folder "
                        f"holding {sorted(ds.files)} (unpacked from {ds.archive}), or unset it to download them")
    missing = [name for name in ds.files if not (folder / name).is_file()]
    if missing:
        raise DataError(f"{ds.name}: {folder} ({given}) has no {', '.join(missing)}; it must hold "
                        f"{sorted(ds.files)}, the files of {ds.archive} ({ds.page})")
    hint = f"replace it with the file of the official {ds.archive} ({ds.page}), or unset {given} to download it"
    return {name: _verified(ds, folder / name, hint) for name in ds.files}


def _verified(ds: Dataset, file: Path, hint: str, name: str | None = None) -> Path:
    """``file`` if its SHA-256 is the published one of ``name`` (default: its own name), else a DataError."""
    expected = ds.files[name or file.name]
    found = sha256(file)
    if found != expected:
        raise DataError(f"{ds.name}: {name or file.name} ({file}) has SHA-256 {found}, expected {expected} (a "
                        f"different or damaged file); {hint}")
    return file


def _download(ds: Dataset, urls: list[str], folder: Path, progress: bool) -> Path:
    """Download the archive into ``folder`` (trying each URL in turn) and return its path."""
    import pooch
    import requests

    folder.mkdir(parents=True, exist_ok=True)
    reasons = []
    logger = pooch.get_logger()
    for url in urls:
        print(f"rcotorch: downloading the {ds.name} data set ({ds.archive}) from {url} to {folder}",
              file=sys.stderr, flush=True)
        level = logger.level
        logger.setLevel(logging.WARNING)       # the line above says it; the archive's hash is not published
        try:
            path = pooch.retrieve(url, known_hash=None, fname=ds.archive, path=folder, progressbar=progress,
                                  downloader=pooch.HTTPDownloader(progressbar=progress, timeout=60))
        except (requests.RequestException, OSError, ValueError) as e:
            reasons.append(f"{url}: {type(e).__name__}: {e}")
            continue
        finally:
            logger.setLevel(level)
        if zipfile.is_zipfile(path):
            return Path(path)
        size = Path(path).stat().st_size
        Path(path).unlink()
        reasons.append(f"{url}: the answer is not a zip archive ({size} bytes; perhaps a web page)")
    raise DataError(f"{ds.name}: could not download {ds.archive}:\n  " + "\n  ".join(reasons) + "\n"
                    f"Without network access: download {ds.archive} on another machine ({ds.page}), unpack it, "
                    f"and pass the folder holding {sorted(ds.files)} as path= or in ${ds.env}.")


def _extract(ds: Dataset, archive: Path, folder: Path) -> dict[str, Path]:
    """Extract the data set's files from the archive (found by name, in any sub-folder), verify each, and move
    it into ``folder`` only once it is verified."""
    with zipfile.ZipFile(archive) as z:
        members = {Path(info.filename).name: info for info in z.infolist() if not info.is_dir()}
        missing = [name for name in ds.files if name not in members]
        if missing:
            raise DataError(f"{ds.name}: the downloaded {ds.archive} has no {', '.join(missing)} (it holds "
                            f"{sorted(members)}); the source may have changed: get the files from {ds.page} and "
                            f"pass their folder as path= or in ${ds.env}")
        out = {}
        for name in ds.files:
            with tempfile.NamedTemporaryFile(dir=folder, prefix=f".{name}.", delete=False) as tmp:
                with z.open(members[name]) as src:
                    shutil.copyfileobj(src, tmp)
            try:
                _verified(ds, Path(tmp.name), f"the download differs from the published file; get {ds.archive} "
                          f"from {ds.page} and pass the folder of its files as path= or in ${ds.env}", name)
            except DataError:
                Path(tmp.name).unlink(missing_ok=True)
                raise
            out[name] = Path(tmp.name).replace(folder / name)
    return out


def silverbox_files(path: str | Path | None = None, urls: Sequence[str] | None = None,
                    cache: str | Path | None = None, progress: bool | None = None) -> dict[str, Path]:
    """The Silverbox benchmark's CSV files, verified.

    Parameters
    ----------
    path : str or pathlib.Path, optional
        A folder holding the two CSV files (e.g. the unpacked ``SilverboxFiles.zip``); default
        ``$RCOTORCH_SILVERBOX``, else the cache, filled by a download on first use.
    urls : Sequence[str], optional
        Where to download ``SilverboxFiles.zip`` from (default: the benchmark's own links).
    cache : str or pathlib.Path, optional
        The cache folder for this data set (default ``$RCOTORCH_DATA/silverbox``).
    progress : bool, optional
        Show a download progress bar (default: when stderr is a terminal).

    Returns
    -------
    dict[str, pathlib.Path]
        {'SNLS80mV.csv': path, 'Schroeder80mV.csv': path}.

    Raises
    ------
    DataError
        If a file is missing or differs from the published one, or the download fails.
    """
    return fetch(SILVERBOX, path, urls, cache, progress)


def silverbox(record: str = "SNLS80mV", path: str | Path | None = None, **fetch_options) -> Recording:
    """A Silverbox record as a ``Recording``: input ``V1`` and output ``V2`` in volts, ``dt`` = 2^14 / 1e7 s.

    The Silverbox (Wigren and Schoukens, ECC 2013) is an electronic mass-spring-damper with a cubic hardening
    spring, m y'' + d y' + k1 y + k3 y^3 = u. ``record``: 'SNLS80mV' (the benchmark: an arrow of filtered
    Gaussian noise of rising amplitude, then ten multisine realizations) or 'Schroeder80mV' (a Schroeder-phase
    multisine). ``metadata['splits']`` gives the benchmark's rows of SNLS80mV: 'arrow', 'estimation',
    'validation' (0-based, [start, stop)); ``metadata['citation']`` what to cite.

    Parameters
    ----------
    record : {'SNLS80mV', 'Schroeder80mV'}, optional
        The record.
    path : str or pathlib.Path, optional
        A folder holding the CSV files, as for ``silverbox_files``.
    **fetch_options
        The other options of ``silverbox_files`` (``urls``, ``cache``, ``progress``).

    Returns
    -------
    Recording
        Columns ``V1`` (input) and ``V2`` (output) in volts.

    Raises
    ------
    DataError
        If there is no such record, or the files cannot be had.
    """
    files = silverbox_files(path, **fetch_options)
    name = f"{record}.csv"
    if name not in files:
        raise DataError(f"silverbox: no record {record!r}; records are {[f[:-4] for f in files]}")
    rec = load(files[name], columns=["V1", "V2"], dt=SILVERBOX_TS, units={"V1": "V", "V2": "V"})
    rec.metadata.update(citation=SILVERBOX.citation, record=record)
    if record == "SNLS80mV":
        rec.metadata["splits"] = dict(SILVERBOX.splits)
    return rec
