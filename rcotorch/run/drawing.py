"""A process that draws a run's (or a sweep's) figures beside it.

``rcotorch run`` starts it first, before it imports torch: while the run imports torch, builds its graph and
steps, the drawing process imports matplotlib and the figures on a core of its own, and at the end of the run it
draws the figure data the run sends it (``rcotorch.run.figure_data.RunFigureData``: NumPy arrays and text) on
every core it may use (``rcotorch.run.figures.pngs``) and sends back their PNG bytes. ``rcotorch sweep`` starts
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
import signal
import sys
import threading
import warnings
from collections.abc import Callable

NICE = 10      # the drawing process's niceness above the run's (about a tenth of a core where both want one)


class DrawingProcess:
    """One forked process that draws one run's or sweep's figures (``draw``); ``close`` ends it where it was not
    used."""

    def __init__(self) -> None:
        self.pid: int | None = None
        self._jobs: int | None = None          # the pipe the figure data go to
        self._results: int | None = None       # the pipe the PNG bytes come back on
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
        """Whether the process runs and has not been sent its figures yet."""
        return self.pid is not None and self._jobs is not None

    def draw(self, data) -> Callable[[], dict[str, bytes]]:
        """Send ``data`` (``RunFigureData`` or ``SweepFigureData``) to be drawn; the returned function waits for
        the figures' PNG bytes {name: bytes}, and draws them in this process where the drawing process was not
        started or failed (so that an error in a figure is raised here, as drawn here)."""
        sent = False
        if self.started:
            try:
                payload = pickle.dumps(data, protocol=pickle.HIGHEST_PROTOCOL)
                with os.fdopen(self._jobs, "wb") as f:
                    self._jobs = None
                    f.write(payload)
                sent = True
            except OSError:                  # the process has ended
                pass

        def wait() -> dict[str, bytes]:
            out = self._receive() if sent else None
            if out is None:
                self.close()
                from .figures import figures_of, pngs
                out = pngs(figures_of(data))
            return out
        return wait

    def _receive(self) -> dict[str, bytes] | None:
        with os.fdopen(self._results, "rb") as f:
            self._results = None
            payload = f.read()
        _, status = os.waitpid(self.pid, 0)
        self.pid = None
        if status != 0 or not payload:
            return None
        return pickle.loads(payload)

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
    """In the forked process: read the figure data from ``jobs`` while importing the figures, draw them and
    write their pickled PNG bytes to ``results``; end with status 0 only where all of that succeeded (or no
    figures came: the run ended without them)."""
    code = 1
    try:
        gc.disable()        # no collection here: the finalizers of the parent's garbage (files, folders) stay its own
        signal.signal(signal.SIGINT, signal.SIG_IGN)     # Ctrl-C reaches the process group: the run answers it
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        with contextlib.suppress(OSError):
            os.nice(NICE)       # a core the run needs goes to the run: the drawing takes the cores it leaves idle
        got: list[bytes] = []

        def read() -> None:
            with os.fdopen(jobs, "rb") as f:
                got.append(f.read())
        reader = threading.Thread(target=read, daemon=True)
        reader.start()
        from . import figures  # matplotlib: the long part, beside the run
        figures.warm()
        reader.join()
        if not got or not got[0]:
            code = 0
            return
        data = pickle.loads(got[0])
        payload = pickle.dumps(figures.pngs(figures.figures_of(data)), protocol=pickle.HIGHEST_PROTOCOL)
        with os.fdopen(results, "wb") as f:
            f.write(payload)
        code = 0
    except BaseException:       # the run draws the figures itself, and reports what fails there
        code = 1
    finally:
        os._exit(code)
