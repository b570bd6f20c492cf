"""Faults of the Python API refused with a library error that names the block, port, argument or estimate at
fault: a user's function that raises (a StaticMap's on both engines, an estimate function of ``rt.refine``), a
StaticMap that mixes the members of a batch, non-finite or out-of-range settings of the estimator, the noise
source and the LTI block, and a negative step count."""

import math

import numpy as np
import pytest
import torch

import rcotorch as rt


def _known():
    G = rt.models.sdof(m=1.0, c=5.0, k=30.0, measured=["velocity"], sees=["velocity"])
    return rt.LTI.from_control(G, inputs=["w", "u"], outputs=["y", "y0"], dt=0.1, name="known")


def _refinement(batch=2):
    truth = rt.LTI([[0.5]], [[1.0]], [[0.2]], [[0.1]], ["in"], ["out"], 0.1, name="delta")
    return rt.refinement(_known(), rt.RCOEstimator({"y0": 1}, nc=2, p0=1e4), truth=truth,
                         excitation=rt.WhiteNoise(1, seed=list(range(1, batch + 1))), nu=10, batch_size=batch)


def _limited(v):
    if np.any(np.abs(v) > 1e6):
        raise ValueError("input beyond 1e6")
    return 2.0 * v


def _driven(fn, engine):
    g = rt.Graph([rt.WhiteNoise(1, std=1e7, seed=3, name="src"), rt.StaticMap(fn, 1, name="limiter")],
                 [("src.out", "limiter.in")], batch_size=2)
    g.engine = engine
    return g


# --- a StaticMap whose function raises ----------------------------------------------------------------------
def test_a_static_map_whose_function_raises_when_built_is_a_config_error_naming_the_block():
    def broken(x):
        raise ValueError("no table loaded")

    with pytest.raises(rt.ConfigError, match=r"block 'friction': fn failed on an input \(1, 1\): "
                                             r"ValueError\('no table loaded'\)"):
        rt.StaticMap(broken, 1, name="friction")


def test_a_static_map_whose_function_raises_during_a_run_on_pytorch_names_the_block():
    g = _driven(_limited, "torch")
    with pytest.raises(rt.ConfigError, match=r"block 'limiter': fn raised ValueError: input beyond 1e6 on an "
                                             r"input \(2, 1\)") as info:
        g.run(3)
    assert isinstance(info.value.__cause__, ValueError)


def test_a_static_map_whose_compiled_function_raises_in_the_native_engine_names_the_block(capfd):
    pytest.importorskip("numba")
    g = _driven(_limited, "auto")
    assert g.native_status() is None                   # the probes stay below 1e6: it compiles
    with pytest.raises(rt.ConfigError, match=r"block 'limiter': its function _limited raised ValueError: input "
                                             r"beyond 1e6 in the native engine \(steps 0 to 3\)"):
        g.run(3)
    assert "Exception ignored" not in capfd.readouterr().err


def test_a_static_map_whose_function_raises_on_the_compile_check_runs_on_pytorch_and_then_names_the_block():
    pytest.importorskip("numba")

    def small_only(v):
        if np.any(np.abs(v) > 100.0):
            raise ValueError("input beyond 100")
        return 2.0 * v

    g = _driven(small_only, "auto")
    why = g.native_status()
    assert "block 'limiter' (StaticMap)" in why and "the function itself raised ValueError" in why, why
    with pytest.raises(rt.ConfigError, match=r"block 'limiter': fn raised ValueError: input beyond 100"):
        g.run(3)


# --- an estimate function of rt.refine that raises -------------------------------------------------------------
def test_an_estimate_function_that_raises_is_a_config_error_naming_its_key(tmp_path):
    def dk(g):
        raise ValueError("no such gain")

    with pytest.raises(rt.ConfigError, match=r"refine: estimate 'dK': its function raised ValueError: "
                                             r"no such gain") as info:
        rt.refine(_refinement(), 20, {"dK": dk}, out=tmp_path / "run", figures=False, intervals=False,
                  validation=False, progress=False)
    assert isinstance(info.value.__cause__, ValueError)


def test_an_estimate_function_that_raises_during_the_run_is_a_config_error_naming_its_key(tmp_path):
    def dk(g):
        if int(g.k) > 0:
            raise ZeroDivisionError("division by zero")
        return torch.zeros(g.batch_size, dtype=torch.float64)

    with pytest.raises(rt.ConfigError, match=r"refine: estimate 'dK': its function raised ZeroDivisionError: "
                                             r"division by zero"):
        rt.refine(_refinement(), 50, {"dK": dk}, out=tmp_path / "run", figures=False, intervals=False,
                  validation=False, progress=False)


