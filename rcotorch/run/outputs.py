"""Output folders that are safe to write, atomic files and checksummed checkpoints.

An output folder (a run's ``--out``, a sweep's root or one of its shards) is opened by one writer at a time:
``OutputFolder.open`` takes a lock file (``.rcotorch.lock``, held for as long as the folder is open), so a
second process fails at once with a clear message. The folder's manifest (``.rcotorch.json``) lists every file
the run wrote; files that were in the folder before it opened are never listed, never deleted and never
overwritten. A folder that already holds a run is refused unless the caller resumes it (``mode='resume'``) or
replaces it (``mode='overwrite'``, which deletes the files of the earlier manifest and nothing else). A folder
holding results without a manifest (written by hand or by an older version) is always refused.

Nothing outside the folder is ever deleted, replaced or appended to. A manifest is data that a user or a tool
can edit, so every path it names is checked before anything is deleted (``inside``): it must be relative,
without ``..``, and lead to the folder through no symbolic link; a file to delete must not be a link either
(rcotorch writes none). An entry that breaks the rule refuses the whole ``--overwrite``, naming the entry, and
nothing is deleted. The log is appended to only when it is a plain file (never through a link), and a folder
whose names that rcotorch writes (``summary.json``, ``rcotorch.log``, ``hparams``, a shard, ...) are symbolic
links is refused when it is opened.

Files are written to a unique temporary file in the same folder and renamed over the target, so a reader (or
a killed writer) never sees half a file and an existing file is only replaced once its successor is complete.
A write that fails (no space left, permission denied, the folder gone) raises ``OutputError`` naming the file
and what to do. An open folder remembers which folder it is: ``check`` refuses to go on once it was deleted or
replaced by another folder of the same name, so that nothing is written into a folder the run did not open.
A checkpoint starts with a header that records the SHA-256 and length of its payload (``torch.save`` output);
``load_checkpoint`` checks both and names the file when it is truncated or corrupted.
"""

from __future__ import annotations

import contextlib
import errno
import fnmatch
import hashlib
import io
import json
import os
import pickle
import re
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, BinaryIO

import torch
from filelock import FileLock, Timeout

from ..errors import CheckpointError, FolderInUseError, OutputError

MANIFEST = ".rcotorch.json"
LOCK = ".rcotorch.lock"
LOG = "rcotorch.log"
TMP_PREFIX = ".rcotorch-tmp-"
# Names that mark a folder as holding results (so that they are never mixed with a new run's).
RESULT_NAMES = ("summary.json", "checkpoint.pt", "events.out.tfevents.*", "*.png", "sweep.csv", "sweep.json",
                "hparams", "shard_*", LOG)
# Names rcotorch writes in a folder it opened (files, or folders it writes into): never symbolic links.
WRITTEN_NAMES = (*RESULT_NAMES, "members", "runs", "tune.csv", "best.toml", "sensitivity.csv", LOCK, MANIFEST)


_UMASK = os.umask(0o022)
os.umask(_UMASK)

# What to do when writing fails, by errno (others: choose another folder).
_ADVICE = {errno.ENOSPC: "free space on its disk or choose another --out",
           errno.EDQUOT: "free space within the disk quota or choose another --out",
           errno.EACCES: "choose a folder you may write to with --out",
           errno.EPERM: "choose a folder you may write to with --out",
           errno.EROFS: "choose a folder on a writable disk with --out",
           errno.ELOOP: "fix the link or choose another --out"}
# Errors that only writing to a full or read-only disk causes: an OSError without a file name and one of these
# comes from the output folder (a buffered write of an event file, say).
WRITE_FAULTS = (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EFBIG)


def write_error(e: OSError, what: str) -> OutputError:
    """``e``, raised by ``what`` (e.g. 'cannot write PATH'), as one line: what failed, why, what to do."""
    why = "a symbolic link loop" if e.errno == errno.ELOOP else e.strerror or str(e)
    return OutputError(f"{what}: {why}; {_ADVICE.get(e.errno, 'choose another --out')}")


