"""Messages on a pipe between forked processes: a length (8 bytes, little-endian), then that many bytes. The
drawing process (``rcotorch.run.drawing``) and a sweep's workers (``rcotorch.run.sweep``) speak it. Importing this
module imports nothing beyond the standard library."""

from __future__ import annotations

import os


def write_frame(fd: int, payload: bytes) -> None:
    """One message on a pipe: its length (8 bytes, little-endian), then its bytes."""
    view = memoryview(len(payload).to_bytes(8, "little") + payload)
    while view:
        view = view[os.write(fd, view):]


def read_frame(fd: int) -> bytes | None:
    """The next message on a pipe (``write_frame``); None where the pipe ended before a whole one."""
    def exactly(n: int) -> bytes | None:
        parts, left = [], n
        while left:
            chunk = os.read(fd, min(left, 1 << 20))
            if not chunk:
                return None
            parts.append(chunk)
            left -= len(chunk)
        return b"".join(parts)
    head = exactly(8)
    return None if head is None else exactly(int.from_bytes(head, "little"))