def test_a_metric_function_that_raises_is_a_config_error_naming_its_key(tmp_path):
    def broken(g):
        raise KeyError("gain")

    with pytest.raises(rt.ConfigError, match=r"refine: metric 'peak': its function raised KeyError: 'gain'"):
        rt.refine(_refinement(), 20, metrics={"peak": broken}, out=tmp_path / "run", figures=False,
                  intervals=False, validation=False, progress=False)


# --- a StaticMap that mixes the members of a batch -------------------------------------------------------------
@pytest.mark.parametrize("fn", [lambda x: x.mean(0, keepdim=True).expand_as(x), lambda x: x.cumsum(0),
                                lambda x: x.flip(0).cumsum(0).flip(0), lambda x: x - np.mean(x)],
                         ids=["batch mean", "running sum", "reversed running sum", "numpy mean of all"])
def test_a_static_map_that_mixes_the_members_of_a_batch_is_refused_naming_the_block(fn):
    with pytest.raises(rt.ConfigError, match=r"block 'average': fn must treat each member \(row of the batch\) "
                                             r"on its own: changing member 1's input moved member [02]'s output"):
        rt.StaticMap(fn, 1, name="average")


def test_a_static_map_of_rows_on_their_own_and_one_that_draws_noise_are_accepted():
    W = torch.tensor([[1.0, -2.0], [0.5, 3.0]], dtype=torch.float64)
    assert rt.StaticMap(lambda x: x @ W, 2, name="mix_columns").outputs == {"out": 2}
    assert rt.StaticMap(lambda x: np.sum(x ** 2, axis=1, keepdims=True), 3, name="energy").outputs == {"out": 1}
    # a function that is not reproducible cannot be probed for coupling: it is accepted as before
    assert rt.StaticMap(lambda x: x + torch.randn_like(x), 1, name="noisy").outputs == {"out": 1}


# --- non-finite and out-of-range settings ------------------------------------------------------------------------
@pytest.mark.parametrize("p0, shown", [(math.nan, "nan"), (math.inf, "inf"), (-1.0, "-1.0"),
                                       (torch.tensor([1e3, math.nan, 1e3]), r"nan \(member 1\)")])
def test_an_estimator_with_a_p0_that_is_not_finite_and_positive_is_refused_naming_it(p0, shown):
    with pytest.raises(rt.ConfigError, match=rf"block 'ident': p0 must be finite and positive, got {shown}"):
        rt.RCOEstimator({"y0": 1}, p0=p0, name="ident")


@pytest.mark.parametrize("lam, shown", [(math.nan, "nan"), (math.inf, "inf"), (0.0, "0.0"), (1.5, "1.5"),
                                        (torch.tensor([1.0, 0.99, math.nan]), r"nan \(member 2\)"),
                                        ([0.999, 1.01], r"1.01 \(member 1\)")])
def test_an_estimator_with_a_forgetting_factor_outside_0_1_is_refused_naming_it(lam, shown):
    with pytest.raises(rt.ConfigError, match=rf"block 'ident': lam must lie in \(0, 1\], got {shown}"):
        rt.RCOEstimator({"y0": 1}, lam=lam, name="ident")


def test_the_static_gain_estimator_checks_p0_and_lam_too():
    with pytest.raises(rt.ConfigError, match=r"block 'identified': lam must lie in \(0, 1\], got nan"):
        rt.RCOEstimator.static_gain({"y0": 1}, lam=math.nan)


@pytest.mark.parametrize("std, shown", [(math.nan, "nan"), (math.inf, "inf"), (-1.0, "-1.0"),
                                        ([1.0, math.nan], r"nan \(member 1\)")])
def test_white_noise_with_a_std_that_is_not_finite_and_non_negative_is_refused_naming_it(std, shown):
    with pytest.raises(rt.ConfigError, match=rf"block 'drive': std must be finite and non-negative, got {shown}"):
        rt.WhiteNoise(1, std=std, name="drive")


def test_white_noise_with_a_mean_that_is_not_finite_is_refused_naming_it():
    with pytest.raises(rt.ConfigError, match=r"block 'drive': mean must be finite, got inf"):
        rt.WhiteNoise(1, mean=math.inf, name="drive")