# --- atomic files ------------------------------------------------------------------------------------------
def atomic_write(path: str | Path, write: Callable[[BinaryIO], None]) -> None:
    """Write ``path`` through ``write(file)`` into a unique temporary file beside it, then rename it over
    ``path`` (atomic on POSIX and Windows): ``path`` is either the old file or the complete new one."""
    path = Path(path)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f"{TMP_PREFIX}{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as e:
        raise write_error(e, f"cannot write {path}") from e
    try:
        os.chmod(tmp, 0o666 & ~_UMASK)   # as open() would create it (mkstemp makes it private)
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as e:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(e, OSError) and not isinstance(e, OutputError):
            raise write_error(e, f"cannot write {path}") from e
        raise


def write_text(path: str | Path, text: str) -> None:
    """``path.write_text(text)``, atomically."""
    atomic_write(path, lambda f: f.write(text.encode()))


# --- checkpoints -------------------------------------------------------------------------------------------
_MAGIC = b"RCOTORCH-CHECKPOINT 1\n"
_HEADER = len(_MAGIC) + len(b"sha256 \n") + 64 + len(b"bytes \n") + 20


class _Hashing:
    """A write-only file that hashes and counts what passes through it."""

    def __init__(self, f: BinaryIO):
        self.f, self.sha, self.size = f, hashlib.sha256(), 0

    def write(self, data) -> int:
        self.sha.update(data)
        self.size += len(data)
        return self.f.write(data)

    def flush(self) -> None:
        self.f.flush()


def save_checkpoint(path: str | Path, state: dict[str, Any]) -> None:
    """Write ``state`` (``torch.save``) behind a header with its SHA-256 and length, atomically."""
    def write(f: BinaryIO) -> None:
        f.write(b"\0" * _HEADER)
        h = _Hashing(f)
        torch.save(state, h)
        f.seek(0)
        f.write(_MAGIC + b"sha256 " + h.sha.hexdigest().encode() + b"\nbytes " + b"%020d\n" % h.size)
    atomic_write(path, write)


