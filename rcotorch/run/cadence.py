"""When a run logs, and what its logs and health checks read between stops of the engine.

* ``default_log_every``: the steps between logs, from the run's length and batch (about 1000 logs a run, fewer
  for large batches, since a log costs about as much as a few steps of the whole batch), placed so that logs fall
  on health checks' steps or checks on logs' (every stop of the engine costs a pass over the batch's state);
* ``is_log`` and ``next_log``: the log steps, every ``log_every`` steps with a few early ones before the first;
* ``ErrorSums``: the sums of squares of the model error (and the measured output) the engine accumulates, which
  the health checks and the logs each take at their own cadence.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import torch

from ..verdict.health import check_every
from .limits import ENGINE_NS

LOG_BUDGET = 2 ** 21     # member-values logged per run, at most (but at least MIN_LOGS logs)
MIN_LOGS, MAX_LOGS = 20, 1000
MIN_LOGS_CHANGE = 250    # at least, in a run that follows a change (a truth that changes, or a change detector)
# The logs of a run may take about LOG_SHARE of the engine's time, or LOG_FREE_S seconds where that is more: a
# log (with the stop of the engine before it) costs about LOG_US + LOG_US_PER_MEMBER * batch microseconds, a
# member-step of the native engine at least ENGINE_NS nanoseconds (``rcotorch.run.limits``, docs/cli.md).
LOG_SHARE, LOG_FREE_S, LOG_US, LOG_US_PER_MEMBER = 0.1, 0.01, 250.0, 0.7
EARLY_LOGS = 4          # logs before the first interval: at its halves every / 2, every / 4, ...


def default_log_every(steps: int, batch: int, follows_change: bool = False) -> int:
    """Steps between logs: as many logs as take about LOG_SHARE of the engine's time (or LOG_FREE_S), at most
    MAX_LOGS and LOG_BUDGET member-values in all (since a log reads every member), but at least MIN_LOGS, or
    MIN_LOGS_CHANGE in a run that follows a change (its figures draw the change and the estimates' path after
    it, which a few dozen points would join by straight lines across the change). An interval
    longer than the health checks' (in the convergence window) is the nearest multiple of twice theirs (their
    spacing before the window), a shorter one a divisor of theirs near it, so that logs fall on check steps or
    checks on log steps: every stop of the engine costs a pass over the whole batch's state."""
    budget_us = max(LOG_SHARE * steps * batch * ENGINE_NS * 1e-3, LOG_FREE_S * 1e6)
    affordable = budget_us / (LOG_US + LOG_US_PER_MEMBER * batch)
    least = MIN_LOGS_CHANGE if follows_change else MIN_LOGS
    logs = min(MAX_LOGS, max(MIN_LOGS, min(max(int(affordable), least), LOG_BUDGET // batch)))
    every, check = max(1, math.ceil(steps / logs)), check_every(steps)
    if every > check:
        return 2 * check * max(1, round(every / (2 * check)))
    n = max(1, check // every)                  # a divisor of the checks' spacing, no shorter: checks fall on logs
    while check % n:
        n -= 1
    return check // n


def next_multiple(k: int, every: int) -> int:
    """The first multiple of ``every`` after ``k``."""
    return (k // every + 1) * every


def early_logs(every: int) -> list[int]:
    """The steps of the logs before the first interval, in order (integer halves, at least step 1)."""
    return sorted({every >> j for j in range(1, EARLY_LOGS + 1)} - {0})


def is_log(k: int, every: int) -> bool:
    """Whether a run logs after step k: every ``every`` steps, and before the first of those at every / 2,
    every / 4, ... (``EARLY_LOGS`` of them), so that the start of a run, where estimates move most, is seen on
    a log time axis too, while the logs at the regular interval stay the most."""
    return k % every == 0 or (0 < k < every and k in early_logs(every))


def next_log(k: int, every: int) -> int:
    """The first log step after step k (``is_log``)."""
    return next((step for step in early_logs(every) if step > k), None) or next_multiple(k, every)


@dataclass
class ErrorSums:
    """The sums of squares of the model error z (and of the measured output y), per member (B,), that a run
    accumulates, and the steps they cover. The engine adds every step's z^2 and y^2 into ``z`` and ``y``
    (``Graph.advance(accumulate=...)``) and the run counts those steps (``add``); a health check reads ``z``,
    ``y`` and ``check_steps`` and starts them again (``checked``); a log takes the rms of z since the previous
    log (``take_log``), which may span health checks: ``log_z`` holds its part before the last check, ``mark_z``
    the part of ``z`` that the previous log took.

    A checkpoint holds them as two tables (``state``, ``from_state``): ``sums`` and ``counters``, whose keys
    ``acc``, ``log`` and ``mark`` are ``check_steps``, ``log_steps`` and ``mark_steps``.
    """

    z: torch.Tensor           # z^2 summed since the last health check, over check_steps steps
    y: torch.Tensor           # y^2 likewise
    log_z: torch.Tensor       # z^2 summed from the last log to the last health check, over log_steps steps
    mark_z: torch.Tensor      # the part of z the last log took (since the last check), over mark_steps steps
    z_rms_last: torch.Tensor  # the rms of z over the last log's interval (NaN before the first log)
    check_steps: int = 0
    log_steps: int = 0
    mark_steps: int = 0

    TENSORS: ClassVar[tuple[str, ...]] = ("z", "y", "log_z", "mark_z", "z_rms_last")
    COUNTERS: ClassVar[dict[str, str]] = {"acc": "check_steps", "log": "log_steps", "mark": "mark_steps"}

    @classmethod
    def zeros(cls, batch: int, device: torch.device) -> ErrorSums:
        """Empty sums of ``batch`` members (``z_rms_last`` NaN)."""
        z = {k: torch.zeros(batch, dtype=torch.float64, device=device) for k in cls.TENSORS}
        z["z_rms_last"].fill_(math.nan)
        return cls(**z)

    def add(self, steps: int) -> None:
        """Count ``steps`` more steps summed into ``z`` and ``y``."""
        self.check_steps += steps

    def checked(self) -> None:
        """After a health check read ``z``, ``y`` and ``check_steps``: what no log has taken moves to ``log_z``,
        and the check's sums start again."""
        self.log_z += self.z - self.mark_z
        self.log_steps += self.check_steps - self.mark_steps
        for t in (self.z, self.y, self.mark_z):
            t.zero_()
        self.check_steps = self.mark_steps = 0

    def pending_log(self) -> int:
        """The steps no log has taken."""
        return self.log_steps + self.check_steps - self.mark_steps

    def take_log(self) -> torch.Tensor:
        """The rms of z over the steps since the last log (B,), kept as ``z_rms_last``; the next log starts here."""
        z_rms = torch.sqrt((self.log_z + self.z - self.mark_z) / max(self.pending_log(), 1))
        self.log_z.zero_()
        self.mark_z.copy_(self.z)
        self.log_steps, self.mark_steps = 0, self.check_steps
        self.z_rms_last.copy_(z_rms)
        return z_rms

    def state(self) -> tuple[dict[str, torch.Tensor], dict[str, int]]:
        """The checkpoint's ``sums`` (on the CPU) and ``counters``."""
        return ({k: getattr(self, k).cpu() for k in self.TENSORS},
                {key: getattr(self, name) for key, name in self.COUNTERS.items()})

    @classmethod
    def from_state(cls, sums: dict[str, torch.Tensor], counters: dict[str, int], device: torch.device) -> ErrorSums:
        """The sums a checkpoint's ``sums`` and ``counters`` hold, on ``device``."""
        return cls(**{k: sums[k].to(device) for k in cls.TENSORS},
                   **{name: int(counters[key]) for key, name in cls.COUNTERS.items()})
