"""Values derived from tensors, kept until the tensors change: how the library caches what it derives from them.

A block often needs something computed from its buffers that stays the same for many steps (beta reversed
in time, lambda as a float when it is 1, C x for every output port, the samples of a noise chunk, a graph's
plan). ``derived(owner, name, deps, make)`` keeps ``make()`` on ``owner`` and makes it again only
when a dependency changed: a tensor replaced by another or modified in place (its identity and PyTorch's
version counter, which every in-place operation and the native engine's writes advance: ``kernels.bump``),
any other value when it is no longer equal. Keys hold their tensors, so an identity is never reused while it
is cached.

The native engine keeps two things on the same terms, each in one place that owns it:

* a graph's lowered program, ``rcotorch.engine.lowering.ProgramCache`` (``Graph._program_cache``): it holds the
  ``key`` of every parameter buffer the program was made with and checks it before each call of the engine,
  without walking the modules again; ``lowering.refilled`` moves the key on after a change that the program
  already reads, ``lowering.invalidate`` drops the program;
* the estimator's copy of beta that its program reads, ``rcotorch.estimator.rco.NativeCopy``
  (``RCOEstimator._native_copy``): valid while beta is the same tensor, and refilled in place with it
  (``set_markov``, ``_refill_from_system``) rather than made again, so that the program made with it runs on.

docs/architecture.md ("How a parameter flows from the estimator to the C program") follows a parameter through
them.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

import torch

_SLOT = "_memo"


def key(deps: Iterable) -> tuple:
    """What ``deps`` stand for now: each tensor with its version counter, each other value itself."""
    return tuple((d, d._version) if isinstance(d, torch.Tensor) else (None, d) for d in deps)


def _same(a: tuple, b: tuple) -> bool:
    if len(a) != len(b):
        return False
    for (ta, va), (tb, vb) in zip(a, b):
        if ta is not None or tb is not None:
            if ta is not tb or va != vb:
                return False
        elif va != vb:
            return False
    return True


def derived(owner: Any, name: str, deps: Iterable, make: Callable[[], Any]) -> Any:
    """``make()``, cached on ``owner`` under ``name`` until one of ``deps`` changes."""
    store = owner.__dict__.setdefault(_SLOT, {})
    now = key(deps)
    hit = store.get(name)
    if hit is not None and _same(hit[0], now):
        return hit[1]
    value = make()
    store[name] = (now, value)
    return value


def remember(owner: Any, name: str, deps: Iterable, value: Any) -> None:
    """Store ``value`` as what ``derived`` would make for ``deps`` now (when the caller already knows it)."""
    owner.__dict__.setdefault(_SLOT, {})[name] = (key(deps), value)


def forget(owner: Any) -> None:
    """Drop everything cached on ``owner`` (e.g. after its state was loaded)."""
    owner.__dict__.pop(_SLOT, None)
