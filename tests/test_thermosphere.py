"""The reduced thermosphere column against closed forms and reference atmospheres, its Markov parameters by
autograd against finite differences, the cooling bounds, and the thermosphere-no-cooling scenario."""

import math

import numpy as np
import pytest
import torch

import rcotorch as rt
from rcotorch.models import thermosphere as th
from rcotorch.run.runner import Run

F64 = torch.float64


def test_isothermal_densities_are_exponential_in_geopotential_height():
    """n_i = n_i0 exp(-m_i g0 R^2 (1/(R + z0) - 1/(R + z)) / (k T)) at constant T, each with its own mass."""
    col = th.Column()
    T = 800.0
    n = col.densities(torch.full((1, col.n), T, dtype=F64))[0]
    R, z = th.R_EARTH, col.z
    for i, m in enumerate(th.MASS):
        ref = th.N_100KM[i] * torch.exp(-m * th.G0 * R ** 2 * (1 / (R + z[0]) - 1 / (R + z)) / (th.K_B * T))
        np.testing.assert_allclose(n[i].numpy(), ref.numpy(), rtol=1e-5)
    assert float(n[0, -1] / n[2, -1]) > 100 * float(n[0, 0] / n[2, 0])   # O outlasts N2 (diffusive separation)


@pytest.mark.parametrize("dz, rtol", [(5e3, 8e-3), (2.5e3, 2e-3)])
def test_densities_in_a_bates_profile_match_walker_and_us_standard_atmosphere(dz, rtol):
    """U.S. Standard Atmosphere 1976 above 120 km: Bates profile (T_inf = 1000 K, T120 = 360 K, 0.01875 /km) and its
    120 km densities. Walker's (1965) closed form to second order in dz; the tabulated mass density (which also
    has He and Ar) within 3 per cent at 200, 300 and 400 km."""
    n120 = (9.275e16, 4.395e16, 3.726e17)                 # O, O2, N2 at 120 km [m^-3], U.S. Std. Atm. 1976
    col = th.Column(z_bottom=120e3, z_top=600e3, dz=dz, n_bottom=n120, T_bottom=360.0)
    T = th.bates_profile(col.z, 1000.0, 360.0, 0.01875e-3).unsqueeze(0)
    n = col.densities(T)[0]
    for i, m in enumerate(th.MASS):
        ref = th.walker_density(col.z, n120[i], m, 1000.0, 360.0, 0.01875e-3)
        np.testing.assert_allclose(n[i].numpy(), ref.numpy(), rtol=rtol)
    rho = col.mass_density(T)
    for z, table in ((200e3, 2.541e-10), (300e3, 1.916e-11), (400e3, 2.803e-12)):
        assert abs(float(col.at(rho, z, log=True)) / table - 1) < 0.03


def test_conduction_steady_state_matches_the_analytic_profile():
    """With a heat flux F into the top and T fixed at the bottom, kappa = A T^s carries F down unchanged:
    T(z)^(s+1) = T0^(s+1) + (s+1) F (z - z0) / A."""
    col = th.Column()
    F, T0 = 1e-4, th.T_100KM
    T = torch.full((1, col.n), T0, dtype=F64)
    Q = torch.zeros_like(T)
    Q[0, -1] = 2 * F / col.dz                              # the top level holds half a cell
    for _ in range(100):
        T = col.conduct(T, torch.full_like(T, 1e-3), Q, dt=1e9)
    s = th.KAPPA_S
    ref = (T0 ** (s + 1) + (s + 1) * F * (col.z - col.z[0]) / th.KAPPA_A) ** (1 / (s + 1))
    np.testing.assert_allclose(T[0].numpy(), ref.numpy(), rtol=5e-5)
    assert 1000 < float(T[0, -1]) < 1100


def test_no_cooling_matches_a_hand_computation():
    """Kockarts (1980) with the constants written out: h nu = h c 1876 cm^-1, A10 = 13.3 /s,
    k_O = 6.5e-11 cm^3/s, at T = 700 K, [O] = 1.5e10 cm^-3, [NO] = 1e7 cm^-3."""
    h_nu = 6.62607015e-34 * 2.99792458e8 * 1876e2            # 3.7266e-20 J
    T, n_o, n_no = 700.0, 1.5e16, 1e13
    collisions = 6.5e-11 * 1e-6 * n_o
    expected = h_nu * 13.3 * n_no * collisions * math.exp(-h_nu / 1.380649e-23 / T) / (collisions + 13.3)
    assert expected == pytest.approx(7.1612e-9, rel=1e-4)
    got = th.Column().no_cooling_rate(*(torch.tensor([v], dtype=F64) for v in (T, n_o, n_no)))
    assert float(got) == pytest.approx(expected, rel=1e-12)
    # The brief form n_NO n_O exp(-2700/T) times the quenching factor A10 / (A10 + k_O n_O), 0.93 here.
    brief = h_nu * n_no * 6.5e-17 * n_o * math.exp(-2700.0 / T)
    assert float(got) == pytest.approx(brief * 13.3 / (13.3 + collisions), rel=2e-3)     # 2700 K vs 2699 K


