"""How a sweep or a tuning is driven: ``RunControl``, one record of the flags that travel from the command line
(or a caller of ``run_tune`` and ``run_sweep``) through the tuning and its sweeps down to each shard's run.

``rcotorch tune`` and ``rcotorch sweep`` make one record (``--overwrite``, ``--resume``, the stop request of
Ctrl-C, SIGTERM and SIGHUP, the output folder they opened); ``run_tune`` and ``run_sweep`` take it as
``control=``, or make it from their keywords ``progress``, ``overwrite``, ``resume``, ``stop`` and ``folder``.
A tuning hands each of its sweeps a copy (``dataclasses.replace``: the sweep opens its own folder, and resumes
only where that folder holds a sweep); a sweep hands each shard's run its ``stop`` and ``progress``
(``Run.advance``). A record is never changed once made: the checks of ``__post_init__`` hold for every path.
"""

from __future__ import annotations

import signal
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from ..errors import ConfigError

if TYPE_CHECKING:
    from .outputs import OutputFolder


# The signals that stop a run or sweep at the next step boundary, with a checkpoint (exit code 128 + the
# signal's number: 130, 143, 129), by the names the messages use; a sweep's workers answer them too.
STOP_SIGNALS = {signal.SIGINT: "Ctrl-C", signal.SIGTERM: "SIGTERM",
                **({signal.SIGHUP: "SIGHUP"} if hasattr(signal, "SIGHUP") else {})}


@dataclass(frozen=True)
class RunControl:
    """How a sweep or a tuning is driven: progress lines, what to do with an output folder that holds results,
    when to stop, and the folder the caller opened.

    Parameters
    ----------
    progress : bool, optional
        Print a line per shard (a tuning: per round too) and show each locally run shard's progress bar.
    overwrite : bool, optional
        Replace the results the output folder holds (only the files its manifest lists).
    resume : bool, optional
        Continue the interrupted work the output folder holds.
    stop : callable, optional
        ``stop()`` is asked between stretches of steps (and while the Ray backend waits for its shards); when
        it says True the running shard saves a checkpoint and ``rcotorch.run.runner.Interrupted`` is raised.
        None: the work runs to its end.
    folder : rcotorch.run.outputs.OutputFolder, optional
        The output folder, made by the caller, who closes it (and may log into it meanwhile). None: the work
        makes and closes its own.
    workers : int, optional
        How many shards the local backend runs at once, each in a process of its own forked from this one
        (one CPU thread each). None: one per core this process may use (at most one per shard) on Linux and the
        CPU, else 1; 1 runs the shards one after another in this process.

    Raises
    ------
    ConfigError
        If both ``overwrite`` and ``resume`` are set, ``stop`` is not callable or ``workers`` is not a positive
        integer.
    """

    progress: bool = True
    overwrite: bool = False
    resume: bool = False
    stop: Callable[[], bool] | None = None
    folder: OutputFolder | None = None
    workers: int | None = None

    def __post_init__(self):
        if self.overwrite and self.resume:
            raise ConfigError("choose one of --overwrite and --resume")
        if self.stop is not None and not callable(self.stop):
            raise ConfigError(f"stop must be a function that returns True to stop (or None), got {self.stop!r}")
        if self.workers is not None and (isinstance(self.workers, bool) or not isinstance(self.workers, int)
                                         or self.workers < 1):
            raise ConfigError(f"workers must be a positive integer (or None), got {self.workers!r}")

    @property
    def mode(self) -> str:
        """How the output folder is opened (``OutputFolder.open``): 'resume', 'overwrite' or 'new'."""
        return "resume" if self.resume else "overwrite" if self.overwrite else "new"

    @classmethod
    def given(cls, control: RunControl | None, progress: bool = True, overwrite: bool = False,
              resume: bool = False, stop: Callable[[], bool] | None = None,
              folder: OutputFolder | None = None, workers: int | None = None) -> RunControl:
        """The record a function that takes both ``control=`` and the loose keywords runs with.

        Parameters
        ----------
        control : RunControl or None
            The record the caller gave, if any.
        progress, overwrite, resume, stop, folder, workers : optional
            The keywords the caller gave, as for the record's fields.

        Returns
        -------
        RunControl
            ``control`` itself where given, else a record of the keywords.

        Raises
        ------
        ConfigError
            If ``control`` comes with a keyword that differs from its default, or the keywords do not agree
            (both ``overwrite`` and ``resume``).
        """
        if control is None:
            return cls(progress=progress, overwrite=overwrite, resume=resume, stop=stop, folder=folder,
                       workers=workers)
        if not isinstance(control, cls):
            raise ConfigError(f"control must be a {cls.__name__}, got {type(control).__name__}")
        given = [name for name, value, default in (("progress", progress, True), ("overwrite", overwrite, False),
                                                   ("resume", resume, False)) if value != default]
        given += [name for name, value in (("stop", stop), ("folder", folder), ("workers", workers))
                  if value is not None]
        if given:
            raise ConfigError(f"give {', '.join(given)} in control= or as keywords, not both")
        return control
