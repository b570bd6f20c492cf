"""Change detection and tracking (rcotorch.estimator.tracking): the CUSUM against a plain loop of its equations,
its false
alarms on white noise, the covariance restart per member on both engines, and a change of the truth at a step."""

import numpy as np
import pytest
import torch

import rcotorch as rt
from rcotorch.engine import kernels
from rcotorch.estimator.tracking import FIRST, LAST, PENDING, G
from rcotorch.run.runner import Run
from rcotorch.run.scenario import Requirement

needs_native = pytest.mark.skipif(not kernels.available(), reason="the compiled engine is not built")


def cusum_reference(z, warmup, window, holdoff, drift, threshold):
    """The detector's equations for one member, written out with floats: z (steps, n_z) -> (g per step, alarm
    steps)."""
    n_z = z.shape[1]
    phase, g, ref, alarms, gs = 0, 0.0, np.zeros(n_z), [], []
    for k in range(z.shape[0]):
        s = 0.0
        for i in range(n_z):
            sigma2 = ref[i] / window if ref[i] > 0 else 1.0
            s += z[k, i] ** 2 / sigma2 / n_z
            if warmup <= phase < warmup + window:
                ref[i] += z[k, i] ** 2
        g = max(0.0, g + s - 1.0 - drift) if phase >= warmup + window else 0.0
        if g > threshold:
            alarms.append(k + 1)                 # the step after which the detector holds the alarm
            phase, g, ref = warmup - holdoff, 0.0, np.zeros(n_z)
        else:
            phase += 1
        gs.append(g)
    return np.array(gs), alarms


def noise_graph(batch, scale_at, scale, engine, seed=5, **detector):
    """z = white noise of std 1 (two channels), its std multiplied by ``scale`` from step ``scale_at`` on."""
    det = rt.ChangeDetector(2, **detector)
    g = rt.Graph([rt.WhiteNoise(2, seed=seed, name="w"), rt.Gain(np.eye(2), name="gain"), det],
                 [("w.out", "gain.in"), ("gain.out", "detector.z")], batch_size=batch)
    g.engine = engine
    g.add_hook(rt.at_step(scale_at, lambda gr: gr.blocks["gain"].K.mul_(scale)))
    return g, det


@pytest.mark.parametrize("engine", ["torch", pytest.param("native", marks=needs_native)])
def test_cusum_matches_its_equations_written_out(engine):
    settings = dict(warmup=50, window=100, holdoff=80, drift=0.5, threshold=12.0)
    g, det = noise_graph(3, 400, 1.6, engine, **settings)
    gs, zs = [], []
    for _ in range(900):
        g.advance(1)
        zs.append(g.last[("gain", "out")].clone())
        gs.append(det.x[:, G].clone())
    z, got = torch.stack(zs, 1).numpy(), torch.stack(gs, 1).numpy()
    for b in range(3):
        want, alarms = cusum_reference(z[b], **settings)
        np.testing.assert_allclose(got[b], want, rtol=1e-12, atol=1e-12)
        assert alarms and alarms[0] > 400                # the variance step is found, nothing before it
        assert int(det.x[b, FIRST]) == alarms[0] and int(det.x[b, LAST]) == alarms[-1]
        assert int(det.alarms()[b]) == len(alarms) == int(det.x[b, PENDING])


@needs_native
def test_no_false_alarm_on_white_noise_and_a_quick_detection():
    # 64 members, 20,000 steps of white noise; then the std grows by 30% (power x 1.69) at step 20,000.
    g, det = noise_graph(64, 20000, 1.3, "native", warmup=100, window=500, drift=0.5, threshold=40.0)
    g.advance(20000)
    assert int(det.alarms().sum()) == 0
    g.advance(2000)
    delay = det.first_alarm() - 20000
    assert bool((delay > 0).all())
    # g grows by about 1.69 - 1 - 0.5 = 0.19 a step: 40 / 0.19 = 210 steps on average
    assert 100 < float(delay.float().median()) < 400


def building(batch, engine, reset, device="cpu"):
    m, k, Ts = 2.0e4, 2.0e7, 0.01
    G_ = rt.models.shear_building([m] * 3, [k] * 3, force="base", measured=["velocity[1]", "velocity[2]",
                                                                              "velocity[3]"], identified=[1, 2, 3])
    known = rt.LTI.from_control(G_, inputs={"w": 1, "u": 3}, outputs={"y": 3, "y0": 3}, dt=Ts, name="known")
    ident = rt.RCOEstimator.static_gain({"y0": 3}, n_u=3, n_z=3, mask=np.eye(3, dtype=bool), p0=1e20)
    det = rt.ChangeDetector(3, warmup=200, window=200, holdoff=3000, threshold=30.0, dt=Ts)
    g = rt.refinement(known, ident, truth=rt.Gain(np.zeros((batch, 3, 3)), name="unknown"),
                      excitation=rt.WhiteNoise(1, seed=1), noise=rt.WhiteNoise(3, std=2e-4, seed=2), nu=100,
                      batch_size=batch, blocks=[det], connections=[("error.out", "detector.z")], device=device)
    g.engine = engine
    damage = torch.diag(torch.tensor([0.0, 0.2 * k, 0.0], dtype=torch.float64)).reshape(1, 3, 3)
    # only member 0's storey 2 softens: the others must keep their estimator as it was
    g.add_hook(rt.at_step(1000, lambda gr: gr.blocks["unknown"].K.copy_(
        torch.cat([damage, torch.zeros(batch - 1, 3, 3, dtype=torch.float64)]).to(gr.blocks["unknown"].K))))
    if reset:
        g.add_hook(rt.ResetOnChange(g, every=5, p0=1e14, lam=0.997, hold=300))
    return g, det


