"""Checkpoints and what a resume checks: the checkpoint's file and format (``read_checkpoint``), that the caller
asks for the checkpoint's own run (``check_resume``), and that its contents have the layout of a fresh run of
its scenario (``same_layout``; ``what_failed`` words what did not fit). ``rcotorch.run.runner.Run`` saves
checkpoints and rebuilds a run from one (``Run.save``, ``Run.resume``)."""

from __future__ import annotations

import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from ..errors import CheckpointError
from . import scenario as scenarios
from .outputs import OutputFolder, load_checkpoint

CHECKPOINT = "checkpoint.pt"
CHECKPOINT_FORMAT = 4   # the layout of checkpoint.pt (4: the graph's state at the window's start, for intervals)
# What ``--resume`` accepts besides the checkpoint's own settings (anything else must match the checkpoint).
RESUME_CHANGEABLE = ("--steps", "--device", "--out", "--overwrite", "--checkpoint-every", "--threads", "--engine",
                     "--quiet", "--no-figures")


def read_checkpoint(directory: Path) -> tuple[Path, dict[str, Any]]:
    """The checkpoint of the run in ``directory``: its path and its state. Refused (``CheckpointError``) where
    the folder or its checkpoint is missing, another process writes the run, or the checkpoint is of another
    format (another version of rcotorch)."""
    if not directory.is_dir():
        raise CheckpointError(f"--resume {directory}: no such folder")
    OutputFolder(directory, "run").check_free()      # not while another process writes the run
    path = directory / CHECKPOINT
    if not path.is_file():
        raise CheckpointError(f"--resume {directory}: no {CHECKPOINT} there")
    state = load_checkpoint(path)
    version = state.get("format") if isinstance(state, dict) else None
    if version != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{path}: written by another version of rcotorch (format {version})")
    return path, state


def check_resume(path: Path, state: Mapping[str, Any], expect: Mapping[str, Any]) -> None:
    """Refuse a resume that asks for another scenario, batch, seed, dtype or setting than the checkpoint's."""
    changeable = f"a resume keeps the run's settings; it accepts {', '.join(RESUME_CHANGEABLE)}"
    given = {"name": state["scenario"], "batch": state["batch"], "dtype": state["dtype"],
             "seed": state["settings"].get("seed")}
    for key, have in given.items():
        want = expect.get(key)
        if want is not None and want != have:
            flag = "scenario" if key == "name" else f"--{key}"
            raise CheckpointError(f"--resume {path.parent}: the checkpoint's run has {flag} {have!r}, not "
                                  f"{want!r}; {changeable}")
    overrides = dict(expect.get("overrides") or {})
    if overrides:
        resolved = scenarios.get(state["scenario"]).resolve(overrides)
        for key in overrides:
            if resolved[key] != state["settings"].get(key):
                raise CheckpointError(f"--resume {path.parent}: --set {key}={overrides[key]} differs from the "
                                      f"checkpoint's {key} = {state['settings'].get(key)!r}; {changeable}")


def same_layout(what: str, got: Any, want: Mapping[str, Any], shapes: bool = True) -> None:
    """Raise ValueError unless a checkpoint's ``got`` has the entries of ``want`` (a fresh run's) and, with
    ``shapes``, each tensor of ``want``'s shape."""
    if not isinstance(got, Mapping):
        raise ValueError(f"{what}: a {type(got).__name__}, not a table")
    missing, unknown = sorted(map(str, set(want) - set(got))), sorted(map(str, set(got) - set(want)))
    if missing or unknown:
        raise ValueError(f"{what}: " + "; ".join([f"missing {', '.join(missing[:3])}"] * bool(missing)
                                                  + [f"unknown {', '.join(unknown[:3])}"] * bool(unknown)))
    for key, v in want.items() if shapes else ():
        if isinstance(v, torch.Tensor) and (not isinstance(got[key], torch.Tensor) or got[key].shape != v.shape):
            shape = tuple(got[key].shape) if isinstance(got[key], torch.Tensor) else type(got[key]).__name__
            raise ValueError(f"{what}: {key} has shape {shape}, not {tuple(v.shape)}")


def what_failed(e: BaseException) -> str:
    """A short, one-line account of an error met reading a checkpoint's contents."""
    if isinstance(e, KeyError):
        return f"missing {e.args[0]!r}" if e.args else "an entry is missing"
    text = " ".join(str(e).split()).rstrip(".") or type(e).__name__
    text = re.sub(r"^Error\(s\) in loading state_dict for \w+: ", "graph: ", text)    # torch's load_state_dict
    return text if len(text) <= 200 else text[:197] + "..."


def member_settings(settings: Mapping[str, Any], batch: int) -> list[dict[str, Any]] | None:
    """Per-member settings of a resolved batch (the inverse of ``Scenario.resolve_members``)."""
    varying = {k: v for k, v in settings.items() if isinstance(v, list)}
    if not varying:
        return None
    return [{k: v[b] for k, v in varying.items()} for b in range(batch)]
