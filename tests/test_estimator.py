"""The RCO estimator: its transfer function, structure (static gain, mask), convergence and divergence handling."""

import contextlib

import control
import numpy as np
import pytest
import torch

import rcotorch as rt
from rcotorch.engine import kernels

DT = 0.1
OMEGA = np.array([0.0, 0.05, 0.7, 3.0, 9.0, np.pi / DT - 1e-3])


def _fixed(est, theta):
    """Reset a batch of one and set theta by hand."""
    est.reset(1)
    est.theta.copy_(torch.as_tensor(theta, dtype=torch.float64).reshape(est.theta.shape))
    return est


def test_siso_transfer_function_closed_form():
    # u(k) = 0.5 y0(k-1) + 0.3 u(k-1)  ->  0.5 / (z - 0.3), DC gain 0.5 / 0.7.
    est = _fixed(rt.RCOEstimator({"y0": 1}, nc=1, markov=[[[1.0]]], dt=DT), [0.5, 0.3])
    assert est.phi_names == ["y0(k-1)", "u(k-1)"]
    z = np.exp(1j * OMEGA * DT)
    ref = 0.5 / (z - 0.3)
    np.testing.assert_allclose(est.frequency_response(OMEGA)[0, :, 0, 0].numpy(), ref, rtol=1e-13)
    tf = est.to_control(0)
    assert tf.dt == DT
    np.testing.assert_allclose(np.asarray(tf(z)).reshape(-1), ref, rtol=1e-13)
    np.testing.assert_allclose(est.dc_gain()[0, 0, 0].item(), 0.5 / 0.7, rtol=1e-14)
    np.testing.assert_allclose(tf.dcgain(), 0.5 / 0.7, rtol=1e-14)


def test_a_member_with_a_singular_denominator_gets_nan_not_an_error():
    # Member 0: u(k) = 0.5 y0(k-1) + u(k-1), a pole at z = 1 (I - sum M = 0, no DC gain); member 1 as above. CUDA's
    # solver reports such a matrix (or a diverged member's NaN one) as singular; the other members are kept.
    est = rt.RCOEstimator({"y0": 1}, nc=1, markov=[[[1.0]]], dt=DT)
    est.reset(2)
    est.theta.copy_(torch.tensor([[[0.5, 1.0]], [[0.5, 0.3]]], dtype=torch.float64))
    gain = est.dc_gain()
    assert torch.isnan(gain[0]).all()
    np.testing.assert_allclose(gain[1, 0, 0].item(), 0.5 / 0.7, rtol=1e-14)
    response = est.frequency_response(torch.tensor([0.0, 1.0]))
    assert torch.isnan(response[0, 0]).all() and torch.isfinite(response[0, 1]).all()   # z = 1 only