@pytest.mark.parametrize("engine", ["torch", pytest.param("native", marks=needs_native)])
def test_the_restart_acts_on_the_alarmed_member_only(engine):
    g, det = building(3, engine, reset=True)
    plain, _ = building(3, engine, reset=False)
    g.advance(999)
    plain.advance(999)
    est = g.role("estimator")
    assert est.lam.numel() == 1 or bool((est.lam == 1).all())
    while int(det.x[0, FIRST]) < 0 and int(g.k) < 1100:
        g.advance(1)
    alarm = int(det.x[0, FIRST])
    assert det.first_alarm().tolist()[1:] == [-1, -1] and 1000 < alarm <= 1010
    g.advance(-alarm % 5)                      # the hook acts at the next multiple of its 5 steps
    plain.advance(int(g.k) - int(plain.k))
    P, P_plain = est.P, plain.role("estimator").P
    assert torch.equal(P[1:], P_plain[1:])                       # untouched members run as without the hook
    assert torch.equal(P[0], 1e14 * torch.eye(3, dtype=torch.float64)) and int(det.x[0, PENDING]) == 0
    assert est.lam.tolist() == [0.997, 1.0, 1.0]
    g.advance(400)                                                # the hold ends: back to lam = 1
    assert est.lam.tolist() == [1.0, 1.0, 1.0]


@needs_native
def test_both_engines_track_alike():
    runs = {}
    for engine in ("torch", "native"):
        g, det = building(2, engine, reset=True)
        g.advance(1600)
        runs[engine] = (g.role("estimator").theta.clone(), det.x.clone())
    np.testing.assert_allclose(runs["native"][0].numpy(), runs["torch"][0].numpy(), rtol=1e-9, atol=1e-3)
    np.testing.assert_array_equal(runs["native"][1][:, :2].numpy(), runs["torch"][1][:, :2].numpy())   # phase, step
    np.testing.assert_allclose(runs["native"][1].numpy(), runs["torch"][1].numpy(), rtol=1e-9, atol=1e-12)
    assert runs["native"][1][0, FIRST] > 1000 and runs["native"][1][1, FIRST] == -1


def test_detection_and_restart_on_the_gpu():
    from virtual_cuda import virtual_cuda
    with virtual_cuda():
        g, det = building(2, "torch", reset=True, device="cuda")
        g.advance(1030)
        assert det.x.is_cuda and g.role("estimator").lam.is_cuda
        assert det.first_alarm().cpu().tolist()[1] == -1 and int(det.first_alarm()[0]) > 1000
        assert g.role("estimator").lam.cpu().tolist() == [0.997, 1.0]


def test_at_step_acts_once_at_its_step():
    g = rt.Graph([rt.WhiteNoise(1, seed=1, name="w"), rt.Gain([[1.0]], name="gain")], [("w.out", "gain.in")])
    seen = []
    g.add_hook(rt.at_step(3, lambda gr: seen.append(int(gr.k))))
    g.advance(10)
    assert seen == [3]


def test_bad_settings_are_refused():
    with pytest.raises(rt.ConfigError, match="detector"):
        rt.ChangeDetector(2, window=0)
    with pytest.raises(rt.ConfigError, match="threshold"):
        rt.ChangeDetector(2, threshold=-1.0)
    g = rt.Graph([rt.WhiteNoise(1, seed=1, name="w"), rt.Gain([[1.0]], name="gain")], [("w.out", "gain.in")])
    with pytest.raises(rt.ConfigError, match="no ChangeDetector named 'detector'"):
        rt.ResetOnChange(g)
    with pytest.raises(rt.ConfigError, match="at_step"):
        rt.at_step(0, print)


def test_the_damage_scenario_meets_its_requirements(tmp_path):
    run = Run("shear-building-damage", out=tmp_path)
    run.advance(progress=False)
    summary = run.finish(figures=False)
    assert len(summary["requirements"]) == 5 and all(r["pass"] for r in summary["requirements"].values())
    change = summary["changes"]["detector"]
    assert 6000 < change["first_alarm_step"] <= 6000 + 5 * 44.6 and change["alarms"] == 1
    assert change["first_alarm_s"] == pytest.approx(change["first_alarm_step"] * 0.01)


def test_a_resumed_damage_run_is_bitwise_the_same(tmp_path):
    # checkpointed after the change, the alarm, the restart (per-member forgetting under way) and the first
    # closed-loop Markov parameters
    kw = dict(steps=6400, batch=2, intervals=False, validation=False)
    full = Run("shear-building-damage", out=tmp_path / "full", **kw)
    full.advance(progress=False)
    part = Run("shear-building-damage", out=tmp_path / "part", **kw)
    part.advance(until=6303, progress=False)
    assert int(part.graph.blocks["detector"].alarms().sum()) == 2
    part.save()
    part.close()
    resumed = Run.resume(tmp_path / "part")
    resumed.advance(progress=False)
    a, b = full.graph.state_dict(), resumed.graph.state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[key], b[key]) for key in a)


