"""A process that draws a run's (or a sweep's) figures beside it.

``rcotorch run`` starts it first, before it imports torch: while the run imports torch, builds its graph and
steps, the drawing process imports matplotlib and the figures on a core of its own, and at the end of the run it
draws the figure data the run sends it (``rcotorch.run.figure_data.RunFigureData``: NumPy arrays and text) on
every core it may use (``rcotorch.run.figures.draw``) and sends back their PNG bytes. ``rcotorch sweep`` starts
one the same way for the sweep's figures (``rcotorch.run.figure_data.SweepFigureData``), which it draws while the
sweep writes its table and HParams sessions. It never imports torch.
Where it cannot start (off Linux, no process to spare) or fails, the run draws its figures itself, the same
bytes. Importing this module imports neither torch nor matplotlib.
"""

from __future__ import annotations

import contextlib
import gc
import os
import pickle
import queue
import signal
import sys
import threading
import warnings
from collections.abc import Callable

from .pipes import read_frame, write_frame

NICE = 10      # the drawing process's niceness above the run's (about a tenth of a core where both want one)


class DrawingProcess:
    """One forked process that draws one run's or sweep's figures (``draw``, one or more jobs); ``close`` ends it
    where it was not used."""

    def __init__(self) -> None:
        self.pid: int | None = None
        self._jobs: int | None = None          # the pipe the figure data go to
        self._results: int | None = None       # the pipe the PNG bytes come back on
        self._sent = 0                         # jobs sent, and the results read back, in order
        self._got: dict[int, dict[str, bytes]] = {}
        self._read = 0
        if not sys.platform.startswith("linux") or not hasattr(os, "fork"):
            return
        jobs_r, jobs_w = os.pipe()
        results_r, results_w = os.pipe()
        pid = -1
        try:
            with warnings.catch_warnings():  # Python 3.12+ warns of forking with threads: none run where it draws
                warnings.simplefilter("ignore", DeprecationWarning)
                pid = os.fork()
        except OSError:                      # no process to spare: the run draws its figures itself
            for fd in (jobs_r, jobs_w, results_r, results_w):
                os.close(fd)
            return
        if pid == 0:
            os.close(jobs_w)
            os.close(results_r)
            _serve(jobs_r, results_w)
        os.close(jobs_r)
        os.close(results_w)
        self.pid, self._jobs, self._results = pid, jobs_w, results_r

    @property
    def started(self) -> bool:
        """Whether the process runs and takes figures to draw (its last job not sent yet)."""
        return self.pid is not None and self._jobs is not None

    def draw(self, data, more: bool = False) -> Callable[[], dict[str, bytes]]:
        """Send ``data`` (``RunFigureData`` or ``SweepFigureData``) to be drawn; the returned function waits for
        the figures' PNG bytes {name: bytes}, and draws them in this process where the drawing process was not
        started or failed (so that an error in a figure is raised here, as drawn here). ``more``: another job
        follows (the process draws its jobs in the order sent); else this is its last."""
        index = None
        if self.started:
            try:
                write_frame(self._jobs, pickle.dumps(data, protocol=pickle.HIGHEST_PROTOCOL))
                index = self._sent
                self._sent += 1
            except OSError:                  # the process has ended
                pass
            if not more or index is None:
                os.close(self._jobs)
                self._jobs = None

        def wait() -> dict[str, bytes]:
            out = None if index is None else self._result(index)
            if out is None:
                self.close()
                from .figures import draw
                out = draw(data)
            return out
        return wait

    def _result(self, index: int) -> dict[str, bytes] | None:
        """The PNG bytes of job ``index``, reading the results in order; None where the process ended (or failed)
        before it sent them. The process is reaped once every result sent is read."""
        while index >= self._read and self._results is not None:
            frame = read_frame(self._results)
            if frame is None:
                self._reap()
                break
            self._got[self._read] = pickle.loads(frame)
            self._read += 1
        if self._results is not None and self._jobs is None and self._read == self._sent:
            self._reap()
        return self._got.pop(index, None)

    def _reap(self) -> None:
        if self._results is not None:
            os.close(self._results)
            self._results = None
        if self.pid is not None and self._jobs is None:
            os.waitpid(self.pid, 0)
            self.pid = None

    def close(self) -> None:
        """End the process (where it still runs) and release its pipes."""
        for name in ("_jobs", "_results"):
            fd = getattr(self, name)
            if fd is not None:
                os.close(fd)
                setattr(self, name, None)
        if self.pid is not None:
            try:
                os.kill(self.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            os.waitpid(self.pid, 0)
            self.pid = None


def _serve(jobs: int, results: int) -> None:
    """In the forked process: read the figure data from ``jobs`` while importing the figures (a thread reads every
    job as it comes, so that a job sent while this draws never waits on the pipe); draw each job in a process of
    its own, forked as the job comes (a job sent while an earlier one is drawn is drawn beside it), and write
    their pickled PNG bytes to ``results`` in the order the jobs came. End with status 0 only where all of that
    succeeded (or no figures came: the run ended without them); at the first job that fails, end at once with
    status 1 (the run draws that job and the later ones itself)."""
    code = 1
    try:
        gc.disable()        # no collection here: the finalizers of the parent's garbage (files, folders) stay its own
        signal.signal(signal.SIGINT, signal.SIG_IGN)     # Ctrl-C reaches the process group: the run answers it
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        with contextlib.suppress(OSError):
            os.nice(NICE)       # a core the run needs goes to the run: the drawing takes the cores it leaves idle
        got: queue.SimpleQueue = queue.SimpleQueue()
        drawn: queue.SimpleQueue = queue.SimpleQueue()   # (pid, pipe) of each job's process, in order; None: the end

        def read() -> None:
            while True:
                frame = read_frame(jobs)
                got.put(frame)
                if frame is None:
                    return

        def forward() -> None:
            while (job := drawn.get()) is not None:
                pid, pipe = job
                payload = read_frame(pipe)
                os.close(pipe)
                _, status = os.waitpid(pid, 0)
                if payload is None or status != 0:
                    os._exit(1)
                write_frame(results, payload)
        threading.Thread(target=read, daemon=True).start()
        forwarder = threading.Thread(target=forward, daemon=True)
        forwarder.start()
        from . import figures  # matplotlib: the long part, beside the run
        figures.warm()
        while (frame := got.get()) is not None:
            drawn.put(_draw_apart(figures, frame))
        drawn.put(None)
        forwarder.join()
        code = 0
    except BaseException:       # the run draws the figures itself, and reports what fails there
        code = 1
    finally:
        os._exit(code)


def _draw_apart(figures, frame: bytes) -> tuple[int, int]:
    """Fork a process that draws one job (its pickled figure data) and writes its pickled PNG bytes to a pipe;
    returns its pid and the pipe's reading end."""
    r, w = os.pipe()
    with warnings.catch_warnings():           # the threads here only read pipes: none holds what the fork needs
        warnings.simplefilter("ignore", DeprecationWarning)
        pid = os.fork()
    if pid == 0:
        code = 1
        try:
            os.close(r)
            data = pickle.loads(frame)
            write_frame(w, pickle.dumps(figures.draw(data), protocol=pickle.HIGHEST_PROTOCOL))
            code = 0
        finally:
            os._exit(code)
    os.close(w)
    return pid, r
