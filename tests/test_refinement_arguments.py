"""``rt.refinement`` changes none of its arguments but the estimator, which the graph runs: a data block with gaps
in its input keeps its own hold-off while the graph plays a copy with the derived one, sharing the recording;
the error for a physical system given twice or not at all names what was given."""

import numpy as np
import pytest
import torch

import rcotorch as rt

TS = 0.01


def _known():
    G = rt.models.sdof(m=1.0, c=0.8, k=0.6, measured=["velocity"], sees=["position"])
    return rt.LTI.from_control(G, inputs=["w", "u"], outputs=["y", "y0"], dt=TS, name="known")


def _data(gap=slice(100, 105), steps=400, **kw):
    rng = np.random.default_rng(0)
    values = rng.normal(size=(steps, 2))
    valid = np.ones_like(values, dtype=bool)
    values[gap, 0], valid[gap, 0] = np.nan, False
    return rt.Recorded(rt.Recording(values, ["w", "y"], TS, valid=valid), {"w": "w", "y": "y"}, **kw)


def test_the_data_block_given_keeps_its_holdoff_and_the_graph_plays_a_copy_with_the_derived_one():
    data = _data()
    mask = data.valid_mask.clone()
    ident = rt.RCOEstimator.static_gain({"y0": 1}, p0=1e2)
    g = rt.refinement(_known(), ident, data=data, nu=8)
    assert data.holdoff == {} and torch.equal(data.valid_mask, mask)       # the caller's block as given
    played = g.blocks["data"]
    assert played is not data and played.name == "data"
    n = rt.wiring.holdoff_samples(_known(), ident)
    assert played.holdoff == {"w": n} and played.valid_mask[0, 100:105 + n, 0].sum() == 0
    assert played.valid_mask[0, :100, 0].all()
    assert played.values is data.values                                  # the recording is not copied
    g.run(200)
    assert int(played.k) == 200 and int(data.k) == 0                     # the copy steps, the block given not
    assert data.holdoff == {} and torch.equal(data.valid_mask, mask)


def test_a_second_refinement_of_the_same_data_derives_its_own_holdoff():
    data = _data()
    first = rt.refinement(_known(), rt.RCOEstimator.static_gain({"y0": 1}), data=data, nu=8, input_holdoff=3)
    second = rt.refinement(_known(), rt.RCOEstimator.static_gain({"y0": 1}), data=data, nu=8)
    assert first.blocks["data"].holdoff == {"w": 3}
    assert second.blocks["data"].holdoff["w"] > 3 and data.holdoff == {}


def test_data_whose_holdoff_is_set_or_without_gaps_enter_as_they_are():
    for data in (_data(holdoff={"w": 4}), _data(gap=slice(0, 0))):
        g = rt.refinement(_known(), rt.RCOEstimator.static_gain({"y0": 1}), data=data, nu=8)
        assert g.blocks["data"] is data


def test_the_estimator_given_is_the_graphs_with_the_derived_markov_parameters():
    ident = rt.RCOEstimator.static_gain({"y0": 1})
    g = rt.refinement(_known(), ident, data=_data(), nu=8)
    assert g.role("estimator") is ident and tuple(ident.beta.shape[1:]) == (8, 1, 1)
    assert ident.sample_time == TS


@pytest.mark.parametrize("given, named", [({}, "got none of them"),
                                          ({"truth": True, "data": True}, "got truth= and data="),
                                          ({"truth": True, "physical": True, "data": True},
                                           "got truth= and physical= and data=")])
def test_the_physical_system_given_twice_or_not_at_all_is_named(given, named):
    blocks = {"truth": rt.Gain([[1.0]], name="delta"), "data": _data(),
              "physical": rt.LTI([[0.5]], [[1.0]], [[1.0]], [[0.0]], inputs=["w"], outputs=["y"], dt=TS)}
    with pytest.raises(rt.ConfigError, match=f"exactly one of truth=, physical= or data=.*{named}"):
        rt.refinement(_known(), rt.RCOEstimator.static_gain({"y0": 1}), nu=8,
                      **{k: blocks[k] for k in given})
