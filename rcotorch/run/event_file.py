"""TensorBoard event files written in the calling thread (``EventFile``), and the CRC-32C of their records.

TensorBoard's own writers (``tensorboard.summary.writer.event_file_writer.EventFileWriter``, which
``torch.utils.tensorboard.SummaryWriter`` uses) checksum every record with a CRC-32C computed in pure Python a
byte at a time, on a writer thread of their own, and that checksum is most of what writing an event costs.
``benchmarks/tb_writer.py`` replays the events of real runs through both writers and records what each costs,
import included, in ``benchmarks/results/tb_writer.json``: there TensorBoard's writer takes many times the time
of this one (the decision rule and its verdict are in that file, and TensorBoard's record framing alone in the
calling thread shows the checksum's share). So the records are framed here, each checksummed by the compiled
CRC-32C of ``google-crc32c``. Beside speed: the first event of an ``EventFile`` carries a chosen wall time
(TensorBoard orders a run's sibling runs by it, ``rcotorch.run.monitor.Monitor.start``), where TensorBoard's writer
stamps it with the time it was made; and a write fault (a full disk) is raised by the write that meets it, in the
thread that logs, not by a later call after the writer thread met it.

The events themselves are TensorBoard's protocol buffers, their summaries made by TensorBoard's and PyTorch's
summary functions; only the record format is written here.
"""

from __future__ import annotations

import os
import socket
import struct
import time
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any


def _scalar_event(values: Iterable[tuple[str, float]]):
    from tensorboard.compat.proto.event_pb2 import Event
    from tensorboard.compat.proto.summary_pb2 import Summary
    return Event(summary=Summary(value=[Summary.Value(tag=tag, simple_value=value) for tag, value in values]))


def _growing_edges(start: float = 1e-12, stop: float = 1e20, factor: float = 1.1) -> list[float]:
    """start, start * factor, ... below stop."""
    edges, v = [], start
    while v < stop:
        edges.append(v)
        v *= factor
    return edges


class EventFile:
    """A TensorBoard event file written in the calling thread: each event framed as a record (its length, the
    masked CRC-32C of the length, the serialized event, the masked CRC-32C of the event) into a buffered file,
    flushed every ``FLUSH_S`` seconds and by ``flush`` and ``close``. Every run's events are written so (the run,
    its siblings, a sweep's sessions): an event costs its serialization and checksum, with no writer thread to
    hand it to. Summaries are made by TensorBoard's and PyTorch's summary functions (``add_summary``).

    Args:
        folder: the run's folder (made if missing).
        purge_step: where a resumed run continues: TensorBoard drops this run's earlier events from that step.
        start: the wall time of the file's first event (default now), which TensorBoard takes as the run's start
            time and lists its runs by (``Monitor.start``).
    """

    FLUSH_S = 5.0
    _count = 0

    def __init__(self, folder: Path, purge_step: int | None = None, start: float | None = None):
        from tensorboard.compat.proto.event_pb2 import Event, SessionLog
        folder.mkdir(parents=True, exist_ok=True)
        EventFile._count += 1
        self.path = folder / (f"events.out.tfevents.{int(time.time()):010d}.{socket.gethostname()}.{os.getpid()}."
                              f"{EventFile._count:04d}")
        self._file = open(self.path, "wb")      # open until close
        self._flushed = time.monotonic()
        self._write(Event(wall_time=time.time() if start is None else start, file_version="brain.Event:2"))
        if purge_step is not None:
            self._write(Event(wall_time=time.time(), step=purge_step, session_log=SessionLog(status=SessionLog.START)))
        self.flush()

    # The histograms' bin edges: TensorBoard's convention, +-1e-12 growing by 10% a bin up to 1e20, and 0.
    default_bins = [-e for e in reversed(_growing_edges())] + [0.0] + _growing_edges()

    def scalars(self, step: int, wall: float, values: Iterable[tuple[str, float]]) -> None:
        """One event holding every (tag, value) pair at ``step`` and wall time ``wall``."""
        event = _scalar_event(values)
        event.step, event.wall_time = step, wall
        self._write(event)

    def add_event(self, event, step: int | None = None, wall: float | None = None) -> None:
        """An event at ``step`` (none: the event's own) and wall time ``wall`` (none: now)."""
        event.wall_time = time.time() if wall is None else wall
        if step is not None:
            event.step = int(step)
        self._write(event)

    def add_summary(self, summary, step: int | None = None, wall: float | None = None) -> None:
        """A ``Summary`` protocol buffer as an event (``add_event``)."""
        from tensorboard.compat.proto.event_pb2 import Event
        self.add_event(Event(summary=summary), step, wall)

    def add_scalar(self, tag: str, value: float, step: int, wall: float | None = None) -> None:
        self.scalars(step, time.time() if wall is None else wall, [(tag, float(value))])

    def add_text(self, tag: str, text: str, step: int, walltime: float | None = None) -> None:
        """Markdown text under ``tag`` (TensorBoard's Text tab)."""
        from torch.utils.tensorboard.summary import text as text_summary
        self.add_summary(text_summary(tag, text), step, walltime)

    def add_custom_scalars(self, layout: Mapping[str, Any]) -> None:
        """The Custom Scalars layout ({section: {title: ['Multiline' or 'Margin', tags]}})."""
        from torch.utils.tensorboard.summary import custom_scalars
        self.add_summary(custom_scalars(layout))

    def __enter__(self) -> EventFile:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # The record: what TensorBoard's RecordWriter frames, with the checksum in C instead of its pure Python, which
    # made its writer many times slower (benchmarks/tb_writer.py, benchmarks/results/tb_writer.json).
    def _write(self, event) -> None:
        data = event.SerializeToString()
        head = struct.pack("<Q", len(data))
        self._file.write(head + struct.pack("<I", masked_crc32c(head)) + data + struct.pack("<I", masked_crc32c(data)))
        if time.monotonic() - self._flushed > self.FLUSH_S:
            self.flush()

    def flush(self) -> None:
        if not self._file.closed:
            self._file.flush()
            self._flushed = time.monotonic()

    def close(self) -> None:
        if not self._file.closed:
            try:
                self._file.flush()
            finally:
                self._file.close()


# --- the records' checksum ------------------------------------------------------------------------------------
# TensorBoard's event records are checksummed (their length and their bytes) with CRC-32C; google-crc32c computes it
# in C (TensorBoard's own, in pure Python, is what made its writer slow: see the module's docstring).
def crc32c(data: bytes) -> int:
    """The CRC-32C (Castagnoli) of ``data``."""
    import google_crc32c
    return google_crc32c.value(data)


def masked_crc32c(data: bytes) -> int:
    """The masked CRC-32C of TensorBoard's record format."""
    x = crc32c(data)
    return (((x >> 15) | (x << 17)) + 0xA282EAD8) & 0xFFFFFFFF