def test_controller_output_is_the_transfer_functions_impulse_response():
    """Stepping the estimator with theta held (valid = 0 skips the update) realizes its own transfer function."""
    theta = [0.5, -0.2, 0.3, 0.1]                     # y0(k-1), y0(k-2), u(k-1), u(k-2)
    est = _fixed(rt.RCOEstimator({"y0": 1}, nc=2, markov=[[[1.0]]], dt=DT), theta)
    n = 15
    u = []
    for k in range(n):
        y0 = torch.full((1, 1), 1.0 if k == 0 else 0.0, dtype=torch.float64)
        u.append(est.step(y0=y0, z=torch.ones(1, 1, dtype=torch.float64),
                          valid=torch.zeros(1, 1, dtype=torch.float64))["u"].item())
    assert torch.equal(est.theta.flatten(), torch.tensor(theta, dtype=torch.float64))
    ref_tf = control.tf([0.0, 0.5, -0.2], [1.0, -0.3, -0.1], DT)
    ref = control.impulse_response(ref_tf, T=np.arange(n) * DT).outputs * DT
    np.testing.assert_allclose(u, ref, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("n_u,proper", [(2, False), (2, True), (1, True)])
def test_transfer_function_from_phi_definition(n_u, proper):
    rng = np.random.default_rng(3 + n_u + 2 * proper)
    nc = 2
    est = rt.RCOEstimator({"a": 1, "b": 1}, n_u=n_u, nc=nc, proper=proper, markov=np.ones((1, 1, n_u)), dt=DT)
    theta = 0.3 * rng.standard_normal((n_u, est.n_phi))
    _fixed(est, theta)
    # Reference from the definition of phi (by name): u(k) = sum_l N_l s(k-l) + sum_l M_l u(k-l).
    pos = {name: j for j, name in enumerate(est.phi_names)}
    z = np.exp(1j * OMEGA * DT)
    ref = []
    for zk in z:
        num = np.zeros((n_u, 2), complex)
        den = np.eye(n_u, dtype=complex)
        for lag in range(0 if proper else 1, nc + 1):
            for j, s in enumerate("ab"):
                num[:, j] += theta[:, pos[f"{s}(k-{lag})" if lag else f"{s}(k)"]] * zk ** -lag
        for lag in range(1, nc + 1):
            for c in range(n_u):
                den[:, c] -= theta[:, pos[f"u[{c}](k-{lag})" if n_u > 1 else f"u(k-{lag})"]] * zk ** -lag
        ref.append(np.linalg.solve(den, num))
    ref = np.array(ref)
    np.testing.assert_allclose(est.frequency_response(OMEGA)[0].numpy(), ref, rtol=1e-11, atol=1e-13)
    sys = est.to_control(0)
    resp = np.moveaxis(np.asarray(sys(z)), -1, 0)                    # (F, outputs, inputs)
    np.testing.assert_allclose(resp, ref, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(est.dc_gain()[0].numpy(), ref[0].real, rtol=1e-11, atol=1e-13)
    np.testing.assert_allclose(sys.dcgain(), ref[0].real, rtol=1e-8, atol=1e-10)


def test_static_gain_structure():
    est = rt.RCOEstimator.static_gain({"q": 2}, n_u=2, markov=np.ones((3, 1, 2)), dt=DT)
    assert est.proper and est.nc == 0 and not est.feed_u
    assert est.phi_names == ["q[0](k)", "q[1](k)"]
    assert est.feedthrough() == {"u": ("q",)}
    K = np.array([[2.0, -1.0], [0.5, 3.0]])
    _fixed(est, K)
    np.testing.assert_allclose(est.dc_gain()[0].numpy(), K, rtol=0, atol=0)
    np.testing.assert_allclose(est.frequency_response(OMEGA)[0].numpy(), np.broadcast_to(K, (len(OMEGA), 2, 2)))
    np.testing.assert_allclose(est.to_control(0).dcgain(), K, rtol=1e-14)
    # u(k) = K q(k) at once.
    q = torch.tensor([[1.0, 2.0]], dtype=torch.float64)
    u = est.step(q=q, z=torch.zeros(1, 1, dtype=torch.float64), valid=torch.zeros(1, 1, dtype=torch.float64))["u"]
    np.testing.assert_allclose(u.numpy(), q.numpy() @ K.T, rtol=1e-15)


def test_mask_pins_entries_to_zero():
    mask = [[True, False], [False, True]]
    theta0 = [[1.0, 7.0], [7.0, 2.0]]                                    # masked entries are dropped
    est = rt.RCOEstimator.static_gain({"q": 2}, n_u=2, n_z=2, mask=mask, theta0=theta0, p0=100.0,
                                      markov=np.random.default_rng(0).standard_normal((4, 2, 2)))
    assert est.n_theta == 2 and est.theta_names == ["0:q[0](k)", "1:q[1](k)"]
    B = 3
    est.reset(B)
    assert est.P.shape == (B, 2, 2)
    assert torch.equal(est.theta[:, 0, 1], torch.zeros(B, dtype=torch.float64))
    g = torch.Generator().manual_seed(1)
    for _ in range(50):
        est.step(q=torch.randn(B, 2, generator=g, dtype=torch.float64),
                 z=torch.randn(B, 2, generator=g, dtype=torch.float64))
    assert bool(est.alive.all())
    assert torch.equal(est.theta[:, 0, 1], torch.zeros(B, dtype=torch.float64))
    assert torch.equal(est.theta[:, 1, 0], torch.zeros(B, dtype=torch.float64))
    assert bool((est.theta[:, 0, 0] != 1.0).all()) and bool((est.theta[:, 1, 1] != 2.0).all())
    assert torch.isfinite(est.theta).all()


def test_bad_mask_shape_and_settings():
    with pytest.raises(rt.DimensionError, match="mask"):
        rt.RCOEstimator({"y0": 1}, nc=2, mask=[[True, False]])
    with pytest.raises(rt.ConfigError, match="p0"):
        rt.RCOEstimator({"y0": 1}, p0=0.0)
    with pytest.raises(rt.ConfigError, match="lam"):
        rt.RCOEstimator({"y0": 1}, lam=1.5)
    with pytest.raises(rt.ConfigError, match="first_delay must be >= 0"):
        rt.RCOEstimator.static_gain({"y0": 1}, markov=[[[1.0]]], first_delay=-1)
    est = rt.RCOEstimator({"y0": 1})
    est.reset(1)
    one = torch.ones(1, 1, dtype=torch.float64)
    with pytest.raises(rt.ConfigError, match="no Markov parameters"):
        est.step(y0=one, z=one)
    est.set_markov([[[1.0]], [[0.5]]])
    with pytest.raises(rt.ConfigError, match="call reset"):
        est.step(y0=one, z=one)
    est.reset(1)
    est.step(y0=one, z=one)


def test_bad_ties_are_named():
    """A tie of the wrong shape or type, or tied entries given different starting values or bounds, fail when
    the estimator is built."""
    with pytest.raises(rt.DimensionError, match="block 'identified': tie has shape \\(1, 2\\)"):
        rt.RCOEstimator.static_gain({"y0": 3}, n_u=3, tie=[[0, 0]])
    with pytest.raises(rt.ConfigError, match="tie must hold integer labels"):
        rt.RCOEstimator.static_gain({"y0": 1}, tie=[[0.5]])
    tie = [[0, -1], [-1, 0]]
    with pytest.raises(rt.ConfigError, match="theta0 differs between entries .* share a parameter"):
        rt.RCOEstimator.static_gain({"y0": 2}, n_u=2, tie=tie, theta0=[[1.0, 0.0], [0.0, 2.0]])
    with pytest.raises(rt.ConfigError, match="theta_bounds low differs"):
        rt.RCOEstimator.static_gain({"y0": 2}, n_u=2, tie=tie, theta_bounds=([0.0, 0.0, 0.0, -1.0], 5.0))
    est = rt.RCOEstimator.static_gain({"y0": 2}, n_u=2, tie=tie, theta0=[[1.0, 0.0], [0.0, 1.0]],
                                      theta_bounds=(0.0, 5.0))
    assert est.n_theta == 1 and est.theta_names == ["0:y0[0](k) = 1:y0[1](k)"]


def test_tied_gain_stays_tied_in_a_closed_loop():
    """Two masses whose springs change by the same dk: one shared parameter on the diagonal, the cross terms
    pinned; the tied entries stay exactly equal, the pinned ones exactly zero, and the value converges."""
    G = rt.models.structure(np.eye(2), 0.8 * np.array([[2, -1], [-1, 2]]), [[1.2, -0.5], [-0.5, 1.1]], [1, 1],
                            measured=["velocity[1]"], sees=["position[0]", "position[1]"])
    known = rt.LTI.from_control(G, inputs={"w": 1, "u": 2}, outputs={"y": 1, "y0": 2}, dt=0.05, name="known")
    est = rt.RCOEstimator.static_gain({"y0": 2}, n_u=2, tie=[[0, -1], [-1, 0]], p0=1e3)
    g = rt.refinement(known, est, truth=rt.Gain(-0.3 * np.eye(2)), excitation=rt.WhiteNoise(1, seed=3), nu=30,
                      batch_size=2)
    g.run(4000)
    th = est.theta.numpy()
    assert np.all(th[:, 0, 0] == th[:, 1, 1]) and np.all(th[:, 0, 1] == 0.0) and np.all(th[:, 1, 0] == 0.0)
    np.testing.assert_allclose(th[:, 0, 0], -0.3, rtol=0.02)
    assert est.P.shape == (2, 1, 1)


def test_figure1_sdof_converges(sdof_known, zoh_first_order):
    est = rt.RCOEstimator({"y0": 1}, nc=5, p0=1e8)
    g = rt.refinement(sdof_known(DT), est, truth=zoh_first_order(DT), excitation=rt.WhiteNoise(1, seed=1),
                      nu=10, batch_size=1)
    g.run(3000)
    assert bool(est.alive.all())
    assert abs(est.dc_gain()[0, 0, 0].item() - 5.0) < 0.05
    # The frequency response approaches ZOH(10 / (s + 2)) too.
    z = np.exp(1j * OMEGA[1:] * DT)
    ref = np.asarray(control.sample_system(control.tf([10.0], [1.0, 2.0]), DT, "zoh")(z))
    np.testing.assert_allclose(est.frequency_response(OMEGA[1:])[0, :, 0, 0].numpy(), ref, rtol=1e-2)


def test_static_gain_recovers_discrete_truth(sdof_known):
    """A discrete truth u(k) = -0.5 q(k) lies in the model class of a static gain: the estimate is exact."""
    est = rt.RCOEstimator.static_gain({"y0": 1}, p0=1e8)
    g = rt.refinement(sdof_known(0.05, "position"), est, truth=rt.Gain(-0.5),
                      excitation=rt.WhiteNoise(1, seed=3), nu=20)
    g.run(1000)
    assert abs(est.theta.item() + 0.5) < 1e-3


# --- divergence ------------------------------------------------------------------------------------------

def _per_member_truth(poles):
    """ZOH(10 / (s + 2)) at DT per member, with the pole replaced: a pole outside the unit circle blows up."""
    b = 10.0 * (1.0 - np.exp(-2.0 * DT)) / 2.0
    n = len(poles)
    return rt.LTI(np.reshape(poles, (n, 1, 1)), [[b]], [[1.0]], [[0.0]], ["in"], ["out"], DT)


def _divergence_run(known, poles, seeds, steps=400):
    est = rt.RCOEstimator({"y0": 1}, nc=2, p0=1e4)
    g = rt.refinement(known, est, truth=_per_member_truth(poles), excitation=rt.WhiteNoise(1, seed=seeds),
                      nu=10, batch_size=len(poles))
    tr = g.run(steps, record={"u": "identified.u", "z": "error.out", "y": "plant.y"})
    return est, tr


def test_diverging_member_is_frozen_and_others_unaffected(sdof_known):
    a = np.exp(-2.0 * DT)
    poles, seeds = [a, 0.9 * a, 10.0, 0.8 * a], [11, 12, 13, 14]
    good = [0, 1, 3]
    est4, tr4 = _divergence_run(sdof_known(DT), poles, seeds)
    est3, tr3 = _divergence_run(sdof_known(DT), [poles[i] for i in good], [seeds[i] for i in good])
    assert est4.alive.tolist() == [True, True, False, True]
    assert int(est4.diverged_at[2]) >= 0
    assert est4.diverged_at[good].tolist() == [-1, -1, -1]
    assert not torch.isfinite(tr4["y"][:, 2]).all()                  # the bad physical system did blow up
    assert torch.isfinite(est4.theta).all() and torch.isfinite(est4.P).all()
    assert torch.isfinite(tr4["u"]).all()
    assert (tr4["u"][int(est4.diverged_at[2]) + 1:, 2] == 0).all()   # a frozen member outputs u = 0
    for key in ("u", "z", "y"):
        assert torch.isfinite(tr4[key][:, good]).all()
        assert torch.equal(tr4[key][:, good], tr3[key])
    assert torch.equal(est4.theta[good], est3.theta)
    assert torch.equal(est4.P[good], est3.P)
    assert bool(est3.alive.all())


def test_nan_measurement_freezes_member(sdof_known):
    """A NaN injected into one member's z stops that member at that step, theta and P held."""
    est = rt.RCOEstimator({"y0": 1}, nc=2, p0=1e4, markov=[[[-0.1]]], dt=DT)
    B = 4
    est.reset(B)
    g = torch.Generator().manual_seed(0)
    for k in range(30):
        z = torch.randn(B, 1, generator=g, dtype=torch.float64)
        if k == 20:
            z[1] = float("nan")
            theta_before, P_before = est.theta[1].clone(), est.P[1].clone()
        est.step(y0=torch.randn(B, 1, generator=g, dtype=torch.float64), z=z)
    assert est.alive.tolist() == [True, False, True, True]
    assert est.diverged_at.tolist() == [-1, 20, -1, -1]
    assert torch.equal(est.theta[1], theta_before) and torch.equal(est.P[1], P_before)
    assert torch.isfinite(est.theta).all()


# --- the update is the retrospective least-squares problem ------------------------------------------------

def _phi_from_names(names, hist, k):
    """phi(k) built from its entry names ('a(k-1)', 'b[1](k-2)', 'u[0](k-1)', 'q(k)') and signal histories."""
    out = []
    for name in names:
        sig, lag = name[:-1].split("(k")
        lag = -int(lag) if lag else 0                      # "-2" -> 2
        base, comp = (sig.split("[")[0], int(sig.split("[")[1][:-1])) if "[" in sig else (sig, 0)
        out.append(hist[base][k - lag][comp] if k - lag >= 0 else 0.0)
    return np.array(out)


FEATURES = {   # name -> (term, the same function in numpy, written out independently)
    "q": (rt.features.port("q"), lambda q, v: q),
    "q^3": (rt.features.power("q", 3), lambda q, v: q ** 3),
    "sign(v)*v^2": (rt.features.sign("v") * rt.features.power("v", 2), lambda q, v: np.sign(v) * v ** 2),
    "|q|*v": (rt.features.absolute("q") * rt.features.port("v"), lambda q, v: np.abs(q) * v),
    "sat(v, -0.5, 0.5)": (rt.features.saturation("v", -0.5, 0.5), lambda q, v: np.clip(v, -0.5, 0.5)),
    "dz(q, -0.2, 0.2)": (rt.features.dead_zone("q", 0.2), lambda q, v: q - np.clip(q, -0.2, 0.2)),
    "tanh(v/0.7)": (rt.features.tanh("v", 0.7), lambda q, v: np.tanh(v / 0.7)),
    "3*(2*q-1)": (3.0 * rt.features.affine("q", 2.0, -1.0), lambda q, v: 3 * (2 * q - 1)),
    "q^2*v": (rt.features.monomial(q=2, v=1), lambda q, v: q ** 2 * v),
    "0.5": (rt.features.constant(0.5), lambda q, v: 0.5 + 0 * q),
}


@pytest.mark.parametrize("kernel", ["torch", "native"])
@pytest.mark.parametrize("case", ["siso", "mimo_masked", "static_gain", "tied", "features", "relative_degree_0"])
def test_update_minimizes_retrospective_cost(case, kernel):
    """With lam = 1, theta(N) = argmin sum_k |z(k) + sum_i beta_i [th - theta(k-i)] phi(k-i)|^2_R
    + |eta - eta0|^2 / p0 over the free parameters eta (th = T eta: masked entries zero, tied entries
    equal), computed in numpy from the run's own data. ``kernel='torch'``: PyTorch operations only (the
    path of Graph(engine='torch'), CUDA and float32); 'native': rls_update's compiled kernel."""
    if kernel == "native" and not kernels.available():
        pytest.skip(f"no native engine: {kernels.why_unavailable()}")
    with kernels.disabled() if kernel == "torch" else contextlib.nullcontext():
        _check_retrospective_cost(case)


def _check_retrospective_cost(case):
    rng = np.random.default_rng({"siso": 1, "mimo_masked": 2, "static_gain": 3, "tied": 4, "features": 5,
                                 "relative_degree_0": 6}[case])
    p0, N = 1.0, 40
    T = None
    feats = None
    if case == "features":
        signals, n_u, n_z, d, nu, R, mask = {"q": 1, "v": 1}, 1, 1, 1, 3, np.eye(1), None
        feats = {name: f for name, (_, f) in FEATURES.items()}
        est = rt.RCOEstimator(signals, nc=1, p0=p0, features=[t for t, _ in FEATURES.values()],
                              markov=0.3 * rng.standard_normal((nu, 1, 1)), first_delay=d)
        assert est.signal_names == list(FEATURES)
    elif case == "tied":
        # Three outputs, one function of each output's own two features: u_j = a s_j + b s_j^2 (a, b shared),
        # the cross terms pinned: theta (3 x 6) over phi = [s_0, s_1, s_2, s_0^2, s_1^2, s_2^2](k).
        signals, n_u, n_z, d, nu = {"s": 3, "s2": 3}, 3, 2, 1, 3
        R = np.array([[1.5, 0.2], [0.2, 0.7]])
        tie = -np.ones((3, 6), dtype=int)
        for j in range(3):
            tie[j, j], tie[j, 3 + j] = 7, 9                 # any labels: 7 -> a, 9 -> b
        mask = tie >= 0
        T = np.zeros((18, 2))
        for j in range(3):
            T[j * 6 + j, 0] = T[j * 6 + 3 + j, 1] = 1.0
        est = rt.RCOEstimator.static_gain(signals, n_u=n_u, n_z=n_z, p0=p0, R=R, tie=tie,
                                          markov=rng.standard_normal((nu, n_z, n_u)), first_delay=d)
        assert est.n_theta == 2 and est.P.shape[1:] == (2, 2)
        assert est.theta_names == ["0:s[0](k) = 1:s[1](k) = 2:s[2](k)", "0:s2[0](k) = 1:s2[1](k) = 2:s2[2](k)"]
    elif case == "relative_degree_0":
        # u reaches z at once (beta_0 != 0, an accelerometer): a masked MIMO static gain with first_delay 0.
        signals, n_u, n_z, d, nu = {"a": 1, "b": 2}, 2, 2, 0, 3
        R = np.array([[1.2, -0.1], [-0.1, 0.8]])
        mask = np.array([[True, False, True], [False, True, True]])
        est = rt.RCOEstimator.static_gain(signals, n_u=n_u, n_z=n_z, p0=p0, R=R, mask=mask,
                                          markov=0.5 * rng.standard_normal((nu, n_z, n_u)), first_delay=d)
        assert est.first_delay == 0 and est.window == nu
    elif case == "siso":
        signals, n_u, n_z, d, nu, R, mask = {"y0": 1}, 1, 1, 1, 3, np.eye(1), None
        est = rt.RCOEstimator(signals, nc=2, p0=p0, markov=rng.standard_normal((nu, 1, 1)), first_delay=d)
    elif case == "mimo_masked":
        signals, n_u, n_z, d, nu = {"a": 1, "b": 2}, 2, 2, 2, 3
        R = np.array([[2.0, 0.3], [0.3, 0.5]])
        mask = rng.random((n_u, 5)) > 0.3         # n_phi = 3 signal entries x 1 lag + 2 past u
        est = rt.RCOEstimator(signals, n_u=n_u, n_z=n_z, nc=1, p0=p0, R=R, mask=mask,
                              theta0=0.1 * rng.standard_normal((n_u, 5)),
                              markov=rng.standard_normal((nu, n_z, n_u)), first_delay=d)
    else:
        signals, n_u, n_z, d, nu, R, mask = {"q": 1}, 1, 1, 1, 4, np.eye(1), None
        est = rt.RCOEstimator.static_gain(signals, p0=p0, markov=rng.standard_normal((nu, 1, 1)))
    beta = est.beta[0].numpy()
    free = np.ones((n_u, est.n_phi), bool) if mask is None else np.asarray(mask)
    est.reset(1)
    theta0 = est.theta[0].numpy().copy()
    hist = {s: [] for s in (feats or signals)} | {"u": []}          # what phi is built from
    phis, thetas, zs = [], [], []
    for k in range(N):
        inputs = {s: torch.tensor(rng.standard_normal((1, w))) for s, w in signals.items()}
        z = torch.tensor(0.2 * rng.standard_normal((1, n_z)))    # small: keeps the u-feedback stable
        for s in signals if feats is None else ():
            hist[s].append(inputs[s][0].numpy())
        for name, f in (feats or {}).items():
            hist[name].append(np.atleast_1d(f(inputs["q"][0].numpy(), inputs["v"][0].numpy())))
        thetas.append(est.theta[0].numpy().copy())
        phi = _phi_from_names(est.phi_names, hist, k) if est.proper else None
        u = est.step(**inputs, z=z)["u"][0].numpy()
        if not est.proper:
            phi = _phi_from_names(est.phi_names, hist, k)
        np.testing.assert_allclose(u, thetas[-1] @ phi, rtol=1e-12, atol=1e-14)   # u(k) = theta(k) phi(k)
        hist["u"].append(u)
        phis.append(phi)
        zs.append(z[0].numpy())
    assert bool(est.alive.all())
    # Build z_hat(th, k) = zeta(k) + Psi(k)^T T eta over the free parameters eta (th row-major).
    if T is None:
        idx = np.flatnonzero(free.reshape(-1))
        T = np.eye(n_u * est.n_phi)[:, idx]
    info = np.eye(T.shape[1]) / p0
    rhs = info @ np.linalg.lstsq(T, theta0.reshape(-1), rcond=None)[0]
    for k in range(N):
        zeta = zs[k].copy()
        psi_t = np.zeros((n_z, n_u * est.n_phi))
        for i in range(nu):
            j = k - d - i
            if j < 0:
                continue
            zeta -= beta[i] @ thetas[j] @ phis[j]
            psi_t += np.kron(beta[i], phis[j][None, :])
        psi_t = psi_t @ T
        info += psi_t.T @ R @ psi_t
        rhs -= psi_t.T @ R @ zeta
    ref = T @ np.linalg.solve(info, rhs)
    np.testing.assert_allclose(est.theta[0].numpy().reshape(-1), ref, rtol=1e-9, atol=1e-11)
    np.testing.assert_allclose(est.P[0].numpy(), np.linalg.inv(info), rtol=1e-8, atol=1e-12)


def test_basis_features_recover_a_cubic_spring():
    """Truth: the discrete SDOF model with the static force u = -k3 q^3 in feedback (a discrete interconnection);
    a static gain on the feature q^3 converges to -k3, a closed-form value."""
    Ts, k3 = 0.05, 2.0
    G = rt.models.sdof(1.0, 0.5, 4.0, measured=["velocity"], sees=["position"])
    known = rt.LTI.from_control(G, inputs=["w", "u"], outputs=["y", "y0"], dt=Ts, name="known")
    truth = rt.StaticMap(lambda q: -k3 * q ** 3, 1)
    ident = rt.RCOEstimator.static_gain({"y0": 1}, features={"y0^3": lambda s: s["y0"] ** 3}, p0=1e2)
    assert ident.phi_names == ["y0^3(k)"]
    g = rt.refinement(known, ident, truth=truth, excitation=rt.WhiteNoise(1, std=2.0, seed=3), nu=40)
    g.run(8000)
    assert abs(float(ident.theta[0, 0, 0]) + k3) < 1e-3 * k3


def test_features_are_probed_when_built():
    with pytest.raises(rt.DimensionError, match="feature 'bad' must return a \\(batch, m\\) tensor.*as a column"):
        rt.RCOEstimator.static_gain({"y0": 1}, features={"bad": lambda s: s["y0"][:, 0]})
    with pytest.raises(rt.ConfigError, match="feature 'boom' failed"):
        rt.RCOEstimator.static_gain({"y0": 1}, features={"boom": lambda s: s["nope"]})
    with pytest.raises(rt.DimensionError, match="block 'cube'"):
        rt.StaticMap(lambda q: q.sum(), 1, name="cube")


def test_u_bounds_saturate_and_theta_bounds_project():
    """A cooling-like constraint: u may not be negative. The saturated u is what the model receives and
    what the retrospective cost uses; theta is projected onto its box after each update."""
    import control

    Ts = 0.1
    G = rt.models.sdof(1.0, 5.0, 30.0, measured=["velocity"], sees=["velocity"])
    known = rt.LTI.from_control(G, inputs=["w", "u"], outputs=["y", "y0"], dt=Ts, name="known")
    truth = rt.LTI.from_control(control.tf([10], [1, 2]), inputs=["in"], outputs=["out"], dt=Ts)
    ident = rt.RCOEstimator({"y0": 1}, nc=2, p0=1e4, u_bounds=(0.0, float("inf")), theta_bounds=(-0.5, 0.8))
    g = rt.refinement(known, ident, truth=truth, excitation=rt.WhiteNoise(1, seed=1), nu=10)
    us = g.run(500, record={"u": "identified.u"})["u"]
    assert float(us.min()) >= 0.0 and float(us.max()) > 0.0
    assert float(ident.theta.min()) >= -0.5 and float(ident.theta.max()) <= 0.8
    assert torch.equal(ident.win[:, :, -1].clamp(min=0.0), ident.win[:, :, -1])  # stored u are the applied ones
    with pytest.raises(rt.ConfigError, match="low > high"):
        rt.RCOEstimator({"y0": 1}, u_bounds=(1.0, 0.0))
    with pytest.raises(rt.DimensionError, match="theta_bounds entries"):
        rt.RCOEstimator({"y0": 1}, nc=1, theta_bounds=([0.0, 0.0, 0.0], 1.0))


def _accelerometer_building(engine: str):
    """A 3-storey shear building read by accelerometers on floors 2 and 3 (the force pairs reach them at once:
    the first Markov parameter is the feedthrough), storey 2 softer by 20% in the truth, no noise."""
    m, k = 2e4, 2e7
    G = rt.models.shear_building([m] * 3, [k] * 3, damping_ratio=0.02, force="base",
                                 measured=["acceleration[2]", "acceleration[3]"], identified=[1, 2, 3])
    known = rt.LTI.from_control(G, inputs={"w": 1, "u": 3}, outputs={"y": 2, "y0": 3}, dt=0.01, name="known")
    ident = rt.RCOEstimator.static_gain({"y0": 3}, n_u=3, n_z=2, mask=np.eye(3, dtype=bool), p0=1e14)
    g = rt.refinement(known, ident, truth=rt.Gain(np.diag([0.0, 0.2 * k, 0.0]), name="unknown"),
                      excitation=rt.WhiteNoise(1, std=1.0, seed=1), nu=300, batch_size=3)
    g.engine = engine
    return g, k


def test_stiffness_changes_identified_from_accelerometers():
    """Relative degree 0: refinement derives first_delay = 0 from the known model's feedthrough D_yu (checked
    against python-control's D); both engines agree, and the static gain on the drifts converges to the truth's
    dk = (0, -0.2, 0) (slowly, as the early samples' bias, taken while the model's state followed a wrong theta,
    is outweighed: the error falls by more than 3x from 3,000 to 30,000 steps, about the sqrt(10) of a random
    error's fall)."""
    native, k = _accelerometer_building("native")
    torch_, _ = _accelerometer_building("torch")
    G = rt.models.shear_building([2e4] * 3, [2e7] * 3, damping_ratio=0.02, force="base",
                                 measured=["acceleration[2]", "acceleration[3]"], identified=[1, 2, 3])
    assert np.abs(G.D[:2, 1:]).max() > 0                                 # u reaches y at once
    est = native.role("estimator")
    assert est.first_delay == 0
    np.testing.assert_allclose(est.beta[0, 0].numpy(), -G.D[:2, 1:], rtol=1e-12)   # beta_0 = -D_yu (z = y0 - y)
    for g in (native, torch_):
        g.run(3000)
    assert native.ran_engine == "native" and torch_.ran_engine == "torch"
    a, b = native.role("estimator").theta, torch_.role("estimator").theta
    assert torch.allclose(a, b, rtol=1e-9, atol=1e-9 * k)
    truth = torch.tensor([0.0, -0.2, 0.0], dtype=torch.float64)

    def error():
        return float((-torch.diagonal(native.role("estimator").theta, dim1=1, dim2=2) / k - truth).abs().max())
    early = error()
    native.run(27000)
    assert error() < 3e-3 and error() < early / 3, (early, error())