def _stiffness_change_graph(batch=2):
    """A mass on a spring (m = 1, k = 0.6, c = 0.8, Ts = 0.01 s) whose stiffness rises by 0.5 at t = 20 s, a
    static gain on position and velocity that tracks it with forgetting, and a change detector on z."""
    known = rt.LTI.continuous([[0, 1], [-0.6, -0.8]], [[0, 0], [1, 1]], [[0, 1], [1, 0], [0, 1]], np.zeros((3, 2)),
                              inputs=["w", "u"], outputs={"y": 1, "y0": 2}, dt=0.01, name="known")
    truth = rt.Gain(np.zeros((1, 2)), name="unknown")
    ident = rt.RCOEstimator.static_gain({"y0": 2}, p0=1e3, lam=0.998)
    det = rt.ChangeDetector(1, warmup=1000, window=500, holdoff=1000, threshold=30.0)
    g = rt.refinement(known, ident, truth=truth, excitation=rt.WhiteNoise(1, seed=3), nu=15, batch_size=batch,
                      noise=rt.WhiteNoise(1, std=0.005, seed=4), blocks=[det],
                      connections=[("error.out", "detector.z")])
    g.add_hook(rt.at_step(2000, lambda gr: gr.blocks["unknown"].K.copy_(torch.tensor([[-0.5, 0.0]]))))
    return g


def test_a_changing_truth_is_drawn_as_it_was_and_the_alarm_is_marked(tmp_path):
    """A graph built in Python with ``truth_history``: TensorBoard's truth run holds the value in effect at each
    logged step, the |error| is against it, the detector's share of alarmed members is logged, and the
    estimate figure draws the truth as a step with a change line at 20 s and the first alarm after it."""
    from tensorboard.backend.event_processing.plugin_event_multiplexer import EventMultiplexer
    from tensorboard.util import tensor_util

    g = _stiffness_change_graph()
    result = rt.refine(g, 4000, {"dK": lambda gr: -gr.role("estimator").theta[:, 0, 0]},
                       truth_history={"dK": [(0.0, 0.0), (20.0, 0.5)]}, scales={"dK": 1.0}, out=tmp_path / "run",
                       intervals=False, validation=False, progress=False)
    assert result.summary["truth"] == {"dK": 0.5}
    change = result.summary["changes"]["detector"]
    first = change["first_alarm_step"]
    assert all(2000 < f < 2500 for f in first), first
    assert change["first_alarm_s"] == pytest.approx([f * 0.01 for f in first])     # the known model's Ts
    mux = EventMultiplexer(size_guidance={"scalars": 0, "tensors": 0})
    mux.AddRunsFromDirectory(str(tmp_path / "run"))
    mux.Reload()

    def values(run, tag):
        return {e.step: float(tensor_util.make_ndarray(e.tensor_proto)) for e in mux.Tensors(run, tag)}

    truth = values("truth", "Estimates/dK [-]")
    assert truth and all(v == (0.5 if k >= 2000 else 0.0) for k, v in truth.items())
    assert min(truth) < 2000 <= max(truth)
    est, err = values(".", "Estimates/dK [-]"), values(".", "Estimates/dK |error| [-]")
    for k in est:                                              # |error| against the truth of its step (B = 2)
        assert err[k] == pytest.approx(abs(est[k] - truth[k]), abs=0.5)
    before = [k for k in est if 1000 < k < 2000]
    # it tracked 0 before the change, within a few hundredths (lam = 0.998 remembers about 500 steps)
    assert before and all(err[k] < 0.1 for k in before)
    alarmed = values(".", "Model error/detector alarmed members [%]")
    assert all(v == 0.0 for k, v in alarmed.items() if k <= 2000) and alarmed[max(alarmed)] == 100.0

    from rcotorch.run.figures import run_figures
    figs = run_figures(result.run)
    ax = figs["estimates"].axes[0]
    lines = {line.get_label(): line for line in ax.get_lines()}
    xs, ys = lines["truth"].get_data()
    assert list(ys) == [0.0, 0.5, 0.5] and xs[1] == pytest.approx(20.0)
    assert lines["change"].get_xdata()[0] == pytest.approx(20.0)
    assert lines["detector: first alarm"].get_xdata()[0] == pytest.approx(first[0] * 0.01)
    # the alarm is drawn over the change's line and the truth, and marked at the top of the panel
    alarm = lines["detector: first alarm"]
    assert alarm.get_zorder() > max(lines["change"].get_zorder(), lines["truth"].get_zorder())
    marks = [line for line in ax.get_lines() if line.get_marker() == "v"]
    assert marks and marks[0].get_xdata()[0] == pytest.approx(first[0] * 0.01) and marks[0].get_ydata()[0] == 1.0


def test_a_run_that_ends_before_a_change_is_judged_against_the_truth_before_it(tmp_path):
    """A truth history whose change (20 s, step 2000) comes after the run's end: summary.json's truth, the
    requirement and the figures' final truth are the value before the change (0), not the final one (0.5); a
    run past the change is judged against 0.5."""
    est = {"dK": lambda gr: -gr.role("estimator").theta[:, 0, 0]}
    for steps, truth in ((1500, 0.0), (2600, 0.5)):
        result = rt.refine(_stiffness_change_graph(), steps, est, truth_history={"dK": [(0.0, 0.0), (20.0, 0.5)]},
                           scales={"dK": 1.0}, requirements=[Requirement("estimates.dK", "abs_err", 0.1)],
                           out=tmp_path / f"run{steps}", intervals=False, validation=False, progress=False)
        assert result.summary["truth"] == {"dK": truth}
        values = result.summary["estimates"]["dK"]
        check = result.summary["requirements"]["estimates.dK"]
        assert check["value"] == pytest.approx([abs(v - truth) for v in values])
        assert result.run.truth_now() == {"dK": truth} and result.run.truth == {"dK": 0.5}
        if steps == 1500:                    # it tracked 0 before the change: the requirement holds against 0
            assert check["pass"] and max(abs(v) for v in values) < 0.1


