"""Values derived from tensors, kept until the tensors change: the one cache mechanism of the library.

A block often needs something computed from its buffers that stays the same for many steps (beta reversed
in time, lambda as a float when it is 1, C x for every output port, the samples of a noise chunk, a graph's
lowered program). ``derived(owner, name, deps, make)`` keeps ``make()`` on ``owner`` and makes it again only
when a dependency changed: a tensor replaced by another or modified in place (its identity and PyTorch's
version counter, which every in-place operation and the native engine's writes advance), any other value
when it is no longer equal. Keys hold their tensors, so an identity is never reused while it is cached.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

import torch

_SLOT = "_memo"


def _key(deps: Iterable) -> tuple:
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
    key = _key(deps)
    hit = store.get(name)
    if hit is not None and _same(hit[0], key):
        return hit[1]
    value = make()
    store[name] = (key, value)
    return value


def remember(owner: Any, name: str, deps: Iterable, value: Any) -> None:
    """Store ``value`` as what ``derived`` would make for ``deps`` now (when the caller already knows it)."""
    owner.__dict__.setdefault(_SLOT, {})[name] = (_key(deps), value)


def forget(owner: Any) -> None:
    """Drop everything cached on ``owner`` (e.g. after its state was loaded)."""
    owner.__dict__.pop(_SLOT, None)
