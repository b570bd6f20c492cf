"""What the machine lets this process take: the memory still available, from the kernel's estimate, the
memory cgroups the process is in and its address-space limit. Used before large allocations (a run's state, a
recording's arrays), so that a request that cannot fit is refused by name instead of ending in MemoryError."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable
from pathlib import Path

MEMINFO = Path("/proc/meminfo")


def _reclaimable(folder: Path) -> int:
    """The page cache a cgroup v2 holds that the kernel can drop (``inactive_file`` in ``memory.stat``), 0 where
    it is not known."""
    with contextlib.suppress(OSError, ValueError, IndexError):
        for line in (folder / "memory.stat").read_text().splitlines():
            if line.startswith("inactive_file "):
                return int(line.split()[1])
    return 0


def _cgroup_dirs() -> list[Path]:
    """The memory cgroup folders of this process and those above it (v2, else v1), where they can be read."""
    root, dirs = Path("/sys/fs/cgroup"), []
    with contextlib.suppress(OSError):
        for line in Path("/proc/self/cgroup").read_text().splitlines():
            _, controllers, where = line.split(":", 2)
            base = root if not controllers else root / "memory" if "memory" in controllers.split(",") else None
            if base is None:
                continue
            folder = base / where.lstrip("/")
            while True:
                dirs.append(folder)
                if folder == base:
                    break
                folder = folder.parent
    return list(dict.fromkeys(dirs + [root]))


def _address_space_room() -> int | None:
    """The bytes left under this process's address-space limit (``ulimit -v``), None without one."""
    import resource
    limit = resource.getrlimit(resource.RLIMIT_AS)[0]
    if limit == resource.RLIM_INFINITY:
        return None
    with contextlib.suppress(OSError, ValueError, IndexError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmSize:"):
                return max(0, limit - int(line.split()[1]) * 1024)
    return limit


def available_memory(meminfo: Path = MEMINFO, cgroups: list[Path] | None = None,
                     address_space: Callable[[], int | None] | int | None = _address_space_room
                     ) -> tuple[int, str] | None:
    """The memory this process may still take, in bytes, and what sets it: the least of ``MemAvailable`` in
    ``meminfo``, each cgroup's limit less what the cgroup uses (cgroup v2 ``memory.max`` and ``memory.current``,
    or v1 ``memory.limit_in_bytes`` and ``memory.usage_in_bytes``; default: the process's own cgroup and the
    ones above it, ``_cgroup_dirs``) and the room left under the address-space limit (``ulimit -v``; a number,
    None for none, default ``_address_space_room``). None when none of them can be read."""
    found: list[tuple[int, str]] = []
    with contextlib.suppress(OSError, ValueError, IndexError):
        for line in meminfo.read_text().splitlines():
            if line.startswith("MemAvailable:"):
                found.append((int(line.split()[1]) * 1024, f"MemAvailable in {meminfo}"))
    if not found and meminfo == MEMINFO:                # no MemAvailable: the free physical pages
        with contextlib.suppress(ValueError, OSError, AttributeError):
            found.append((os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"), "the free physical pages"))
    for folder in _cgroup_dirs() if cgroups is None else cgroups:
        for limit_name, usage_name in (("memory.max", "memory.current"),
                                       ("memory.limit_in_bytes", "memory.usage_in_bytes")):
            with contextlib.suppress(OSError, ValueError):
                text = (folder / limit_name).read_text().strip()
                if text == "max" or int(text) >= 2 ** 60:               # v1 writes a huge number for none
                    continue
                usage = 0
                with contextlib.suppress(OSError, ValueError):
                    usage = int((folder / usage_name).read_text().strip()) - _reclaimable(folder)
                found.append((max(0, int(text) - usage), f"the limit {folder / limit_name} less what the cgroup "
                                                            "uses"))
    room = address_space if address_space is None or isinstance(address_space, int) else address_space()
    if room is not None:
        found.append((room, "the address-space limit (ulimit -v) less what this process maps"))
    return min(found, key=lambda f: f[0]) if found else None