def test_a_truth_history_that_disagrees_with_the_truth_is_refused():
    g = _stiffness_change_graph(1)
    with pytest.raises(rt.ConfigError, match="ends at 0.4, but its truth is 0.5"):
        rt.refine(g, 10, {"dK": lambda gr: gr.role("estimator").theta[:, 0, 0]}, truth={"dK": 0.5},
                  truth_history={"dK": [(0.0, 0.0), (20.0, 0.4)]}, progress=False, intervals=False)
    with pytest.raises(rt.ConfigError, match="in time order"):
        rt.refine(g, 10, {"dK": lambda gr: gr.role("estimator").theta[:, 0, 0]},
                  truth_history={"dK": [(20.0, 0.0), (0.0, 0.5)]}, progress=False, intervals=False)
    with pytest.raises(rt.ConfigError, match="not an estimate"):
        rt.refine(g, 10, {"dK": lambda gr: gr.role("estimator").theta[:, 0, 0]},
                  truth_history={"dC": [(0.0, 0.0)]}, progress=False, intervals=False)


def test_a_run_whose_truth_changes_keeps_a_linear_time_axis(tmp_path):
    """A motor whose bearing friction grows at half time and is re-identified at once: the estimate's logged
    path settles early by the log-axis rule, but a run whose truth changes keeps a linear time axis (a log axis
    would squeeze the change into its last decade)."""
    from rcotorch.run.figures import log_time_axis, run_figures
    J, b, Kt, Ts = 0.02, 0.05, 0.1, 0.005
    known = rt.LTI.continuous([[-b / J]], [[Kt / J, 1 / J]], [[1.0], [1.0]], [[0, 0], [0, 0]],
                              inputs=["w", "u"], outputs={"y": 1, "y0": 1}, dt=Ts, name="motor")
    det = rt.ChangeDetector(1, warmup=1000, window=1000, holdoff=2000, threshold=30.0)
    g = rt.refinement(known, rt.RCOEstimator.static_gain({"y0": 1}, p0=1e3, lam=0.998),
                      truth=rt.Gain(np.zeros((1, 1)), name="wear"), excitation=rt.WhiteNoise(1, std=2.0, seed=1),
                      noise=rt.WhiteNoise(1, std=0.01, seed=5), nu=40, blocks=[det],
                      connections=[("error.out", "detector.z")])
    g.add_hook(rt.at_step(6000, lambda gr: gr.blocks["wear"].K.fill_(-0.03)))
    g.add_hook(rt.ResetOnChange(g, every=5, p0=1e3, lam=0.99, hold=1000))
    result = rt.refine(g, 12000, {"db": lambda gr: -gr.role("estimator").theta[:, 0, 0]},
                       truth_history={"db": [(0.0, 0.0), (30.0, 0.03)]}, out=tmp_path / "run", intervals=False,
                       validation=False, progress=False, figures=False, log_every=480)
    h = result.run.history
    t = np.asarray(h["step"], dtype=float) * Ts
    assert log_time_axis(t, [torch.stack(h["db"]).numpy()])       # by its settling alone: a log axis
    assert run_figures(result.run)["estimates"].axes[0].get_xscale() == "linear"


def test_the_band_over_time_widens_at_the_change_and_narrows_again(tmp_path):
    """The confidence band through a run: wide at the start, narrow before the change, wide again after it (the
    restarted P and the model error the old estimate leaves), as narrow as the final interval at the end."""
    run = Run("shear-building-damage", batch=2, out=tmp_path)
    run.advance(progress=False)
    summary = run.finish(figures=False)
    steps, bands = run.band_over_time()
    steps = np.asarray(steps)
    hw = bands["dk2"].numpy()                                                     # (T, members)
    kd = run.scenario.change_step(run.settings)
    before = hw[np.flatnonzero(steps < kd)[-1]]
    after = hw[(steps > kd) & (steps <= kd + 300)].max(0)           # the widest in the 3 s after the change
    assert np.all(hw[0] > 10 * before) and np.all(after > 10 * before)
    final = np.asarray(summary["intervals"]["dk2"]["upper"]) - np.asarray(summary["estimates"]["dk2"])
    np.testing.assert_allclose(hw[-1], final, rtol=1e-9)
    assert np.all(hw[-1] < after / 10)


def _two_mass(nc, proper, feed_u=True, dtype=torch.float64):
    """Two masses on springs (m = 1, k = 1 and 0.5, c = 0.1), u a force pair on the second spring's drift, y the
    velocities and y0 the drift: a refinement whose loop u = theta phi(y0) the tests close."""
    A = [[0, 1, 0, 0], [-1.5, -0.1, 0.5, 0], [0, 0, 0, 1], [0.5, 0, -0.5, -0.1]]
    B = [[0, 0], [1, 1], [0, 0], [0, -1]]
    C = [[0, 1, 0, 0], [0, 0, 0, 1], [-1, 0, 1, 0]]
    known = rt.LTI.continuous(A, B, C, np.zeros((3, 2)), inputs=["w", "u"], outputs={"y": 2, "y0": 1},
                              dt=0.05, name="known", dtype=dtype)
    ident = rt.RCOEstimator({"y0": 1}, n_u=1, n_z=2, nc=nc, proper=proper, feed_u=feed_u, dtype=dtype)
    g = rt.refinement(known, ident, truth=rt.Gain(np.zeros((1, 1)), name="unknown"),
                      excitation=rt.WhiteNoise(1, seed=1), nu=30, batch_size=3, blocks=[rt.ChangeDetector(2)],
                      connections=[("error.out", "detector.z")], dtype=dtype)
    return g, known


