"""Code made as text (rcotorch.engine.codegen): the package runs it in that one module only, and what it writes
computes the same in Python and compiled by numba."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import rcotorch
from rcotorch.engine import codegen

ROOT = Path(rcotorch.__file__).resolve().parent


def test_exec_and_eval_are_called_in_the_generator_module_only():
    found = []
    for path in ROOT.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in ("exec", "eval"):
                found.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert len(found) == 1 and found[0].startswith("engine/codegen.py:"), found


def _square_plus(i, x, c):
    return x[i] * x[i] + c


def test_tuple_map_builds_the_tuple_in_python_and_in_compiled_code():
    each = codegen.tuple_map(_square_plus, 3)
    assert each((1.0, 2.0, 3.0, 4.0), 0.5) == (1.5, 4.5, 9.5)
    assert codegen.tuple_map(_square_plus, 0)((1.0,), 0.5) == ()
    numba = pytest.importorskip("numba")
    jitted = numba.njit(codegen.tuple_map(numba.njit(_square_plus), 3))
    assert jitted((1.0, 2.0, 3.0, 4.0), 0.5) == (1.5, 4.5, 9.5)
