"""The native engine's instruction records (csrc/engine.h): declared once, encoded by name by Builder.emit.

Independent reference for the encoding: the order in which the engine's header documents each record, written
out by hand here (a block of a user's may still give its record so); a record given by name must encode to the
same integers and run to the same numbers as the PyTorch engine."""

import pytest
import torch

import rcotorch as rt
from rcotorch.engine import kernels, lowering
from rcotorch.errors import ConfigError

pytestmark = pytest.mark.skipif(not kernels.available(), reason=f"no native engine: {kernels.why_unavailable()}")


class _Difference(rt.Block):
    """y = a - b, lowered to one SUM instruction written as ``emit`` receives it."""

    def __init__(self, emit):
        super().__init__("diff", {"a": 2, "b": 2}, {"y": 2})
        self.emit = emit

    def output(self, port, inputs):
        return inputs["a"] - inputs["b"]

    def lower(self, b):
        self.emit(b)


def _graph(emit):
    g = rt.Graph([rt.WhiteNoise(2, seed=1, name="a"), rt.WhiteNoise(2, seed=2, name="b"),
                  _Difference(emit)], [("a.out", "diff.a"), ("b.out", "diff.b")], batch_size=3)
    g.engine = "native"
    return g


def _named(b):
    b.emit("SUM", port="y", WIDTH=2, OUT=b.output("y"), terms=[dict(IN=b.input("a"), SIGN=1),
                                                               dict(IN=b.input("b"), SIGN=-1)])


def _encoded(b):   # width, number of inputs, out, then [in, sign] per input
    b.emit("SUM", [2, 2, b.output("y"), b.input("a"), 1, b.input("b"), -1], port="y")


def test_a_record_given_by_name_encodes_in_the_declared_order_and_runs_as_pytorch():
    named, encoded = lowering.program(_graph(_named)), lowering.program(_graph(_encoded))
    assert torch.equal(named.code, encoded.code)
    g = _graph(_named)
    y = g.run(50, record={"y": "diff.y"})["y"]
    assert g.ran_engine == "native"
    ref = _graph(_named)
    ref.engine = "torch"
    assert torch.allclose(y, ref.run(50, record={"y": "diff.y"})["y"], rtol=1e-12, atol=1e-14)


def test_every_table_is_counted_by_a_field_of_its_record():
    assert set(kernels.OP) == set(kernels.OP_LAYOUT)
    for layout, tables in kernels.TABLES.items():
        for _table, count, entry in tables:
            assert count in kernels.LAYOUT[layout] and entry in kernels.LAYOUT
    assert kernels.LAYOUT["GAIN"] == ("ROWS", "COLS", "K", "IN", "OUT", "SHARED")


@pytest.mark.parametrize("emit, says", [
    (lambda b: b.emit("SUM", port="y", WIDTH=2, terms=[]), "missing OUT"),
    (lambda b: b.emit("SUM", port="y", WIDTH=2, OUT=b.output("y")), "missing terms"),
    (lambda b: b.emit("SUM", port="y", WIDTH=2, OUT=b.output("y"), ROWS=1, terms=[]), "unknown ROWS"),
    (lambda b: b.emit("SUM", port="y", WIDTH=2, NIN=3, OUT=b.output("y"), terms=[dict(IN=0, SIGN=1)]),
     "NIN = 3, but the table terms has 1 entries"),
    (lambda b: b.emit("SUM", port="y", WIDTH=2, OUT=b.output("y"), terms=[dict(IN=0)]), "missing SIGN"),
    (lambda b: b.emit("SUM", [2, 2, b.output("y"), 0, 1], port="y"), "too few"),
    (lambda b: b.emit("GAIN", [1, 1, 0, 0, 0, 1, 7], port="y"), "7 ints, but the fields of GAIN"),
    (lambda b: b.emit("SUMS", port="y"), "no such op"),
])
def test_a_record_with_a_missing_or_unknown_field_is_refused_naming_the_block_and_the_instruction(emit, says):
    with pytest.raises(ConfigError, match="block 'diff'") as err:
        lowering.program(_graph(emit))
    assert says in str(err.value)



def test_the_binding_modes_are_the_bits_engine_h_declares():
    from rcotorch.engine import _engine
    mode = kernels.BindMode
    load, store, first_lane = _engine.BIND_LOAD, _engine.BIND_STORE, _engine.BIND_FIRST_LANE
    assert (mode.LOAD, mode.STORE, mode.LOAD_AND_STORE, mode.LOAD_FIRST_LANE) == \
        (load, store, load | store, load | first_lane)
    binds = lowering.program(_graph(_named)).binds
    assert {bd.mode for bd in binds if bd.what.startswith("signal")} == {mode.STORE}        # written back only
    assert {bd.mode for bd in binds if bd.what.endswith("parameter")} == {mode.LOAD}        # read only