def _parse_header(head: bytes) -> tuple[str | None, int]:
    """(sha256, payload length) from a checkpoint's header, or (None, 0) when it is not one."""
    parts = head[len(_MAGIC):].split(b"\n")
    if not head.startswith(_MAGIC) or len(parts) != 3 or parts[2] or not parts[0].startswith(b"sha256 ") \
            or not parts[1].startswith(b"bytes ") or not parts[1][6:].isdigit():
        return None, 0
    return parts[0][7:].decode("ascii", "replace"), int(parts[1][6:])


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """Read a checkpoint written by ``save_checkpoint``; a missing, truncated or corrupted file raises
    ``CheckpointError`` naming it."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise CheckpointError(f"{path}: no such checkpoint") from None
    except OSError as e:
        raise CheckpointError(f"{path}: cannot read the checkpoint: {e.strerror}") from None
    if len(data) < _HEADER:
        raise CheckpointError(f"{path}: the checkpoint is truncated: {len(data)} bytes, shorter than its header")
    sha, size = _parse_header(data[:_HEADER])
    if sha is None:
        raise CheckpointError(f"{path}: not an rcotorch checkpoint (its header is missing or damaged)")
    payload = memoryview(data)[_HEADER:]
    if len(payload) != size:
        what = "truncated" if len(payload) < size else "longer than written"
        raise CheckpointError(f"{path}: the checkpoint is {what}: {len(payload)} of {size} bytes")
    if hashlib.sha256(payload).hexdigest() != sha:
        raise CheckpointError(f"{path}: the checkpoint is corrupted (its SHA-256 does not match its header)")
    try:
        return torch.load(io.BytesIO(payload), map_location="cpu", weights_only=True)
    except Exception as e:  # a payload that hashes right but does not load
        text = str(e)
        code = re.search(r"GLOBAL ([\w.]+)", text) if isinstance(e, pickle.UnpicklingError) else None
        if code:   # torch's weights-only unpickler met a class or function: unpickling it could run code
            raise CheckpointError(f"{path}: refused: the checkpoint holds {code.group(1)}, and loading it could "
                                  "run code; rcotorch loads only tensors and plain data (the checkpoints it "
                                  "writes)") from None
        why = re.search(r"WeightsUnpickler error:\s*(\S.*)", text)     # the cause, after torch's general advice
        reason = why.group(1) if why else (text.strip().splitlines() or [type(e).__name__])[0]
        raise CheckpointError(f"{path}: the checkpoint cannot be read: {reason}") from None


# --- output folders ----------------------------------------------------------------------------------------
def list_in_manifest(folder: str | Path, files: list[Path]) -> None:
    """Add ``files``, written into the finished output folder ``folder`` by what encloses it (a sweep's figures,
    written into its first shard's run), to that folder's manifest, atomically: so that it still lists everything
    in it that rcotorch wrote."""
    folder = Path(folder)
    path = folder / MANIFEST
    data = json.loads(path.read_text())
    data["files"] = sorted(set(data["files"]) | {str(Path(f).relative_to(folder)) for f in files})
    write_text(path, json.dumps(data, indent=1) + "\n")


def _holds_results(names: list[str]) -> list[str]:
    return sorted(n for n in names if any(fnmatch.fnmatch(n, p) for p in RESULT_NAMES))


def inside(folder: str | Path, rel: Any, what: str) -> Path:
    """The path that ``rel`` (an entry of a manifest, ``what`` naming it in messages) names inside ``folder``.

    Raises ``OutputError`` naming the entry unless it is a relative path without ``..`` whose every folder on the
    way is a real folder inside ``folder`` (no symbolic link), and which is not a symbolic link itself."""
    folder = Path(folder)
    if not isinstance(rel, str) or not rel.strip() or "\0" in rel:
        raise OutputError(f"{what} {rel!r}: not a file name; rcotorch deletes only inside {folder}")
    parts = Path(rel).parts
    if Path(rel).is_absolute() or os.path.isabs(rel):
        raise OutputError(f"{what} {rel!r} is an absolute path, outside {folder}")
    if ".." in parts:
        raise OutputError(f"{what} {rel!r} climbs out of {folder} with '..'")
    here = folder
    for i, part in enumerate(parts):
        if part == ".":
            continue
        here = here / part
        if here.is_symlink():
            link = "a symbolic link" if i == len(parts) - 1 else f"through the symbolic link {here}"
            raise OutputError(f"{what} {rel!r} is {link} (to {os.readlink(here)}); rcotorch follows no link "
                              f"out of {folder} and writes none")
    try:
        real, base = os.path.realpath(here), os.path.realpath(folder)
    except OSError as e:                              # a loop on the way
        raise OutputError(f"{what} {rel!r}: {e.strerror}") from None
    if real != base and os.path.commonpath([real, base]) != base:
        raise OutputError(f"{what} {rel!r} leads to {real}, outside {folder}")
    return here


class OutputFolder:
    """The folder a run or sweep writes, opened by one process at a time.

    Args:
        path: the folder (created with its parents when missing).
        kind: ``'run'`` or ``'sweep'``, recorded in the manifest; resuming needs the same kind.
    """

    def __init__(self, path: str | Path, kind: str):
        self.path, self.kind = Path(path), kind
        self._lock: FileLock | None = None
        self._foreign: set[str] = set()    # files that were there before we opened the folder
        self._children: list[str] = []     # subfolders that are output folders of their own (shards)
        self._identity: tuple | None = None   # (device, inode) of the open folder and of its lock file
        self._made: tuple[bool, bool] = (False, False)   # whether open made the folder, the lock file
        self._fresh = False                # opened to start a run (not to resume one)
        self._pending: list[str] = []      # log lines from before the folder was opened
        self.info: dict[str, Any] = {}

    @property
    def is_open(self) -> bool:
        return self._lock is not None

    def open(self, mode: str = "new", info: dict[str, Any] | None = None) -> OutputFolder:
        """Take the folder. ``mode``: ``'new'`` (refuses a folder holding results), ``'overwrite'`` (deletes
        the files an earlier run listed in its manifest, then starts afresh) or ``'resume'`` (continues the
        run whose manifest is there). ``info`` (e.g. the scenario) is kept in the manifest."""
        if mode not in ("new", "overwrite", "resume"):
            raise ValueError(f"mode must be 'new', 'overwrite' or 'resume', got {mode!r}")
        p = self.path
        made = self._make_folder()
        self._refuse_links([LOCK])
        made_lock = not (p / LOCK).exists()
        lock = self._take_lock()
        try:
            self._claim(mode)
            self.info = dict(self.info, **(info or {}), kind=self.kind)
            self._lock, self._made, self._fresh = lock, (made, made_lock), mode != "resume"
            self._identity = self._stat()
            self.register()
        except BaseException as e:       # the folder is left as it was found
            self._lock = self._identity = None
            if made_lock:
                with contextlib.suppress(OSError):
                    (p / LOCK).unlink()
            lock.release()
            if made:
                with contextlib.suppress(OSError):
                    p.rmdir()
            if isinstance(e, OSError) and not isinstance(e, OutputError):
                raise write_error(e, f"cannot write to the output folder {p}") from e
            raise
        pending, self._pending = self._pending, []
        if pending:
            with contextlib.suppress(OSError):     # the log is no reason to refuse the folder
                self._append_log("".join(pending))
        return self

    def _make_folder(self) -> bool:
        """Create the folder (with its parents) unless it is there; True when it was made."""
        p = self.path
        try:
            if p.is_dir():
                return False
            if p.exists():
                raise OutputError(f"{p} is a file, not a folder; choose another --out")
            p.mkdir(parents=True)
        except FileExistsError as e:     # a name on the way leads nowhere: a symbolic link loop, or to nothing
            name = Path(e.filename or p)
            try:
                os.stat(name)
            except OSError as why:
                if why.errno == errno.ELOOP:
                    raise OutputError(f"{name} is a symbolic link loop (following it leads back to it); fix the "
                                      "link or choose another --out") from None
                if name.is_symlink():
                    raise OutputError(f"{name} is a symbolic link to {os.readlink(name)}, which does not exist; "
                                      "create that folder or choose another --out") from None
            raise OutputError(f"{name} is not a folder; choose another --out") from None
        except OutputError:
            raise
        except OSError as e:
            raise write_error(e, f"cannot create the output folder {p}") from None
        return True

    def _stat(self) -> tuple:
        folder, lock = os.stat(self.path), os.stat(self.path / LOCK)
        return folder.st_dev, folder.st_ino, lock.st_dev, lock.st_ino

    def check(self) -> None:
        """Raise ``OutputError`` when the open folder was deleted, moved away or replaced by another folder (one
        without this writer's lock file) since it was opened: what the run writes would be lost, or land in a
        folder it did not open.

        Which of these happened is told by the lock file this writer holds open (``_opened_folder``): a folder
        moved away (and perhaps replaced) keeps it, and the line says where the folder is now, so that it can be
        moved back and the run resumed; a deleted folder's lock file is gone. Where the lock's descriptor cannot
        be had, a folder at the path that holds nothing but TensorBoard event files (which this run's own writer,
        writing by path, may have made again) counts as the opened one deleted."""
        if self._identity is None:
            return
        try:
            now = self._stat()
        except OSError:
            now = None
        if now == self._identity:
            return
        p = self.path
        stop = "nothing more is written there"
        try:
            folder = os.stat(p)
            same = (folder.st_dev, folder.st_ino) == self._identity[:2]
        except OSError:
            same = False
        if same:                                 # the folder is the one opened; its lock file is not
            raise OutputError(f"the lock file {p / LOCK} of the output folder {p} was removed or replaced while "
                              f"rcotorch was writing to it, and {stop}; another process may be writing there: "
                              "resume once none is, or run again")
        there = os.path.isdir(p) and not self._only_event_files()      # a folder of someone else's at the path
        exists, where = self._opened_folder()
        at = f" (it is now {where})" if where is not None else ""
        if exists and not os.path.isdir(p):
            raise OutputError(f"the output folder {p} was moved away while rcotorch was writing to it{at}, and "
                              f"{stop}; move it back and resume, or run again")
        if exists:
            now_at = f"; the original is now {where}:" if where is not None else ";"
            raise OutputError(f"the output folder {p} was replaced by another folder while rcotorch was writing to "
                              f"it, and {stop}{now_at} move the original back and resume, or run again")
        if not there:
            raise OutputError(f"the output folder {p} was deleted while rcotorch was writing to it; the results "
                              "are lost: run again")
        lost = "; the original was deleted: run again" if exists is False else \
            "; move the original back and resume, or run again"
        raise OutputError(f"the output folder {p} was replaced by another folder while rcotorch was writing to it, "
                          f"and {stop}{lost}")

    def _opened_folder(self) -> tuple[bool | None, Path | None]:
        """Whether the folder that was opened still exists, wherever it is now (None: this cannot be told), and
        where it is (None where it is gone or the system does not say). Told by the descriptor of the lock file
        this writer holds open: a file that is no longer in any folder has no links left."""
        fd = getattr(getattr(self._lock, "_context", None), "lock_file_fd", None)
        if not isinstance(fd, int) or self._identity is None:
            return None, None
        try:
            info = os.fstat(fd)
        except OSError:
            return None, None
        if (info.st_dev, info.st_ino) != self._identity[2:]:          # not the lock file opened with the folder
            return None, None
        if info.st_nlink == 0:
            return False, None
        try:                                                           # Linux names an open file's path
            name = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            return True, None
        if name.endswith(" (deleted)") or not os.path.isabs(name):
            return True, None
        return True, Path(name).parent

    def _only_event_files(self) -> bool:
        try:
            return all(p.name.startswith("events.out.tfevents") for p in self.path.rglob("*") if not p.is_dir())
        except OSError:
            return False

    def discard(self) -> None:
        """Undo ``open`` when the folder was opened to start a run that then wrote nothing but its log (a sweep
        refused before its first shard): remove the manifest, the log, the lock file and the folder where
        ``open`` made them, so that the next run finds the folder as it was. Otherwise nothing happens (the
        folder stays open)."""
        if not self.is_open or not self._fresh:
            return
        own = [f for f in self._scan() if f not in self._foreign]
        if set(own) - {LOG} or any((self.path / c).exists() for c in self._children):
            return
        made, made_lock = self._made
        for name in [MANIFEST, *own] + ([LOCK] if made_lock else []):
            with contextlib.suppress(OSError):
                (self.path / name).unlink()
        self._lock.release()
        self._lock = self._identity = None
        if made:
            with contextlib.suppress(OSError):
                self.path.rmdir()

    def _take_lock(self) -> FileLock:
        p = self.path
        lock = FileLock(p / LOCK, timeout=0, thread_local=False)
        try:
            lock.acquire()
        except Timeout:
            raise FolderInUseError(f"{p} is in use: another rcotorch run is writing to it (it holds {p / LOCK}); "
                              "wait for it to end or choose another --out") from None
        except OSError as e:
            raise write_error(e, f"cannot write to the output folder {p}") from None
        return lock

    def check_free(self) -> None:
        """Raise ``FolderInUseError`` when another writer holds the folder (nothing is changed; a folder that
        cannot be written is left for ``open`` to report)."""
        if self.is_open or not (self.path / LOCK).exists():
            return
        try:
            lock = self._take_lock()
        except FolderInUseError:
            raise
        except OutputError:
            return
        lock.release()

    def _claim(self, mode: str) -> None:
        p = self.path
        names = [n for n in os.listdir(p) if n not in (LOCK, MANIFEST) and not n.startswith(TMP_PREFIX)]
        self._refuse_links([*names, MANIFEST])
        manifest = self.manifest()
        if manifest is None:
            found = _holds_results(names)
            if found:
                raise OutputError(f"{p} holds results that no rcotorch manifest lists ({', '.join(found[:4])}"
                                  f"{', ...' if len(found) > 4 else ''}): rcotorch never deletes or overwrites "
                                  "files it did not write; move them or choose another --out")
            if mode == "resume":
                raise OutputError(f"{p} holds no rcotorch {self.kind} to resume")
        elif mode == "new":
            raise OutputError(f"{p} already holds a {manifest.get('kind', 'run')} "
                              f"({manifest.get('scenario', 'unknown scenario')}); use --resume to continue it, "
                              "--overwrite to replace it, or choose another --out")
        elif mode == "resume" and manifest.get("kind") != self.kind:
            raise OutputError(f"{p} holds a {manifest.get('kind')}, not a {self.kind}")
        if manifest is not None:
            self._check_listed(manifest)
            self._remove_stale_temporaries()
            if mode == "overwrite":
                self._delete_listed(manifest)
                manifest = None
        if manifest is not None:
            self.info = {k: v for k, v in manifest.items() if k not in ("files", "children")}
            self._children = list(manifest.get("children", []))
        own = set(manifest.get("files", [])) if manifest else set()
        self._foreign = {f for f in self._scan() if f not in own}

    def _refuse_links(self, names: list[str]) -> None:
        """Raise ``OutputError`` when one of ``names`` (in the folder) that rcotorch writes is a symbolic link."""
        for n in sorted(names):
            path = self.path / n
            if any(fnmatch.fnmatch(n, w) for w in WRITTEN_NAMES) and path.is_symlink():
                raise OutputError(f"{path} is a symbolic link (to {os.readlink(path)}) where rcotorch writes its own "
                                  "file or folder; it follows no link out of its output folder: remove the link or "
                                  "choose another --out")

    def _remove_stale_temporaries(self) -> None:
        """Temporary files of a writer that was killed mid-write (named by ``atomic_write``; links are left)."""
        for f in self.path.glob(f"{TMP_PREFIX}*.tmp"):
            if not f.is_symlink():
                with contextlib.suppress(OSError):
                    f.unlink()

    def _check_listed(self, manifest: dict[str, Any]) -> None:
        """Refuse a manifest that names anything outside the folder (``inside``), its children's included,
        before anything is deleted."""
        where = self.path / MANIFEST
        children = manifest.get("children", [])
        if not isinstance(children, list):
            raise OutputError(f"{where}: 'children' is not a list; move the folder aside")
        try:
            for rel in manifest.get("files", []):
                inside(self.path, rel, "the entry")
            for child in children:
                inside(self.path, child, "the child folder")
        except OutputError as e:
            raise OutputError(f"{where}: refused: {e}; rcotorch deletes, replaces and appends only inside the "
                              "folder it was given: correct the manifest or choose another --out") from None
        for child in children:
            sub = OutputFolder(self.path / child, "run")
            sub_manifest = sub.manifest()
            if sub_manifest is not None:
                sub._check_listed(sub_manifest)

    def _delete_listed(self, manifest: dict[str, Any]) -> None:
        """Delete what an earlier run wrote here (its manifest's files and its children's), nothing else; the
        manifest was checked by ``_check_listed``."""
        for child in manifest.get("children", []):
            sub = OutputFolder(self.path / child, "run")
            sub_manifest = sub.manifest()
            if sub_manifest is not None:
                sub.open("overwrite")
                sub.close()
                for name in (MANIFEST, LOCK):
                    with contextlib.suppress(OSError):
                        (sub.path / name).unlink()
                with contextlib.suppress(OSError):
                    sub.path.rmdir()           # only when nothing else is left in it
        for rel in manifest.get("files", []):
            with contextlib.suppress(FileNotFoundError, IsADirectoryError):
                inside(self.path, rel, "the entry").unlink()
        dirs = {(self.path / rel).parent for rel in manifest.get("files", [])} - {self.path}
        for d in sorted(dirs, key=lambda d: -len(d.parts)):
            with contextlib.suppress(OSError):
                d.rmdir()
        with contextlib.suppress(FileNotFoundError):
            (self.path / MANIFEST).unlink()

    def _scan(self) -> list[str]:
        """Every file below the folder (relative paths), except the lock, the manifest, temporaries and the
        contents of nested output folders."""
        out = []
        for root, dirs, files in os.walk(self.path):
            here = Path(root)
            if here != self.path and ((here / LOCK).exists() or (here / MANIFEST).exists()):
                dirs.clear()
                continue
            for f in files:
                if here == self.path and f in (LOCK, MANIFEST):
                    continue
                if not f.startswith(TMP_PREFIX):
                    out.append(str((here / f).relative_to(self.path)))
        return out

    def manifest(self) -> dict[str, Any] | None:
        """The folder's manifest, or None when it has none."""
        path = self.path / MANIFEST
        try:
            data = json.loads(path.read_text())
        except FileNotFoundError:
            return None
        except (OSError, ValueError) as e:
            raise OutputError(f"{path}: unreadable rcotorch manifest ({e}); move the folder aside") from None
        if not isinstance(data, dict) or not isinstance(data.get("files"), list):
            raise OutputError(f"{path}: not an rcotorch manifest; move the folder aside")
        return data

    def add_child(self, name: str) -> None:
        """Record a subfolder that is an output folder of its own (a sweep's shard)."""
        if name not in self._children:
            self._children.append(name)

    def register(self) -> None:
        """Record every file this writer has added so far in the manifest (atomically)."""
        if not self.is_open:
            return
        self.check()
        files = sorted(f for f in self._scan() if f not in self._foreign)
        body = dict(self.info, files=files, children=self._children)
        write_text(self.path / MANIFEST, json.dumps(body, indent=1) + "\n")

    def log(self, line: str) -> None:
        """Append a time-stamped line to the folder's ``rcotorch.log`` (before the folder is opened, the line
        waits: it is written when ``open`` succeeds, and dropped when it fails)."""
        stamped = f"{time.strftime('%Y-%m-%d %H:%M:%S')} {line}\n"
        if not self.is_open:
            self._pending.append(stamped)
            return
        self.check()
        self._append_log(stamped)

    def _append_log(self, text: str) -> None:
        """Append to the log, a plain file of the folder's (never through a symbolic link)."""
        path = self.path / LOG
        try:
            fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0), 0o666)
        except OSError as e:
            if path.is_symlink():
                raise OutputError(f"{path} is a symbolic link (to {os.readlink(path)}); rcotorch appends to no "
                                  "file outside its output folder: remove the link") from None
            raise write_error(e, f"cannot write {path}") from e
        try:
            with os.fdopen(fd, "a") as f:
                f.write(text)
        except OSError as e:
            raise write_error(e, f"cannot write {path}") from e

    def close(self) -> None:
        """Update the manifest and release the lock."""
        if self._lock is None:
            return
        try:
            self.register()
        except OSError:
            pass       # the folder became unwritable: the manifest keeps listing less, never more
        finally:
            self._lock.release()
            self._lock = self._identity = None
