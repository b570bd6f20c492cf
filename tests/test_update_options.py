"""The estimator's update settings as one record, ``rt.UpdateOptions``: the keywords and the record make the same
estimator, the estimator keeps the record as ``options``, and a setting given both ways is refused."""

import dataclasses

import pytest
import torch

import rcotorch as rt

SETTINGS = dict(p0=[1e2, 1e3], lam=0.99, R=2.0, theta_bounds=(-5.0, 5.0), r_delta=0.1, normalize=3.0, p_max=1e4)


def test_the_record_and_the_keywords_make_the_same_estimator():
    by_keywords = rt.RCOEstimator({"y0": 1}, nc=2, **SETTINGS)
    by_record = rt.RCOEstimator({"y0": 1}, nc=2, options=rt.UpdateOptions(**SETTINGS))
    a, b = by_keywords.state_dict(), by_record.state_dict()
    assert list(a) == list(b) and all(torch.equal(a[k], b[k]) for k in a)
    assert by_keywords.options == by_record.options == rt.UpdateOptions(**SETTINGS)
    assert torch.equal(by_record.r_weight, 2.0 * torch.eye(1, dtype=torch.float64))


def test_the_defaults_are_the_constructors_and_a_record_is_frozen():
    est = rt.RCOEstimator.static_gain({"y0": 1})
    assert est.options == rt.UpdateOptions()
    with pytest.raises(dataclasses.FrozenInstanceError):
        est.options.lam = 0.5
    other = rt.RCOEstimator.static_gain({"y0": 1}, options=dataclasses.replace(est.options, lam=0.9))
    assert float(other.lam) == 0.9 and est.options.lam == 1.0


def test_set_options_replaces_them_in_the_record_too():
    est = rt.RCOEstimator.static_gain({"y0": 1}, options=rt.UpdateOptions(p0=10.0))
    first = est.options
    est.set_options(normalize=0.5)
    assert est.options == rt.UpdateOptions(p0=10.0, normalize=0.5) and first.normalize is None


def test_a_setting_given_as_a_keyword_and_in_the_record_is_refused():
    with pytest.raises(rt.ConfigError, match="lam, p_max given both as keywords and in options="):
        rt.RCOEstimator({"y0": 1}, lam=0.9, p_max=5.0, options=rt.UpdateOptions(p0=3.0))
    with pytest.raises(rt.ConfigError, match="options must be an UpdateOptions"):
        rt.RCOEstimator({"y0": 1}, options={"p0": 3.0})


def test_the_records_values_are_checked_as_the_keywords_are():
    with pytest.raises(rt.ConfigError, match="lam must lie in"):
        rt.RCOEstimator({"y0": 1}, options=rt.UpdateOptions(lam=1.5))
    with pytest.raises(rt.DimensionError, match="R has shape"):
        rt.RCOEstimator({"y0": 1}, options=rt.UpdateOptions(R=[[1.0, 0.0], [0.0, 1.0]]))
