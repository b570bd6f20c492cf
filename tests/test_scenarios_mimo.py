"""Section V.B (2-DOF stiffness) and Section VI (series RLC): models against python-control / closed forms,
the 2-DOF discrete-interconnection truth within 1%, and both scenarios' requirements with their defaults."""

import contextlib
import importlib.util
from pathlib import Path

import control
import numpy as np
import pytest
import scipy.linalg
import scipy.signal
import torch

from rcotorch.models.circuits import series_rlc
from rcotorch.run.runner import Run


@contextlib.contextmanager
def one_thread():
    """Small tensors: one intra-op thread avoids oversubscription when the machine is busy."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(n)


def _module(stem):
    """A scenario file loaded as a module (for its model builders and formulas)."""
    path = Path(__file__).resolve().parents[1] / "scenarios" / f"{stem}.py"
    spec = importlib.util.spec_from_file_location(f"_test_scenario_{stem}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# --- series RLC model --------------------------------------------------------------------------------------
def test_series_rlc_matches_circuit_transfer_functions():
    R, L, C = 250.0, 55e-3, 23.5e-6
    G = series_rlc(R, L, C, measured=["v_R"], sees=["v_C", "charge", "current"])
    den = [L * C, R * C, 1.0]
    refs = [control.tf([R * C, 0.0], den), control.tf([1.0], den), control.tf([C], den), control.tf([C, 0.0], den)]
    s = 1j * np.array([10.0, 300.0, 900.0, 5e3, 1e5])
    H = np.asarray(G(s))                                      # (outputs, inputs, F)
    for row, ref in enumerate(refs):
        for col in range(2):                                  # u is a second source in series with w
            np.testing.assert_allclose(H[row, col], ref(s), rtol=1e-10)
    with pytest.raises(ValueError, match="unknown circuit signal"):
        series_rlc(R, L, C, measured=["v_L"])


@pytest.mark.parametrize("initial", [dict(L0_rel=0.3, C0_rel=-0.3), dict(L0_rel=-0.25, C0_rel=0.3, R0_rel=0.1)])
def test_rlc_gains_close_the_loop_to_the_true_circuit_and_back_out(initial):
    """Continuous known model + u = gC v_C + gR v_R + gw w (python-control feedback) has the true transfer
    function; with R0 = R the back-out formulas return L, C, R; with R0 != R they return the equivalent circuit
    (R0, R0 L / R, R C / R0) that has the same transfer function (R, L, 1/C are not jointly identifiable)."""
    mod = _module("rlc_circuit")
    s = mod.SCENARIO.resolve(initial)
    L0, C0, R0 = mod.initial_values(s)
    g = mod.true_gains(s)
    G = series_rlc(R0, L0, C0, measured=["v_R"], sees=["v_C", "v_R"])
    A, B, Cm = G.A, G.B, G.C
    bw, bu = B[:, :1], B[:, 1:]
    closed = control.ss(A + bu @ np.array([[g["gC"], g["gR"]]]) @ Cm[1:], bw * (1 + g["gw"]), Cm[:1], 0)
    true = series_rlc(s["R"], s["L"], s["C"], measured=["v_R"], sees=[], actuation=False)
    w = 1j * np.logspace(1, 6, 30)
    np.testing.assert_allclose(np.asarray(closed(w)).ravel(), np.asarray(true(w)).ravel(), rtol=1e-9)
    est = mod.back_out(torch.tensor([[g["gC"], g["gR"], g["gw"]]], dtype=torch.float64), L0, C0, R0)
    a = R0 / s["R"]
    np.testing.assert_allclose([float(est["L"]), float(est["C"]), float(est["R"])],
                               [s["L"] * a, s["C"] / a, s["R"] * a], rtol=1e-12)


def test_rlc_measurement_noise_is_one_percent_of_the_output_rms():
    mod = _module("rlc_circuit")
    s = mod.SCENARIO.resolve()
    Td = mod.truth_discrete(s)
    num, den = scipy.signal.ss2tf(Td.A, Td.B, Td.C, Td.D)
    w = np.random.default_rng(0).normal(size=400_000)
    y = scipy.signal.lfilter(num[0], den, w)[1000:]
    rms = mod.output_rms(s)
    assert abs(np.sqrt(np.mean(y ** 2)) / rms - 1) < 0.01       # Lyapunov rms vs a long simulation
    g = mod.SCENARIO.build(s, 2, torch.float64, "cpu")
    noise = g.run(20000, record={"n": "noise.out"})["n"]         # the measurement noise added to y
    y = g.run(1, record={"y": f"{g.roles['physical']}.y", "m": "measurement.out", "n": "noise.out"})
    assert torch.equal(y["m"], y["y"] + y["n"])
    assert abs(float(noise.std()) / (0.01 * rms) - 1) < 0.02
    assert abs(float(noise.mean())) < 0.05 * 0.01 * rms


def test_rlc_noisy_physical_block_checkpoints_and_resumes_bitwise(tmp_path):
    """The measurement noise's state (its counter) is in the graph's state_dict."""
    with one_thread():
        straight = Run("rlc-circuit", steps=400, batch=2, out=tmp_path / "a")
        straight.advance(progress=False)
        first = Run("rlc-circuit", steps=200, batch=2, out=tmp_path / "b")
        first.advance(progress=False)
        first.save()
        first.close()                   # a live run holds its folder
        resumed = Run.resume(tmp_path / "b", steps=400)
        resumed.advance(progress=False)
    assert torch.equal(straight.graph.blocks["identified"].theta, resumed.graph.blocks["identified"].theta)
    assert "blocks.noise.k" in straight.graph.state_dict()


# --- 2-DOF structure ---------------------------------------------------------------------------------------
def test_twodof_midpoint_model_matches_continuous_feedback_to_higher_order():
    """The discrete loop A_d - B_d dK Cy0 against expm((A - B dK Cq) Ts): O(Ts^2) with y0 = q(k), O(Ts^3)
    with the midpoint y0 = q(k) + Ts/2 q'(k) (the docstring's argument, checked with scipy's expm)."""
    mod = _module("twodof_stiffness")
    base = mod.SCENARIO.resolve()
    dK = np.diag([base["dk1"], base["dk3"]])
    errs = {}
    for sees in ("sampled", "midpoint"):
        for ts in (0.04, 0.02, 0.01):
            s = dict(base, Ts=ts, sees=sees)
            G = mod.known_model(s)
            Gd = control.sample_system(G, ts, method="zoh")
            Ad_loop = Gd.A - Gd.B[:, 1:] @ dK @ Gd.C[1:]
            T = mod.known_model(s, base["dk1"], base["dk3"], actuation=False)
            errs[sees, ts] = np.abs(Ad_loop - scipy.linalg.expm(T.A * ts)).max()
    for sees, order in (("sampled", 2), ("midpoint", 3)):
        ratio = errs[sees, 0.02] / errs[sees, 0.01]
        assert 2 ** order * 0.8 < ratio < 2 ** order * 1.25, (sees, ratio)
    assert errs["midpoint", 0.02] < errs["sampled", 0.02] / 50