def test_closed_loop_markov_of_a_static_gain_is_python_controls_feedback():
    import control

    from rcotorch.estimator.tracking import closed_loop_markov
    g, known = _two_mass(0, True)
    est = g.role("estimator")
    theta = torch.tensor([[[0.3]], [[-0.2]], [[0.0]]], dtype=torch.float64)
    beta = closed_loop_markov(g, theta)
    assert beta.shape == (3, est.nu, 2, 1)
    np.testing.assert_allclose(beta[2].numpy(), est.beta[0].numpy(), rtol=0, atol=1e-15)      # theta = 0: open
    Ad, Bd = known.A[0].numpy(), known.B[0].numpy()[:, 1:]
    G = control.ss(Ad, Bd, known.C[0].numpy(), np.zeros((3, 1)), 0.05)                  # u -> [y; y0]
    for b in range(2):
        K = control.ss([], [], [], [[0.0, 0.0, float(theta[b, 0, 0])]], 0.05)          # [y; y0] -> u
        cl = control.feedback(G, K, sign=1)                                             # v -> [y; y0]
        T = np.arange(est.first_delay + est.nu) * 0.05
        resp = np.asarray(control.impulse_response(cl, T=T).y)[:2, 0] * 0.05         # a unit pulse, (2, steps)
        np.testing.assert_allclose(-beta[b, :, :, 0].numpy().T, resp[:, est.first_delay:], rtol=1e-9, atol=1e-14)


@pytest.mark.parametrize("feed_u", [True, False])
def test_closed_loop_markov_of_a_dynamic_subsystem_is_the_loop_simulated(feed_u):
    """nc = 2, strictly proper: u(k) = a1 y0(k-1) + a2 y0(k-2) [+ b1 u(k-1) + b2 u(k-2)] + v(k), simulated step
    by step with the known model's matrices against the closed-loop Markov parameters."""
    from rcotorch.estimator.tracking import closed_loop_markov
    g, known = _two_mass(2, False, feed_u=feed_u)
    est = g.role("estimator")
    theta = torch.tensor([[[0.4, -0.25, 0.3, 0.1][:est.n_phi]]], dtype=torch.float64).expand(3, -1, -1)
    beta = closed_loop_markov(g, theta)
    Ad, B, C, D = (M[0].numpy() for M in (known.A, known.B, known.C, known.D))
    a1, a2 = theta[0, 0, :2].tolist()
    b1, b2 = theta[0, 0, 2:].tolist() if feed_u else (0.0, 0.0)
    x, y0s, us, ys = np.zeros(4), [0.0, 0.0], [0.0, 0.0], []
    for k in range(est.first_delay + est.nu):
        u = a1 * y0s[-1] + a2 * y0s[-2] + b1 * us[-1] + b2 * us[-2] + (1.0 if k == 0 else 0.0)
        out = C @ x + D[:, 1] * u
        ys.append(out[:2])
        y0s.append(out[2])
        us.append(u)
        x = Ad @ x + B[:, 1] * u
    np.testing.assert_allclose(-beta[0, :, :, 0].numpy(), np.array(ys)[est.first_delay:], rtol=1e-9, atol=1e-14)


def test_closed_loop_tracking_is_refused_on_markov_parameters_not_the_known_models():
    g, _ = _two_mass(0, True)
    rt.ResetOnChange(g, markov="closed-loop")                    # the graph's own: accepted
    est = g.role("estimator")
    est.set_markov(2 * est.beta, est.first_delay)
    with pytest.raises(rt.ConfigError, match="not those of its known model"):
        rt.ResetOnChange(g, markov="closed-loop")
    with pytest.raises(rt.ConfigError, match="markov must be"):
        rt.ResetOnChange(g, markov="closed")
    with pytest.raises(rt.ConfigError, match="markov_after"):
        rt.ResetOnChange(g, markov_after=-1)
    dynamic, _ = _two_mass(2, False)
    with pytest.raises(rt.ConfigError, match="needs a static identified subsystem"):
        rt.ResetOnChange(dynamic, markov="closed-loop")


def _damage(storey, change, markov, batch, engine="auto"):
    from rcotorch.run import scenario as scenarios
    sc = scenarios.get("shear-building-damage")
    s = sc.resolve({"storey": storey, "change": change, "track_markov": markov})
    g = sc.build(s, batch, torch.float64, "cpu")
    g.engine = engine
    return sc, s, g


