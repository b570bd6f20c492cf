"""Copies of a graph stepped inside it: a copy that differs from the graph in a few blocks (an estimator holding
other parameters, the model it feeds back through, a physics in place of the physical system) needs of its own
only the blocks that differ and those its recorded signals depend on through them; every other signal it reads
from the graph's blocks, which compute the same numbers. The intervals' replay steps its copies so
(``rcotorch.verdict.intervals``), and validation its initial model beside the refined one
(``rcotorch.verdict.validation``)."""

from __future__ import annotations

import copy
from collections.abc import Callable, Mapping
from typing import Any

import torch


def own_blocks(structure: tuple[list, Mapping], changed: set[str], signals: list) -> set[str]:
    """The blocks a copy whose blocks ``changed`` differ from the graph's (``structure``: its block names and
    wiring) needs of its own for its ``signals``: those ``changed`` drives (through any input) of those the
    signals' blocks read (through any input)."""
    _, sources = structure
    readers: dict[str, set[str]] = {}
    feeders: dict[str, set[str]] = {}
    for (dst, _), (src, _) in sources.items():
        readers.setdefault(src, set()).add(dst)
        feeders.setdefault(dst, set()).add(src)

    def closure(start: set[str], step: dict[str, set[str]]) -> set[str]:
        out, todo = set(start), list(start)
        while todo:
            for nxt in step.get(todo.pop(), ()):
                if nxt not in out:
                    out.add(nxt)
                    todo.append(nxt)
        return out
    return closure(changed, readers) & closure({sig[0] for sig in signals}, feeders)


def hooks_leave(hooks: list, own: set[str], est_name: str) -> bool:
    """Whether every step hook promises to leave the blocks ``own`` alone (``Graph.add_hook``: its ``acts_on``),
    the estimator excepted where the hook keeps theta (``keeps_theta``): every copy holds theta, so that what
    such a hook changes in an estimator does not change what the copy puts out. Only then may the copies run
    inside one graph, where the hooks act on the base copy's blocks alone."""
    for hook in hooks:
        acts = getattr(hook, "acts_on", None)
        if acts is None:
            return False
        mine = own - {est_name} if getattr(hook, "keeps_theta", False) else own
        if set(acts) & mine:
            return False
    return True


def join(base, structure: tuple[list, Mapping], own: set[str], signals: list, tag: str,
          block: Callable[[str], Any]) -> dict:
    """Add to ``base`` (a frozen copy not yet stepped; ``structure``: its block names and wiring before any copy
    joined it) the blocks ``own`` of a copy of it (``own_blocks``; ``block(name)``: that copy's block ``name``,
    in the state base's has), renamed '<name>__<tag>' (or with more underscores where base has that name). They
    read every other signal from base's blocks, which compute the same numbers. Returns {signal of the copy: the
    signal of base that carries it}."""
    names, sources = structure
    rename = {}
    for name in own:                       # a name no block of base has (more underscores where one had it)
        new = f"{name}__{tag}"
        while new in base.blocks or new in rename.values():
            new = f"{name}_{new[len(name):]}"
        rename[name] = new
    blocks = []
    for name in [name for name in names if name in own]:                  # in the graph's order
        blk = block(name)
        blk.name = rename[name]
        blocks.append(blk)
    wiring = {(rename[dst], p): (rename.get(src, src), q) for (dst, p), (src, q) in sources.items() if dst in own}
    base.extend(blocks, wiring)
    return {sig: (rename.get(sig[0], sig[0]), sig[1]) for sig in signals}


def held_block(base, est_name: str, eta: torch.Tensor, name: str):
    """A copy of ``base``'s block ``name``, the estimator holding theta at ``eta``."""
    blk = copy.deepcopy(base.blocks[name])
    if name == est_name:
        blk.hold(eta)
    return blk
