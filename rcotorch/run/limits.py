"""What a run may ask for: a dtype of ``DTYPES``, a device torch has, positive counts, at most ``MAX_STEPS``
steps, and no more memory than the machine has available (``check_memory``, before anything is allocated)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import torch

from ..errors import ConfigError, SettingError
from ..system import available_memory

if TYPE_CHECKING:
    from .scenario import Scenario

# The dtypes a run takes, by name.
DTYPES = {"float64": torch.float64, "float32": torch.float32}
# A member-step of the native engine takes at least ENGINE_NS nanoseconds (docs/cli.md).
ENGINE_NS = 30.0
# The most steps a run may take: its step counters are 64-bit integers, but the bound is time: at the engine's
# fastest (ENGINE_NS a member-step) 10^12 steps of one member already take more than 8 hours.
MAX_STEPS = 10 ** 12
# The least memory a run holds while it steps (``memory_needed``), measured on sdof-stiffness: the known model's
# Markov parameters are made one small tensor a sample, about MARKOV_SAMPLE_BYTES each until they are stacked
# (``derive_markov`` examines max(4 nu, 64) + nu samples); the estimator's window and Markov filter hold about
# STATE_NUMBERS numbers per member and Markov parameter; every member about MEMBER_BYTES more (its RLS state,
# sums and health statistics). The intervals' and validation's replays at the end of a run need more.
MARKOV_SAMPLE_BYTES, STATE_NUMBERS, MEMBER_BYTES = 600, 5, 1500


def run_device(name: str) -> torch.device:
    """The device ``--device NAME`` names, where rcotorch runs and this machine has it."""
    hint = "valid devices: cpu, cuda, cuda:N"
    try:
        dev = torch.device(name)
    except (RuntimeError, TypeError):
        raise ConfigError(f"--device {name!r} is not a device; {hint}") from None
    if dev.type not in ("cpu", "cuda"):
        raise ConfigError(f"--device {name!r}: rcotorch runs on cpu or cuda; {hint}")
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ConfigError(f"--device {name} asked for, but torch sees no CUDA device on this machine")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ConfigError(f"--device {name}: this machine has {torch.cuda.device_count()} CUDA device(s)")
    return dev


def positive_int(value, what: str) -> int:
    """``value``, a positive integer (``ConfigError`` naming ``what`` otherwise)."""
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ConfigError(f"{what} must be a positive integer, got {value!r}")
    return value


def steps_bound_reason() -> str:
    """Why a run takes at most MAX_STEPS steps."""
    hours = MAX_STEPS * ENGINE_NS * 1e-9 / 3600
    return f"at the engine's fastest, about {ENGINE_NS:g} ns a member-step, that many take more than {int(hours)} hours"


def bounded_steps(value, what: str) -> int:
    """A number of steps: a positive integer, at most MAX_STEPS."""
    positive_int(value, what)
    if value > MAX_STEPS:
        raise ConfigError(f"{what} must be at most {MAX_STEPS}, got {value}: {steps_bound_reason()}")
    return value


def memory_needed(scenario: Scenario, settings: Mapping[str, Any], batch: int, dtype: str
                  ) -> list[tuple[str, int]]:
    """What a run of ``settings`` holds at least while it steps, in bytes, part by part (its constants above):
    the known model's Markov parameters and the estimator's window where the scenario has the setting ``nu``,
    and the members' state."""
    parts = []
    nu = _nu(scenario, settings)
    if nu is not None:
        samples = max(4 * nu, 64) + nu
        parts.append((f"the known model's {samples} Markov parameters", samples * MARKOV_SAMPLE_BYTES))
        parts.append((f"the estimator's window of {nu} steps", batch * nu * STATE_NUMBERS * DTYPES[dtype].itemsize))
    parts.append((f"{batch} member{'s' * (batch != 1)}' state", batch * MEMBER_BYTES))
    return parts


def _nu(scenario: Scenario, settings: Mapping[str, Any]) -> int | None:
    """The run's number of Markov parameters (the setting ``nu``, the largest of per-member ones), or None."""
    nu = settings.get("nu") if "nu" in scenario.settings else None
    nu = max(nu) if isinstance(nu, list) and nu else nu
    return nu if isinstance(nu, int) and not isinstance(nu, bool) and nu > 0 else None


def _size(n: float) -> str:
    """Bytes in GB or MB, for a message."""
    return f"{n / 1e9:.1f} GB" if n >= 1e8 else f"{n / 1e6:.0f} MB"


def check_memory(scenario: Scenario, settings: Mapping[str, Any], batch: int, dtype: str) -> None:
    """Refuse (``SettingError`` naming nu and the batch) a run whose ``memory_needed`` exceeds the
    ``available_memory``, before anything is allocated."""
    parts = memory_needed(scenario, settings, batch, dtype)
    needed = sum(n for _, n in parts)
    found = available_memory()
    if found is None or needed <= found[0]:
        return
    nu = _nu(scenario, settings)
    drivers, smaller = (f"batch {batch}", "batch") if nu is None else (f"nu = {nu} and batch {batch}", "nu or batch")
    what = "; ".join(f"{name} {_size(n)}" for name, n in parts if n >= needed / 100)
    raise SettingError(f"scenario '{scenario.name}' with {drivers} needs at least {_size(needed)} of memory while "
                       f"it steps ({what}), but {_size(found[0])} is available ({found[1]}); choose a smaller "
                       f"{smaller}", settings=("batch",) if nu is None else ("nu", "batch"))