def test_the_loop_closed_at_the_estimate_follows_a_change_the_known_models_markov_parameters_miss():
    """Storey 3 loses 30%: with the known model's own Markov parameters the estimates wander (the loop's modes
    have moved, and over the one-second window the open-loop parameters are out of phase with them); closed at
    the present estimate, every member is within 2% of the new stiffness 50 periods after the change."""
    errors = {}
    for markov in ("open-loop", "closed-loop"):
        sc, s, g = _damage(3, -0.3, markov, 8)
        g.advance(sc.steps)
        d = torch.stack(list(sc.estimates(g, s).values()), 1)
        errors[markov] = (d - torch.tensor([0.0, 0.0, -0.3], dtype=d.dtype)).abs().amax(1)
    assert float(errors["closed-loop"].max()) < 0.016
    assert float(errors["open-loop"].median()) > 0.03
    est = g.role("estimator")
    assert est.beta.shape[0] == 8        # one set per member from the start


@needs_native
def test_both_engines_close_the_loop_alike():
    thetas = {}
    for engine in ("torch", "native"):
        sc, s, g = _damage(2, -0.2, "closed-loop", 2, engine)
        g.advance(6600)
        est = g.role("estimator")
        assert not torch.equal(est.beta[0], est.beta[0].new_zeros(()).expand_as(est.beta[0]))
        thetas[engine] = (est.theta.clone(), est.beta.clone())
    np.testing.assert_allclose(thetas["native"][1].numpy(), thetas["torch"][1].numpy(), rtol=1e-7, atol=1e-14)
    np.testing.assert_allclose(thetas["native"][0].numpy(), thetas["torch"][0].numpy(), rtol=1e-7, atol=1e-3)


def test_closed_loop_markov_is_the_same_in_the_kernel_and_in_pytorch():
    from rcotorch.estimator.tracking import closed_loop_markov
    for nc, proper in ((0, True), (2, False), (1, True)):
        g, _ = _two_mass(nc, proper)
        est = g.role("estimator")
        gen = torch.Generator().manual_seed(nc)
        theta = 0.3 * torch.randn(3, est.n_u, est.n_phi, dtype=torch.float64, generator=gen)
        native = closed_loop_markov(g, theta)
        with kernels.disabled():
            torch_only = closed_loop_markov(g, theta)
        np.testing.assert_allclose(native.numpy(), torch_only.numpy(), rtol=1e-10, atol=1e-15)


@pytest.mark.parametrize("engine", ["torch", pytest.param("native", marks=needs_native)])
def test_the_loop_is_closed_for_the_alarmed_member_only_and_renewed_where_its_estimate_moved(engine):
    from rcotorch.engine import lowering
    g, det = building(3, engine, reset=False)
    hook = rt.ResetOnChange(g, every=5, p0=1e14, lam=0.997, hold=300, markov="closed-loop", markov_after=50)
    g.add_hook(hook)
    est = g.role("estimator")
    open_loop = est.beta.clone()
    g.advance(1000)
    while int(det.x[0, FIRST]) < 0:
        g.advance(1)
    alarm = int(det.x[0, FIRST])
    g.advance(alarm + 50 + (-(alarm + 50) % 5) - int(g.k))          # the first renewal: member 0 alone
    assert est.beta.shape[0] == 3
    assert torch.equal(est.beta[1:], open_loop.expand(2, -1, -1, -1))
    assert not torch.allclose(est.beta[0], open_loop[0], rtol=1e-3, atol=0)
    np.testing.assert_array_equal(est.theta_closed[0].numpy(), est.theta[0].numpy())
    assert float(est.theta_closed[1:].abs().max()) == 0.0
    prog = lowering.program(g) if engine == "native" else None
    g.advance(5)                                                      # renewed in place: the same program
    assert not torch.equal(est.theta_closed[0], est.theta[0].new_zeros(()).expand_as(est.theta[0]))
    np.testing.assert_array_equal(est.theta_closed[0].numpy(), est.theta[0].numpy())
    if engine == "native":
        assert lowering.program(g) is prog
    # a tolerance the estimate's moves stay below: the parameters are not renewed
    hook.markov_tol = 1e9
    kept = est.beta.clone()
    g.advance(20)
    assert torch.equal(est.beta, kept)


def test_markov_parameters_of_some_members_keep_their_shape_and_delay():
    g, _ = _two_mass(0, True)
    est = g.role("estimator")
    with pytest.raises(rt.DimensionError, match="Markov parameters of 1 members"):
        est.set_markov(est.beta[:, :3], est.first_delay, members=[0])
    with pytest.raises(rt.ConfigError, match="first delay"):
        est.set_markov(est.beta, est.first_delay + 1, members=[0])
    est.set_markov(2 * est.beta, est.first_delay, members=[1])
    assert torch.equal(est.beta[1], 2 * est.beta[0]) and torch.equal(est.beta[0], est.beta[2])


def test_the_loop_is_closed_on_the_gpu():
    from virtual_cuda import virtual_cuda
    with virtual_cuda():
        g, det = building(2, "torch", reset=False, device="cuda")
        g.add_hook(rt.ResetOnChange(g, every=5, p0=1e14, lam=0.997, hold=300, markov="closed-loop",
                                    markov_after=20))
        est = g.role("estimator")
        open_loop = est.beta.clone()
        g.advance(1060)
        assert est.beta.is_cuda and est.theta_closed.is_cuda and est.beta.shape[0] == 2
        assert int(det.first_alarm()[0]) > 1000 and int(det.first_alarm()[1]) == -1
        assert torch.equal(est.beta[1], open_loop[0]) and not torch.equal(est.beta[0], open_loop[0])