def test_cooling_nodes_interpolate_linearly_and_taper():
    z = torch.arange(100e3, 305e3, 5e3, dtype=F64)
    basis = th.interpolation_basis(z, torch.tensor([120e3, 152e3, 200e3], dtype=F64))
    profile = torch.tensor([[4.0, 2.0, 1.0]], dtype=F64) @ basis
    at = dict(zip((z / 1e3).round().int().tolist(), profile[0].tolist()))
    assert at[120] == pytest.approx(4.0) and at[200] == pytest.approx(1.0)
    assert at[135] == pytest.approx(4.0 + (2.0 - 4.0) * 15 / 32)
    assert at[100] == pytest.approx(4.0 * (100 - 88) / 32)           # taper to zero 32 km below the lowest node
    assert at[245] == pytest.approx(1.0 * 3 / 48) and at[250] == 0.0  # ... and 48 km above the highest
    inner = (z >= 120e3) & (z <= 200e3)
    np.testing.assert_allclose(basis[:, inner].sum(0).numpy(), 1.0)


def _hats(z_km: np.ndarray, nodes_km, values) -> np.ndarray:
    """Linear interpolation of ``values`` at ``nodes_km``, tapered to zero one node spacing outside (np.interp)."""
    ext = [2 * nodes_km[0] - nodes_km[1], *nodes_km, 2 * nodes_km[-1] - nodes_km[-2]]
    return np.interp(z_km, ext, [0.0, *values, 0.0], left=0.0, right=0.0)