def test_twodof_discrete_interconnection_truth_within_one_percent(tmp_path):
    """Truth = the same discrete model with u(k) = -diag(dk1, dk3) q(k): the masked static gain is exact."""
    with one_thread():
        run = Run("twodof-stiffness", steps=8000, batch=2, out=tmp_path,
                  overrides=dict(truth="discrete", sees="sampled", Ts=0.05, nu=30, lam=0.999))
        run.advance(progress=False)
    est = run.scenario.estimates(run.graph, run.settings)
    assert ((est["dk1"] - 0.4).abs() / 0.4 < 0.01).all(), est
    assert ((est["dk3"] - 0.5).abs() / 0.5 < 0.01).all(), est
    theta = run.graph.blocks["identified"].theta
    assert (theta[:, 0, 1] == 0).all() and (theta[:, 1, 0] == 0).all()


# --- scenarios with their defaults -------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("name", ["twodof-stiffness", "rlc-circuit"])
def test_scenario_meets_requirements(name, tmp_path):
    with one_thread():
        run = Run(name, out=tmp_path)
        run.advance(progress=False)
        summary = run.finish(figures=True)
    failed = {k: v for k, v in summary["requirements"].items() if not v["pass"]}
    assert summary["requirements"] and not failed, failed
    assert summary["diverged"] == []
    assert (tmp_path / "frequency_response.png").is_file() and (tmp_path / "estimates.png").is_file()
    keys = {"twodof-stiffness": {"dk1", "dk3"}, "rlc-circuit": {"L", "C", "R"}}[name]
    assert keys <= set(summary["estimates"])


@pytest.mark.slow
def test_rlc_from_the_papers_initial_guesses_fails_as_documented(tmp_path):
    """initial='paper' (L0 = 2 uH, C0 = 1 F): the discrete model error falls, L and C do not come back."""
    with one_thread():
        run = Run("rlc-circuit", out=tmp_path, overrides={"initial": "paper"})
        run.advance(progress=False)
        summary = run.summary()
    est, met = summary["estimates"], summary["metrics"]
    assert est["L"] < 0.1 * 55e-3 and est["C"] > 10 * 23.5e-6
    assert not summary["requirements"]["estimates.L"]["pass"]
    assert met["rel_rms_err_refined"] < 0.5 * met["rel_rms_err_initial"]


@pytest.mark.parametrize("name", ["twodof-stiffness", "rlc-circuit"])
def test_seeds_may_differ_between_members_as_their_single_runs(name, tmp_path):
    with Run(name, steps=300, members=[{"seed": 3}, {"seed": 5}], out=tmp_path / "batch") as run:
        run.advance(progress=False)
        batch = run.graph.role("estimator").theta.clone()
    for b, seed in enumerate((3, 5)):
        with Run(name, steps=300, seed=seed, out=tmp_path / f"single-{seed}") as run:
            run.advance(progress=False)
            assert torch.equal(run.graph.role("estimator").theta[0], batch[b])
    assert not torch.equal(batch[0], batch[1])