def test_a_loop_that_cannot_be_closed_is_named():
    A = [[0, 1], [-1.0, -0.1]]
    known = rt.LTI.continuous(A, [[0, 0], [1, 1]], [[0, 1], [1, 0]], np.zeros((2, 2)), inputs=["w", "u"],
                              outputs={"y": 1, "y0": 1}, dt=0.05, name="known")
    # a regressor fed through another block: its path from u is not the known model's alone
    ident = rt.RCOEstimator.static_gain({"y0": 1}, n_z=1)
    g = rt.refinement(known, ident, truth=rt.Gain([[0.0]], name="unknown"), excitation=rt.WhiteNoise(1, seed=1),
                      nu=10, blocks=[rt.Gain([[2.0]], name="scale"), rt.ChangeDetector(1)],
                      connections=[("known.y0", "scale.in"), ("error.out", "detector.z")],
                      feeds={"y0": "scale.out"})
    with pytest.raises(rt.ConfigError, match="'identified.y0' is fed by 'scale.out'"):
        rt.ResetOnChange(g, markov="closed-loop")
    # features: the loop is not linear in the known model's state
    ident = rt.RCOEstimator({"y0": 1}, n_u=1, n_z=1, nc=0, proper=True, features={"cube": lambda s: s["y0"] ** 3})
    g = rt.refinement(known, ident, truth=rt.Gain([[0.0]], name="unknown"), excitation=rt.WhiteNoise(1, seed=1),
                      nu=10)
    with pytest.raises(rt.ConfigError, match="has features"):
        rt.closed_loop_markov(g)


def test_a_loop_the_estimate_makes_unstable_keeps_the_markov_parameters_it_had():
    """u = theta (x2 - x1) adds theta to the second spring's stiffness (0.5): theta < -0.5 makes it a negative spring
    and the loop unstable; that member keeps the known model's own parameters, the other gets its loop's."""
    g, _ = _two_mass(0, True)
    hook = rt.ResetOnChange(g, every=5, hold=100, markov="closed-loop")
    est, det = g.role("estimator"), g.blocks["detector"]
    open_loop = est.beta.clone()
    est.theta[:, 0, 0] = torch.tensor([-0.8, 0.2, 0.0], dtype=torch.float64)
    det.x[:, LAST] = 0.0                                  # every member alarmed at step 0
    assert hook(g)
    assert torch.equal(est.beta[0], open_loop[0]) and float(est.theta_closed[0].abs().max()) == 0.0
    assert not torch.equal(est.beta[1], open_loop[0]) and float(est.theta_closed[1, 0, 0]) == 0.2
    assert torch.equal(est.beta[2], open_loop[0])          # theta = 0: its loop is the known model


def test_the_loop_is_closed_in_float32():
    g, _ = _two_mass(0, True, dtype=torch.float32)
    hook = rt.ResetOnChange(g, every=5, hold=100, markov="closed-loop")      # the float32 parameters are accepted
    est, det = g.role("estimator"), g.blocks["detector"]
    assert est.beta.dtype == torch.float32
    est.theta[:, 0, 0] = torch.tensor([0.3, 0.2, 0.0])
    det.x[:, LAST] = 0.0
    assert hook(g)
    g64, _ = _two_mass(0, True)
    reference = rt.closed_loop_markov(g64, est.theta.double())                # the same loop in float64
    assert est.beta.dtype == torch.float32
    np.testing.assert_allclose(est.beta.double().numpy(), reference.numpy(), rtol=1e-4, atol=1e-9)


def _markov_reference(A, B, C, D, d, nu):
    """-H_(d+t), t = 0..nu-1, of one system, H_0 = D, H_i = C A^(i-1) B, with NumPy's matrix power."""
    H = [D if i == 0 else C @ np.linalg.matrix_power(A, i - 1) @ B for i in range(d, d + nu)]
    return -np.stack(H)