@pytest.mark.parametrize("which", ["A", "B", "C", "D"])
@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_an_lti_block_with_a_matrix_that_is_not_finite_is_refused_naming_the_matrix(which, bad):
    mats = {"A": [[0.5, 0.1], [0.0, 0.8]], "B": [[1.0], [0.0]], "C": [[0.0, 1.0]], "D": [[0.0]]}
    mats[which] = np.array(mats[which], dtype=float)
    mats[which][0, 0] = bad
    with pytest.raises(rt.ConfigError, match=rf"block 'plant': {which} must be finite; it has {bad} at "
                                             r"\(0, 0\)"):
        rt.LTI(*(mats[k] for k in "ABCD"), ["in"], ["out"], 0.1, name="plant")


def test_an_lti_block_with_one_members_matrix_not_finite_names_the_member():
    A = np.stack([np.eye(2) * 0.5, np.eye(2) * 0.5])
    A[1, 1, 0] = math.nan
    with pytest.raises(rt.ConfigError, match=r"block 'plant': A must be finite; it has nan at \(1, 0\) of "
                                             r"member 1"):
        rt.LTI(A, [[1.0], [0.0]], [[0.0, 1.0]], [[0.0]], ["in"], ["out"], 0.1, name="plant")


def test_a_continuous_lti_block_with_a_matrix_that_is_not_finite_is_refused_before_discretizing():
    with pytest.raises(rt.ConfigError, match=r"block 'plant': A \(continuous\) must be finite; it has nan"):
        rt.LTI.continuous([[0.0, 1.0], [math.nan, -1.0]], [[0.0], [1.0]], [[1.0, 0.0]], [[0.0]], ["in"], ["out"],
                          dt=0.1, name="plant")


def test_an_lti_block_with_a_sample_time_or_initial_state_that_is_not_finite_is_refused_naming_it():
    with pytest.raises(rt.ConfigError, match=r"block 'plant': dt must be a positive sample time, got nan"):
        rt.LTI([[0.5]], [[1.0]], [[1.0]], [[0.0]], ["in"], ["out"], math.nan, name="plant")
    with pytest.raises(rt.ConfigError, match=r"block 'plant': x0 must be finite; it has inf"):
        rt.LTI([[0.5]], [[1.0]], [[1.0]], [[0.0]], ["in"], ["out"], 0.1, x0=[math.inf], name="plant")


# --- step counts --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("steps", [-5, 2.5, "3"])
def test_advancing_a_graph_by_a_negative_or_non_integer_count_is_refused_naming_the_argument(steps):
    g = _refinement()
    with pytest.raises(ValueError, match=r"graph: steps must be a non-negative integer, got ") as info:
        g.advance(steps)
    assert isinstance(info.value, rt.ConfigError)
    with pytest.raises(rt.ConfigError, match=r"graph: steps must be a non-negative integer"):
        g.run(steps)
    assert int(g.k) == 0


def test_advancing_a_graph_by_zero_steps_or_a_numpy_integer_is_accepted():
    g = _refinement()
    g.advance(0)
    g.advance(np.int64(3))
    assert int(g.k) == 3


def test_two_random_sources_with_the_same_seed_warn_naming_both_blocks():
    """Excitation and noise built with one seed draw the same numbers (the noise is the excitation scaled,
    correlation 1); the graph says so when it is built. Distinct seeds, or the same seed for different members
    only, do not warn."""
    import warnings

    known = rt.LTI.continuous(*rt.models.sdof_matrices(1.0, 0.4, 4.0, measured=["position"], sees=["position"]),
                              inputs=["w", "u"], outputs={"y": 1, "y0": 1}, dt=0.05, name="known")

    def build(w_seed, v_seed, batch=2):
        ident = rt.RCOEstimator.static_gain({"y0": 1}, p0=1e3)
        return rt.refinement(known, ident, truth=rt.Gain(torch.tensor([[0.5]])), nu=10, batch_size=batch,
                             excitation=rt.WhiteNoise(1, seed=w_seed), noise=rt.WhiteNoise(1, std=0.01, seed=v_seed))
    with pytest.warns(UserWarning, match=r"blocks 'excitation' and 'noise' draw the same random stream \(seed 3 for "
                                         r"member 0 and others\)"):
        g = build(3, 3)
    g.run(20)
    assert torch.allclose(g.blocks["noise"].step()["out"], 0.01 * g.blocks["excitation"].step()["out"])
    with pytest.warns(UserWarning, match="seed 8 for member 1"):
        build([7, 8], [9, 8])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        build(3, 4)
        build([1, 2], [2, 1])                   # one member's excitation stream is the other's noise: independent