@pytest.mark.parametrize("nodes", [(120e3, 150e3, 200e3), (120e3, 152e3, 200e3)])
def test_strength_interpolation_follows_the_rate_between_the_nodes(nodes):
    """interpolate='strength': the profile is rate(z) times the strengths u_j / rate(z_j) interpolated linearly
    (np.interp), so it takes the rate's shape and, at a node on the grid, the node's value; 'cooling'
    interpolates u itself."""
    gen = torch.Generator().manual_seed(3)
    strength = th.Column(cooling_nodes=nodes, no_cooling=False, interpolate="strength")
    linear = th.Column(cooling_nodes=nodes, no_cooling=False)
    z = strength.z.numpy() / 1e3
    rate = torch.rand(2, strength.n, generator=gen, dtype=F64) + 0.5
    u = torch.tensor([[4.0, 2.0, 1.0], [0.5, 3.0, 0.0]], dtype=F64)
    got = 1e9 * strength.identified_cooling(u, rate)
    for b in range(2):
        at_nodes = [np.interp(a / 1e3, z, rate[b].numpy()) for a in nodes]
        expected = rate[b].numpy() * _hats(z, [a / 1e3 for a in nodes], u[b].numpy() / at_nodes)
        np.testing.assert_allclose(got[b].numpy(), expected, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose((1e9 * linear.identified_cooling(u))[b].numpy(),
                                   _hats(z, [a / 1e3 for a in nodes], u[b].numpy()), rtol=1e-12, atol=1e-15)
    on_grid = [int(round((a / 1e3 - z[0]) / (z[1] - z[0]))) for a in nodes if a % 5e3 == 0]
    np.testing.assert_allclose(got[:, on_grid].numpy(), u[:, [nodes.index(z[i] * 1e3) for i in on_grid]].numpy(),
                               rtol=1e-12)


def test_strength_interpolation_needs_the_rate_and_a_known_name():
    col = th.Column(cooling_nodes=(120e3, 152e3, 200e3), no_cooling=False, interpolate="strength")
    with pytest.raises(rt.ConfigError, match="Kockarts rate"):
        col.identified_cooling(torch.ones(1, 3, dtype=F64))
    with pytest.raises(rt.ConfigError, match="interpolate must be one of"):
        th.Column(cooling_nodes=(120e3, 152e3, 200e3), interpolate="spline")


def test_truth_column_has_a_typical_climatology():
    """After a 3-day quiet spin-up at F10.7 = 150: exospheric temperature, density at 407 km, NO cooling share."""
    col = th.Column(dt=1800.0, substeps=2)
    x = col.spin_up(150.0, days=3.0)
    d = col.tendencies(x, torch.tensor([[150.0, 0.0]], dtype=F64))
    assert 850 < float(d["T"][0, -1]) < 1150
    assert 1.0 < float(col.density_at(x, 407e3)) < 4.0
    assert 0.1 < float(d["no_cooling"].sum() / d["heating"].sum()) < 0.5
    assert 115e3 <= float(col.z[d["no_cooling"][0].argmax()]) <= 140e3
    assert float(x[0, -1]) == 0.0                                       # the clock is set back


DT = 3600.0


def _known(dz=10e3, name="known"):
    model = th.Column(dz=dz, no_cooling=False, cooling_nodes=(120e3, 152e3, 200e3), dt=DT, substeps=2)
    x0 = th.Column(dz=dz, dt=DT, substeps=2).spin_up(150.0, days=1.0)
    return th.ColumnBlock(model, {"y": lambda x: model.density_at(x, 407e3), "y0": model.no_cooling_at_nodes},
                          x0=x0, name=name)


@pytest.mark.parametrize("along", ["trajectory", "point"])
def test_column_markov_by_autograd_matches_finite_differences_and_the_core(along):
    blk = _known()
    w = {"w": torch.tensor([[150.0, 1.0]], dtype=F64), "u": torch.tensor([[2.0, 1.0, 0.5]], dtype=F64)}
    Ha = blk.markov("u", "y", 12, inputs=w, method="autograd", along=along)
    Hf = blk.markov("u", "y", 12, inputs=w, method="fd", along=along)
    assert Ha.shape == (1, 12, 1, 3)
    np.testing.assert_allclose(Ha.numpy(), Hf.numpy(), rtol=1e-5, atol=1e-12)
    assert float(Ha[0, 0].abs().max()) == 0.0 and bool((Ha[0, 1:, 0] < 0).all())  # delay 1; cooling lowers density


def _refinement(truth_cools: bool, theta_bounds, steps: int = 96):
    """Known model with theta0 = 1 (Kockarts-strength cooling) refined against a truth with or without NO cooling."""
    known = _known()
    truth = th.Column(dz=10e3, no_cooling=truth_cools, dt=DT, substeps=2)
    plant = th.ColumnBlock(truth, {"y": lambda x: truth.density_at(x, 407e3)}, x0=known.x0, name="plant")
    beta = -known.markov("u", "y", 49, inputs={"w": torch.tensor([[150.0, 0.0]], dtype=F64)})[:, 1:]
    ident = rt.RCOEstimator.static_gain({"y0": 3}, n_u=3, mask=torch.eye(3, dtype=torch.bool), p0=1.0,
                                        theta0=torch.eye(3, dtype=F64), markov=beta, first_delay=1,
                                        u_bounds=(0.0, math.inf), theta_bounds=theta_bounds)
    g = rt.refinement(known, ident, physical=plant, excitation=th.SpaceWeather(DT, peak=0.0))
    u = g.run(steps, record={"u": "identified.u"})["u"]
    return ident, u


def test_a_cooling_cannot_heat():
    """Against a truth *without* NO cooling, 4 days from theta = 1: the refinement must switch the cooling off.
    Without theta bounds theta overshoots below zero, and only the saturation u >= 0 (u_bounds) keeps the model
    from being heated; with theta_bounds = (0, 10) theta is projected onto the box and ends at zero."""
    free, u = _refinement(False, None)
    assert float(free.theta.min()) < -0.1 and float(u.min()) >= 0.0
    ident, u = _refinement(False, (0.0, 10.0))
    assert float(u.min()) >= 0.0 and float(u[-1].max()) < 0.02 * float(u[0].max())
    assert float(ident.theta.min()) >= 0.0 and float(ident.theta.max()) < 0.25


def test_space_weather_driver():
    drv = th.SpaceWeather(3600.0, f107=[120.0, 180.0], peak=[2.0, 4.0], start=2.0, rise=3.0)
    drv.reset(2)
    out = torch.stack([drv.step()["out"] for _ in range(12)], 1)      # hours 0..11
    assert torch.equal(out[:, :, 0], torch.tensor([[120.0] * 12, [180.0] * 12], dtype=F64))
    assert float(out[0, :3, 1].abs().max()) == 0.0
    assert float(out[0, 5, 1]) == pytest.approx(2.0) and float(out[1, 5, 1]) == pytest.approx(4.0)  # peak at 2 + 3 h


def test_scenario_checkpoint_resumes_exactly(tmp_path):
    """The recorded traces grow with the run; a resumed run loads them and continues as an uninterrupted one."""
    over = {"dz_km": 10.0, "Ts": 1800.0, "nu": 8, "refresh_every": 5, "spinup_days": 1.0, "markov_method": "fd"}
    full = Run("thermosphere-no-cooling", steps=16, overrides=over, out=tmp_path / "full")
    full.advance(progress=False)
    part = Run("thermosphere-no-cooling", steps=9, overrides=over, out=tmp_path / "part")
    part.advance(progress=False)
    part.save()
    part.close()                        # a live run holds its folder
    resumed = Run.resume(tmp_path / "part", steps=16)
    resumed.advance(progress=False)
    for name in ("known", "plant"):
        a, b = full.graph.blocks[name].history, resumed.graph.blocks[name].history
        assert a.shape == b.shape == (1, 16, a.shape[2]) and torch.equal(a, b)
    assert torch.equal(full.graph.blocks["identified"].theta, resumed.graph.blocks["identified"].theta)


def test_only_the_known_form_may_shape_the_cooling_by_the_kockarts_rate():
    """interpolate='strength' puts the Kockarts law into the known model: refused for the other structures, which
    'auto' interpolates in the cooling; the known form interpolates in the strength."""
    sc = rt.scenario.get("thermosphere-no-cooling")
    small = {"dz_km": 10.0, "Ts": 3600.0, "nu": 8, "refresh_every": 0, "spinup_days": 1.0}
    for structure, expected in (("kockarts", "strength"), ("temperature", "cooling"), ("error", "cooling")):
        g = sc.build(sc.resolve({**small, "structure": structure}), 1, F64, "cpu")
        assert g.role("known").column.interpolate == expected
    with pytest.raises(rt.ConfigError, match="interpolate='strength'.*structure='temperature'"):
        sc.build(sc.resolve({**small, "structure": "temperature", "interpolate": "strength"}), 1, F64, "cpu")
    g = sc.build(sc.resolve({**small, "interpolate": "cooling", "strengths": "node"}), 1, F64, "cpu")
    assert g.role("known").column.interpolate == "cooling" and g.role("estimator").n_theta == 3


@pytest.mark.slow
def test_scenario_meets_its_requirements_and_converges_to_the_true_strength(tmp_path):
    """Default settings (the known form, one strength of the Kockarts law, 407 km): the density error at 407 km
    cut to a few per cent of the initial model's, the NO cooling tracked at 152 km and over the profile, and the
    run converged, with the strength near the truth's 1 (the interpolation tapers the law to zero above 248 km,
    where the truth still cools a little: the strength ends a few per cent above 1).

    The verdict's theta_change equals the change recomputed from theta and the regressors recorded at every step
    (every regressor of the last day once: the checks are 9 steps apart, the estimator keeps 193)."""
    run = Run("thermosphere-no-cooling", out=tmp_path)
    est = run.graph.role("estimator")
    thetas, phis = [], []
    run.graph.add_hook(lambda g: (thetas.append(est.theta.detach().clone()), phis.append(est.phi_now.clone())))
    run.advance(progress=False)
    summary = run.finish(figures=True)
    failed = {k: v for k, v in summary["requirements"].items() if not v["pass"]}
    assert not failed, failed
    assert len(summary["requirements"]) == 3 and summary["diverged"] == []
    metrics = summary["metrics"]
    assert metrics["density_err_ratio"] < 0.05 and metrics["cooling_rel_rms_152km"] < 0.1
    assert metrics["cooling_profile_rel_rms"] < 0.1 and metrics["replay_cooling_rel_rms_152km"] < 0.1
    assert float(run.graph.blocks["known"].history[:, :, 1:4].min()) >= 0.0   # the estimated cooling never heats
    for fig in ("cooling_152km", "cooling_profiles", "density_error"):
        assert (tmp_path / f"{fig}.png").is_file()
    assert {"cooling_120km", "cooling_152km", "cooling_200km", "cooling_152km_true"} <= set(summary["estimates"])
    strength = est.theta.diagonal(dim1=1, dim2=2)
    assert torch.equal(strength, strength[:, :1].expand(-1, 3)) and 1.0 < float(strength[0, 0]) < 1.1
    health = summary["health"]
    start = health["criteria"]["window_start"]
    assert health["status"] == "converged" and start == 387 and health["z_ratio"] < 0.1
    theta_start, theta_end, phi = thetas[start - 1], thetas[-1], torch.stack(phis[start:])   # phi: (T, B, n)

    def rms(theta):
        return torch.sqrt((torch.einsum("bui,tbi->tbu", theta, phi) ** 2).sum(-1).mean(0))
    change = float(rms(theta_end - theta_start) / torch.maximum(rms(theta_end), rms(theta_start)))
    assert health["theta_change"] == pytest.approx(change, rel=1e-9) and change < 0.02