@needs_native
@pytest.mark.parametrize("d", [0, 1, 3])
def test_the_markov_kernel_writes_each_layout_and_only_the_loops_it_shows_stable(d):
    """Seven systems (a chunk of lanes and part of another), written into rows 9, 2, .. of a (nu, p, m) tensor and
    of the reversed ring the native program reads (two copies of [beta reversed, d zeros]); the rows not named
    keep what they held. With the stability test, a loop of spectral radius 1.02 is not written, 0.999 and 0.5
    are, and one at 1 - 1e-9 is left to the eigenvalues (not shown stable by 16 squarings)."""
    Bm, N, m, p, nu = 7, 4, 2, 3, 5
    gen = np.random.default_rng(d)
    radius = [0.5, 0.999, 1.02, 0.9, 1 - 1e-9, 0.7, 0.3]
    A = []
    for r in radius:
        Q = np.linalg.qr(gen.standard_normal((N, N)))[0]
        angles = gen.uniform(0.1, 3.0, N // 2)
        blocks = [r * np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]]) for t in angles]
        A.append(Q @ np.block([[blocks[0], np.zeros((2, 2))], [np.zeros((2, 2)), blocks[1]]]) @ Q.T)
    A, B, C, D = np.stack(A), gen.standard_normal((Bm, N, m)), gen.standard_normal((Bm, p, N)), \
        gen.standard_normal((Bm, p, m))
    As, Bs, Cs, Ds = (torch.tensor(x) for x in (A, B, C, D))
    rows = torch.tensor([9, 2, 0, 5, 7, 3, 1])
    W, pm = nu + d, p * m
    beta = torch.full((10, nu, p, m), 7.0, dtype=torch.float64)
    ring = torch.full((10, pm, 2 * W), 7.0, dtype=torch.float64)
    ring[..., nu:W] = ring[..., W + nu:] = 0.0
    targets = [kernels.MarkovTarget(beta, offset=0, row_stride=nu * pm, step_stride=pm, entry_stride=1),
               kernels.MarkovTarget(ring, offset=nu - 1, row_stride=pm * 2 * W, step_stride=-1, entry_stride=2 * W,
                                    copies=2, copy_stride=W)]
    versions = beta._version, ring._version
    written = kernels.lti_markov(As, Bs, Cs, Ds, d, nu, targets, rows=rows, stable=True)
    np.testing.assert_array_equal(written.numpy(), [True, True, False, True, False, True, True])
    assert beta._version > versions[0] and ring._version > versions[1]          # written, as PyTorch would say
    for b in range(Bm):
        row = int(rows[b])
        if written[b]:
            ref = _markov_reference(A[b], B[b], C[b], D[b], d, nu)
            np.testing.assert_allclose(beta[row].numpy(), ref, rtol=1e-12, atol=1e-12)
            laid = ref[::-1].reshape(nu, pm).T                        # entry e, delay nu - 1 - j at column j
            for c in range(2):
                np.testing.assert_allclose(ring[row, :, c * W:c * W + nu].numpy(), laid, rtol=1e-12, atol=1e-12)
                assert np.abs(ring[row, :, c * W + nu:(c + 1) * W].numpy()).max(initial=0.0) == 0.0
        else:
            assert bool((beta[row] == 7.0).all()) and bool((ring[row, :, :nu] == 7.0).all())
    for row in (4, 6, 8):                                             # no member of the call
        assert bool((beta[row] == 7.0).all())
    # without the test every member is written; without targets the parameters come back, the same bits
    kernels.lti_markov(As, Bs, Cs, Ds, d, nu, targets, rows=rows)
    alone = kernels.lti_markov(As, Bs, Cs, Ds, d, nu)
    assert torch.equal(alone, beta[rows])
    with pytest.raises(ValueError, match="written at"):
        kernels.lti_markov(As, Bs, Cs, Ds, d, nu, targets, rows=rows + 1)
    with pytest.raises(TypeError, match="MarkovTarget"):
        kernels.lti_markov(As, Bs, Cs, Ds, d, nu, [tuple(targets[0])], rows=rows)


@needs_native
@pytest.mark.parametrize("shown", [True, False])
def test_the_native_renewal_writes_stable_loops_in_place_and_keeps_the_others(shown, monkeypatch):
    """On the native engine, with its program made and one set of Markov parameters per member: theta = -0.8
    makes member 0's loop unstable, member 1's loop is stable. Member 1 gets its loop's parameters (PyTorch's
    computation to rounding), in beta and in the program's copy, and the program stays; member 0 keeps its own.
    ``shown=False``: the kernel's test shows no loop stable, and the eigenvalues decide alike."""
    from rcotorch.engine import lowering
    from rcotorch.estimator.tracking import closed_loop_markov
    g, _ = _two_mass(0, True)
    g.engine = "native"
    hook = rt.ResetOnChange(g, every=5, hold=10_000, markov="closed-loop")
    g.add_hook(hook)
    est, det = g.role("estimator"), g.blocks["detector"]
    est.theta[:, 0, 0] = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    det.x[:, LAST] = 0.0
    g.advance(5)                                           # the first renewal: one set per member from here on
    assert est.beta.shape[0] == 3 and g.ran_engine == "native"
    prog = lowering.program(g)
    if not shown:
        plain = kernels.lti_markov
        monkeypatch.setattr(kernels, "lti_markov", lambda *a, stable=False, **k: torch.zeros(
            a[0].shape[0], dtype=torch.bool) if stable else plain(*a, **k))
    kept, closed = est.beta[0].clone(), est.theta_closed[0].clone()
    est._beta_padded()                                     # what the PyTorch engine derives from beta, kept
    est.theta[:, 0, 0] = torch.tensor([-0.8, 0.25, 0.3], dtype=torch.float64)
    assert hook(g)
    assert lowering.program(g) is prog
    with kernels.disabled():
        reference = closed_loop_markov(g, est.theta.clone())
    assert torch.equal(est.beta[0], kept)
    np.testing.assert_allclose(est.beta[1].numpy(), reference[1].numpy(), rtol=1e-10, atol=1e-15)
    assert torch.equal(est.theta_closed[0], closed)
    np.testing.assert_array_equal(est.theta_closed[1:, 0, 0].numpy(), [0.25, 0.3])
    ring = est._lowered_ring()
    np.testing.assert_array_equal(ring.numpy(), est._laid_out(est.beta, 2).numpy())
    # what the PyTorch engine derived from beta follows the kernel's write (beta's version moved with it)
    assert torch.equal(est._beta_padded(), est._laid_out(est.beta, 1))


def test_a_checkpoint_with_the_transposed_markov_parameters_of_earlier_versions_loads():
    """Earlier versions kept beta also as 'beta_t' (n_z n_u, nu), made from beta; a checkpoint holding it loads
    strictly, beta alone deciding."""
    g, _ = _two_mass(0, True)
    est = g.role("estimator")
    state = est.state_dict()
    assert "beta_t" not in state
    state["beta_t"] = state["beta"].flatten(2).mT.contiguous()
    state["beta"] = 2 * state["beta"]
    fresh, _ = _two_mass(0, True)
    fresh.role("estimator").load_state_dict(state)
    assert torch.equal(fresh.role("estimator").beta, 2 * est.beta)
