"""The figures of runs and sweeps: units, the truth drawn on top, legends that list what is drawn and sit outside
the axes, a logarithmic time axis where the estimates settle early, the initial model's error beside the refined
one's, a sweep's estimates and errors against its swept settings."""

import dataclasses
import os
import signal
import threading

import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import PathCollection
from matplotlib.colors import to_rgba

from rcotorch.run import figures as figures_module
from rcotorch.run.figure_data import run_figure_data
from rcotorch.run.figures import draw_meanwhile, frequency_figure, log_time_axis, png, pngs, run_figures, sweep_figures
from rcotorch.run.runner import Run


def _overlaps(a, b) -> bool:
    return a.x0 < b.x1 and b.x0 < a.x1 and a.y0 < b.y1 and b.y0 < a.y1


def _legends_clear_of_axes(fig) -> None:
    """Every legend of the figure lies outside every axes' plotting area and its x label, and within the
    figure (after a drawing laid them out)."""
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    renderer = canvas.get_renderer()
    legends = list(fig.legends) + [leg for sub in fig.subfigs for leg in sub.legends]
    legends += [ax.get_legend() for ax in fig.axes if ax.get_legend() is not None]
    assert legends
    whole = fig.bbox
    for legend in legends:
        box = legend.get_window_extent(renderer)
        inside = whole.x0 - 1 <= box.x0 and box.x1 <= whole.x1 + 1 and whole.y0 - 1 <= box.y0 <= box.y1 <= whole.y1 + 1
        assert inside, (legend, box, whole)
        for ax in fig.axes:
            assert not _overlaps(box, ax.get_window_extent(renderer)), (legend, ax)
            label = ax.xaxis.label
            if label.get_text():
                assert not _overlaps(box, label.get_window_extent(renderer)), (legend, label.get_text())


@pytest.fixture(scope="module")
def single(tmp_path_factory):
    run = Run("sdof-stiffness", steps=2000, out=tmp_path_factory.mktemp("r") / "r", log_every=20)
    run.advance(progress=False)
    summary = run.summary()
    yield run, summary, run_figures(run)
    run.close()


def test_run_figures_carry_units_legends_and_the_truth_on_top(single):
    run, _, figs = single
    fig = figs["estimates"]
    left = fig.axes[::2]                                   # the left column: the whole run (right: the window)
    assert [a.get_ylabel() for a in left] == ["dK [N/m]", "dC [N s/m]"] and len(fig.axes) == 4
    assert left[-1].get_xlabel().startswith("time [s]")
    (legend,) = fig.legends                               # one legend for the figure, below the axes
    # the continuous truth of sdof-stiffness as shipped makes dC biased: where its physics' value lies is marked
    assert [t.get_text() for t in legend.get_texts()] == ["estimate", "95% band over time", "truth", "initial model",
                                                          "95% interval at the end", "estimate - bias (biased)"]
    for ax in fig.axes:
        lines = {ln.get_label(): ln for ln in ax.get_lines()}
        truth = [ln for ln in ax.get_lines() if ln.get_linestyle() == "--" and to_rgba(ln.get_color()) == to_rgba("k")]
        assert truth, ax                                   # the truth: dashed, black, in every panel
        estimates = [ln for ln in ax.get_lines() if ln not in truth and ln.get_label() != "initial model"]
        assert min(t.get_zorder() for t in truth) > max(ln.get_zorder() for ln in estimates)   # drawn above them
        if "initial model" in lines:
            assert lines["initial model"].get_ydata()[0] == 0.0          # theta starts at zero: dK = 0
    _legends_clear_of_axes(fig)


def test_the_model_error_figure_sets_the_initial_model_beside_the_refined_one(single):
    run, summary, figs = single
    fig = figs["model_error"]
    top, bottom = fig.axes[:2]
    assert top.get_ylabel() == "rms of z = y - y_hat [m/s]" and bottom.get_ylabel() == "z = y - y_hat [m/s]"
    labels = [ln.get_label() for ln in top.get_lines()]
    assert labels == ["refined model, during the run", "initial model, held-out data (member 0)",
                      "refined model, held-out data (member 0)"]
    held = {ln.get_label(): ln.get_ydata()[0] for ln in top.get_lines()[1:]}
    metrics = summary["metrics"]
    assert held["initial model, held-out data (member 0)"] == pytest.approx(metrics["validation_rmse_initial"])
    assert held["refined model, held-out data (member 0)"] == pytest.approx(metrics["validation_rmse"])
    initial, refined = bottom.get_lines()
    # the plotted z of each model on the held-out data has the rms the validation reports
    for line, key in ((initial, "validation_rmse_initial"), (refined, "validation_rmse")):
        assert np.sqrt(np.mean(line.get_ydata() ** 2)) == pytest.approx(summary["metrics"][key], rel=1e-9)
        assert f"rms {summary['metrics'][key]:.3g} m/s" in line.get_label()
    _legends_clear_of_axes(fig)


def test_a_log_time_axis_where_the_estimates_settle_early_and_not_where_they_change_late():
    t = np.arange(1, 1001) * 0.1
    settle = 1 - np.exp(-t / 2.0)                          # settled within 10% of the run
    late = np.where(t > 60, 1.0, 0.0) + 0.01 * np.sin(t)   # a change in the second half (tracking)
    assert log_time_axis(t, [settle[:, None]])
    assert not log_time_axis(t, [settle[:, None], late[:, None]])
    assert not log_time_axis(t[-10:], [settle[-10:, None]])          # less than two decades of time
    assert not log_time_axis(np.arange(0, 1000) * 0.1, [settle])     # starts at 0


def test_a_run_whose_estimates_settle_early_is_drawn_on_a_log_time_axis(single):
    run, _, figs = single
    h = run.history
    series = [np.stack([v.numpy() for v in h[k]]) for k in ("dK", "dC")]
    t = np.asarray(h["step"], dtype=float) * 0.01
    expected = "log" if log_time_axis(t, series) else "linear"
    assert figs["estimates"].axes[0].get_xscale() == expected == figs["model_error"].axes[0].get_xscale()


def test_a_batch_figure_draws_the_traced_members(tmp_path):
    batch = Run("sdof-stiffness", steps=100, batch=12, out=tmp_path / "b", log_every=20, trace=[2, 5, 9])
    batch.advance(progress=False)
    fig = run_figures(batch)["estimates"]
    assert [t.get_text() for t in fig.legends[0].get_texts()][:3] == ["member 2", "member 5", "member 9"]
    assert "(3 of 12 members)" in fig.axes[0].get_title()
    batch.close()


def test_frequency_figures_draw_the_truth_dashed_on_top_and_the_legend_below():
    omega = np.logspace(-1, 2, 50)
    true = 1 / (1j * omega + 1)
    fig = frequency_figure(omega, {"initial model": 0.8 * true, "true system": true, "refined model": true,
                                   "true system, sampled": 1.01 * true}, "test", nyquist=50.0, unit="V/V",
                           bands={"95% band": (0.9 * np.abs(true), 1.1 * np.abs(true))})
    mag = fig.axes[0]
    lines = {ln.get_label(): ln for ln in mag.get_lines()}
    trues = [lines["true system"], lines["true system, sampled"]]
    others = [lines["initial model"], lines["refined model"]]
    assert min(t.get_zorder() for t in trues) > max(o.get_zorder() for o in others)
    assert to_rgba(lines["true system"].get_color()) == to_rgba("k")
    assert all(t.get_linestyle() == "--" for t in trues)
    assert [t.get_text() for t in fig.legends[0].get_texts()] == ["95% band", "initial model", "true system",
                                                                  "refined model", "true system, sampled",
                                                                  "Nyquist frequency"]
    _legends_clear_of_axes(fig)


def _rows():
    rows = []
    for m, (dK, p0, basis) in enumerate([(0.3, 1e1, "a"), (0.5, 1e3, "b"), (0.7, 1e5, "a"), (0.3, 1e5, "b")]):
        est = dK + 0.01 * (m + 1)
        rows.append({"member": m, "dK": dK, "p0": p0, "basis": basis, "seed": m, "est_dK": est, "truth_dK": dK,
                     "err_dK": est - dK, "est_dC": 0.1, "truth_dC": 0.0, "err_dC": 0.1,
                     "status": ["converged", "not_converged", "diverged", "converged"][m]})
    return rows


def test_sweep_figures_draw_each_estimate_and_error_against_each_swept_setting():
    rows = _rows()
    figs = sweep_figures(rows, ["dK", "p0", "basis"], "sdof-stiffness")
    assert sorted(figs) == ["sweep_basis", "sweep_dK", "sweep_p0"]
    fig = figs["sweep_p0"]
    axes = fig.axes
    assert [a.get_ylabel() for a in axes] == ["dK [N/m]", "|error| of dK [N/m]", "dC [N s/m]", "|error| of dC [N s/m]"]
    assert axes[-1].get_xlabel() == "p0" and axes[-1].get_xscale() == "log"        # four decades of p0
    # each member's estimate against its p0, coloured by its status; the truth as black crosses on top
    points = {}
    for coll in axes[0].collections:
        for (x, y) in coll.get_offsets():
            points.setdefault(coll.get_label(), []).append((x, y))
    assert sorted(points["truth"]) == sorted((r["p0"], r["truth_dK"]) for r in rows)
    assert sorted(points["converged"]) == sorted((r["p0"], r["est_dK"]) for r in rows if r["status"] == "converged")
    assert sorted(points["not converged"]) == [(1e3, rows[1]["est_dK"])]
    truth = [c for c in axes[0].collections if c.get_label() == "truth"][0]
    assert truth.get_zorder() > max(c.get_zorder() for c in axes[0].collections if c is not truth)
    errors = sorted(y for c in axes[1].collections if isinstance(c, PathCollection) for _, y in c.get_offsets())
    assert errors == pytest.approx(sorted(abs(r["err_dK"]) for r in rows))
    assert [t.get_text() for t in fig.legends[0].get_texts()] == ["converged", "not converged", "diverged", "truth",
                                                                  "range over members", "median over members",
                                                                  "smallest median |error|"]
    # a setting of words is drawn as categories
    basis = figs["sweep_basis"].axes[-1]
    assert [t.get_text() for t in basis.get_xticklabels()] == ["a", "b"]
    _legends_clear_of_axes(fig)
    assert sweep_figures(rows, ["no_such_column"]) == {} and sweep_figures([], ["dK"]) == {}


def test_figures_drawn_meanwhile_are_the_same_bytes_and_errors_reach_the_caller(tmp_path):
    run = Run("sdof-stiffness", steps=200, batch=3, out=tmp_path / "r", log_every=20)
    run.advance(progress=False)
    threads = []

    def make():
        threads.append(threading.current_thread())
        return run_figures(run)
    drawn = draw_meanwhile(make)()
    assert threads[0] is not threading.main_thread()
    assert drawn == pngs(run_figures(run)) and set(drawn) == {"estimates", "model_error", "residuals",
                                                                            "output_fit"}
    assert all(data.startswith(b"\x89PNG\r\n\x1a\n") for data in drawn.values())

    def broken():
        raise ValueError("no history to draw")
    with pytest.raises(ValueError, match="no history to draw"):
        draw_meanwhile(broken)()
    run.close()


def _one_by_one(figs) -> dict:
    return {name: png(fig) for name, fig in figs.items()}


def test_figures_shared_out_to_forked_processes_are_the_same_bytes_in_the_same_order(tmp_path):
    run = Run("sdof-stiffness", steps=200, batch=3, out=tmp_path / "r", log_every=20)
    run.advance(progress=False)
    expected = _one_by_one(run_figures(run))
    shares = figures_module._shares({name: len(fig.axes) for name, fig in run_figures(run).items()}, 2)
    assert len(shares) == 2 and sorted(sum(shares, [])) == sorted(expected)
    assert shares[0][0] == "estimates"                     # the most axes, drawn by the caller
    drawn = pngs(run_figures(run))
    assert drawn == expected and list(drawn) == list(expected)
    apart = figures_module._DrawnApart(lambda: run_figures(run))
    assert apart.pid is not None and apart() == expected and not apart.drawn_here
    data = run_figure_data(run)
    made_apart = figures_module.draw(data)             # each share made and drawn in a process of its own
    assert made_apart == expected and list(made_apart) == list(expected)
    assert figures_module.draw(dataclasses.replace(data, only=("residuals", "estimates"))) == \
        {name: expected[name] for name in ("estimates", "residuals")}
    forked_in_thread = []
    thread = threading.Thread(target=lambda: forked_in_thread.append(
        figures_module._DrawnApart(lambda: run_figures(run))))
    thread.start()
    thread.join()
    child = forked_in_thread[0].pid
    assert forked_in_thread[0]() == expected and not forked_in_thread[0].drawn_here
    assert forked_in_thread[0].pid is None and child is not None
    run.close()


def test_a_figure_that_fails_in_a_forked_process_raises_its_error_in_the_caller():
    from matplotlib.figure import Figure

    class Broken(Figure):
        def savefig(self, *args, **kwargs):
            raise ValueError(f"cannot draw in {os.getpid()}")
    good = Figure()
    good.subplots().plot([0, 1], [1, 0])
    figs = {"good": good, "broken": Broken()}
    apart = figures_module._DrawnApart(lambda: {"broken": figs["broken"]})
    assert apart.pid is not None
    with pytest.raises(ValueError, match=f"cannot draw in {os.getpid()}$"):   # drawn again here, failing here
        apart()
    with pytest.raises(ValueError, match="cannot draw"):
        pngs(figs)


def test_a_forked_drawing_stopped_by_sigterm_never_runs_the_callers_handler_and_is_drawn_here(tmp_path):
    from matplotlib.figure import Figure

    def make():
        fig = Figure()
        fig.subplots().plot(np.arange(200_000.0), np.sin(np.arange(200_000.0)))     # long enough to be stopped
        return fig
    expected = png(make())
    fig = make()
    marker = tmp_path / "handler ran"
    previous = signal.signal(signal.SIGTERM, lambda *_: marker.write_text(str(os.getpid())))
    try:
        apart = figures_module._DrawnApart(lambda: {"f": fig})
        os.kill(apart.pid, signal.SIGTERM)              # at once: before or while it draws
        child = apart.pid
        assert apart() == {"f": expected} and apart.drawn_here
        assert not marker.exists()
        with pytest.raises(ChildProcessError):
            os.waitpid(child, os.WNOHANG)               # reaped
        unwaited = figures_module._DrawnApart(lambda: {"f": make()})
        unwaited.cancel()
        assert unwaited.pid is None and unwaited.r is None
    finally:
        signal.signal(signal.SIGTERM, previous)


def test_on_a_linear_time_axis_the_first_steps_wild_values_stay_off_the_axis():
    """A change late in the run keeps the time axis linear; estimates that jump to 50 in the first steps (no data
    yet) would squeeze the change of 0.2 into a sliver: the y-axis is fitted to the run after its first 2 %, with
    the truth, and says so. Early values no wilder than the rest leave the axis alone."""
    from types import SimpleNamespace

    from matplotlib.figure import Figure

    from rcotorch.run.figures import _focus_after_start
    t = np.linspace(0.0, 100.0, 201)
    path = np.where(t > 60, -0.2, 0.0) + 0.005 * np.sin(t)
    wild = path.copy()
    wild[:2] = [50.0, -30.0]
    run = SimpleNamespace(truth={"dk": -0.2}, truth_path={"dk": (np.array([0.0, 60.0, 100.0]), [0.0, -0.2, -0.2])},
                          intervals=None, dt=0.01)
    ax = Figure().subplots()
    ax.plot(t, wild)
    _focus_after_start(ax, run, "dk", t, wild[:, None])
    low, high = ax.get_ylim()
    assert -0.3 < low < -0.2 and 0.0 < high < 0.1
    assert any("off the axis" in text.get_text() and " s " in text.get_text() for text in ax.texts)
    ax = Figure().subplots()
    ax.plot(t, path)
    before = ax.get_ylim()
    _focus_after_start(ax, run, "dk", t, path[:, None])
    assert ax.get_ylim() == before and not ax.texts


# --- the residual checks: how small z is, whether it matters, the outputs by name; titles within the figure ---
def _titles_within_the_figure(fig) -> None:
    """Every title (the axes' and the figure's) lies inside the figure once drawn: none is clipped."""
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    renderer = canvas.get_renderer()
    titles = [ax.title for ax in fig.axes if ax.get_title()] + ([fig._suptitle] if fig._suptitle else [])
    assert titles
    for text in titles:
        box = text.get_window_extent(renderer)
        assert fig.bbox.x0 <= box.x0 and box.x1 <= fig.bbox.x1 and box.y1 <= fig.bbox.y1, text.get_text()


def _labels_within_the_png(fig) -> None:
    """Every axis label and title of the figure as ``png`` draws it (what the files hold) lies inside the
    figure: none is clipped at an edge."""
    png(fig)
    renderer = fig._get_renderer()
    texts = [t for ax in fig.axes for t in (ax.xaxis.label, ax.yaxis.label, ax.title) if t.get_text()]
    assert texts
    for text in texts:
        box = text.get_window_extent(renderer)
        assert fig.bbox.x0 <= box.x0 and box.x1 <= fig.bbox.x1, text.get_text()
        assert fig.bbox.y0 <= box.y0 and box.y1 <= fig.bbox.y1, text.get_text()


def _residual_line(fig) -> str:
    return fig.axes[0].get_title().replace("\n", " ")


def test_the_residual_figure_says_how_small_z_is_and_that_a_continuous_truths_mismatch_matters(tmp_path):
    """sdof-stiffness with its continuous truth sampled coarsely (Ts = 0.05 s), no noise: z is not white and
    the verdict says it matters (summary.json health.residuals_matter, with the widening); the figure says so,
    with z's rms against y's."""
    run = Run("sdof-stiffness", steps=3000, out=tmp_path / "coarse", overrides={"Ts": 0.05})
    run.advance(progress=False)
    summary = run.summary()
    figs = run_figures(run)
    res = run.residuals()
    y = res.series["measured"][:, 0, 0].numpy()
    z = y - res.series["refined"][:, 0, 0].numpy()
    z_rms, share = np.sqrt(np.mean(z ** 2)), 100 * np.sqrt(np.mean(z ** 2) / np.mean(y ** 2))
    line = _residual_line(figs["residuals"])
    assert line.startswith(f"z rms {z_rms:.2g} m/s, {share:.2g} % of y's rms; z is not white (Ljung-Box p = ")
    assert summary["health"]["residuals_matter"] is True and "and it matters" in line
    assert f"({summary['health']['residual_widening']:.3g} times)" in line
    assert figs["residuals"].get_suptitle() == "sdof-stiffness: residual z = y - y_hat of the refined model, member 0"
    _titles_within_the_figure(figs["residuals"])
    run.close()


def test_the_residual_figure_of_an_exact_noise_free_run_says_its_correlation_does_not_matter(tmp_path):
    """The discrete truth, represented exactly, no noise: z is tiny and smooth, so the whiteness test fails
    (autocorrelation near 1, p = 0); the figure says how small z is and that this does not matter, as the
    summary does, instead of a bare alarm."""
    run = Run("sdof-stiffness", steps=2000, out=tmp_path / "exact", overrides={"truth": "discrete"})
    run.advance(progress=False)
    summary = run.summary()
    res = run.residuals()
    fig = run_figures(run)["residuals"]
    line = _residual_line(fig)
    share = float(line.split(", ")[1].split(" %")[0])
    assert float(res.whiteness_p[0]) < 0.01 and summary["health"]["residuals_matter"] is False
    assert share < 1.0                                                     # z below a hundredth of y
    assert "z is not white" in line and "which does not matter here: it is a parameter error the model can " \
        "take back" in line
    [z_line] = [ln for ln in fig.axes[0].get_lines() if ln.get_label() == "z"]
    assert z_line.get_ydata()[0] > 0.9                                   # the autocorrelation the line explains
    _titles_within_the_figure(fig)
    run.close()


def test_the_residual_and_output_figures_of_a_two_output_run_name_each_output(tmp_path):
    """shear-building-damage measures floors 2 and 3: the residuals are labelled by floor (not z[0], z[1]), each
    with its rms against its output's, and the output fit draws both floors, each named with its fit; the long
    scenario name leaves every title inside the figure."""
    run = Run("shear-building-damage", out=tmp_path / "shear")
    run.advance(progress=False)
    figs = run_figures(run)
    res = run.residuals()
    names = ["floor 2 acceleration", "floor 3 acceleration"]
    auto = [ln.get_label() for ln in figs["residuals"].axes[0].get_lines()]
    assert [label.split(" (")[0] for label in auto] == [f"z of {n}" for n in names]
    assert all("% of the output's)" in label for label in auto)
    cross = [ln.get_label() for ln in figs["residuals"].axes[1].get_lines()]
    assert cross == [f"z of {n}, w" for n in names]
    fit = figs["output_fit"]
    assert [ax.get_ylabel() for ax in fit.axes] == [f"{n} [m/s^2]" for n in names]
    for c, ax in enumerate(fit.axes):
        measured = [ln for ln in ax.get_lines() if ln.get_label() == "measured"][0]
        assert np.array_equal(measured.get_ydata(), res.series["measured"][-600:, 0, c].numpy())
        assert ax.get_title().startswith(f"{names[c]}: fit ")
    assert fit.get_suptitle().startswith("shear-building-damage: measured and model outputs")
    assert figs["model_error"].axes[1].get_title().endswith(f"output {names[0]}")
    for name in ("residuals", "output_fit", "estimates", "model_error"):
        _labels_within_the_png(figs[name])
        _titles_within_the_figure(figs[name])
    run.close()


def _two_output_graph():
    """y = [theta* w(k-1), 2 theta* w(k-1)] + noise against the known model y_hat = [u(k-1), 2 u(k-1)]: one
    parameter seen by two outputs."""
    import rcotorch as rt
    known = rt.LTI(np.zeros((1, 1)), np.array([[0.0, 1.0]]), np.array([[1.0], [2.0]]), np.zeros((2, 2)),
                   inputs={"w": 1, "u": 1}, outputs={"y": 2}, dt=1.0, name="known")
    physical = rt.LTI(np.zeros((1, 1)), np.eye(1), np.array([[0.7], [1.4]]), np.zeros((2, 1)), inputs={"w": 1},
                      outputs={"y": 2}, dt=1.0)
    ident = rt.RCOEstimator.static_gain({"w": 1}, n_z=2, p0=1e8)
    return rt.refinement(known, ident, physical=physical, excitation=rt.WhiteNoise(1, seed=3),
                         noise=rt.WhiteNoise(2, std=0.05, seed=4), nu=1)


def test_the_figures_of_a_graph_built_in_python_carry_the_name_given_and_its_outputs_names(tmp_path):
    """rt.refine titles its figures with the name it was given, else with the output folder the user named (not
    'refinement'), and labels the outputs with output_names."""
    import rcotorch as rt
    from rcotorch.run.refine import GraphScenario
    res = rt.refine(_two_output_graph(), 600, out=tmp_path / "bench", progress=False, figures=False,
                    output_names=["left", "right"])
    figs = run_figures(res.run)
    assert figs["estimates"].axes[0].get_title().startswith("bench: estimates")
    assert figs["residuals"].get_suptitle().startswith("bench: residual z")
    assert [ax.get_ylabel() for ax in figs["output_fit"].axes] == ["left", "right"]
    assert [ln.get_label().split(" (")[0] for ln in figs["residuals"].axes[0].get_lines()] == ["z of left",
                                                                                                "z of right"]
    assert res.summary["scenario"] == "refinement"                     # the run's name stays the default
    named = GraphScenario(_two_output_graph(), name="storeys")
    unnamed = GraphScenario(_two_output_graph())
    assert (named.name, named.figure_name, unnamed.name, unnamed.figure_name) == ("storeys", "storeys",
                                                                                   "refinement", "")
    from rcotorch.run.figures import _named
    assert _named(named, "estimates") == "storeys: estimates" and _named(unnamed, "estimates") == "estimates"
    with pytest.raises(rt.ConfigError, match="output_names names 3 outputs, but the graph measures 2"):
        GraphScenario(_two_output_graph(), output_names=["a", "b", "c"])
    res.run.close()


def test_a_sweep_figure_of_close_values_draws_them_apart_in_full_with_medians_and_names_the_best():
    """lam at 0.9, 0.99, 0.999 and 1, two seeds each, the estimates within 1e-5 of 0.5: the values are drawn
    as categories (0.999 and 1 apart), every tick label writes its value in full (no offset such as
    '1e-5+5e-1' above the axis), the median over the seeds is drawn with their range, and the |error| panel
    names the value with the smallest median error."""
    lams = [0.9, 0.99, 0.999, 1.0]
    errors = {0.9: (4e-6, 6e-6), 0.99: (2e-6, 3e-6), 0.999: (1e-6, 1.5e-6), 1.0: (2e-6, 8e-6)}
    rows = [{"member": 2 * i + s, "lam": lam, "seed": s, "est_dK": 0.5 + errors[lam][s],
             "truth_dK": 0.5, "err_dK": errors[lam][s], "status": "converged"}
            for i, lam in enumerate(lams) for s in (0, 1)]
    fig = sweep_figures(rows, ["lam"], "sdof-stiffness")["sweep_lam"]
    est, err = fig.axes
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    assert [t.get_text() for t in est.get_xticklabels()] == ["0.9", "0.99", "0.999", "1"]
    assert list(est.get_xticks()) == [0, 1, 2, 3]
    for ax in (est, err):
        assert ax.yaxis.get_offset_text().get_text() == "" and ax.xaxis.get_offset_text().get_text() == ""
    labels = [(t.get_text(), t.get_position()[1]) for t in est.get_yticklabels() if t.get_text()]
    assert len({text for text, _ in labels}) == len(labels) >= 3
    for text, where in labels:                                   # each label is its tick's value, whole
        assert float(text) == pytest.approx(where, rel=1e-12, abs=1e-15)
    [median] = [ln for ln in err.get_lines() if ln.get_label() == "median over members"]
    assert list(median.get_ydata()) == pytest.approx([np.median(errors[lam]) for lam in lams])
    [best] = [ln for ln in err.get_lines() if ln.get_label() == "smallest median |error|"]
    assert list(best.get_xdata()) == [2]
    assert err.get_title() == "|estimate - truth|: smallest median at lam = 0.999"
    assert est.get_title() == "sdof-stiffness: estimates against lam (8 members)"
    _titles_within_the_figure(fig)
    # values far enough apart stay on a linear axis of their own values
    spread = sweep_figures([dict(r, lam=r["lam"] * 0 + 0.2 * (i // 2)) for i, r in enumerate(rows)],
                           ["lam"])["sweep_lam"]
    assert spread.axes[-1].get_xscale() == "linear" and list(spread.axes[0].collections[0].get_offsets()[:, 0]) == \
        pytest.approx([0.0, 0.0, 0.2, 0.2, 0.4, 0.4, 0.6, 0.6])


def test_a_sweep_over_an_integer_setting_labels_its_ticks_as_integers_and_draws_its_ranges_as_one_collection():
    """nu = 5..68, four seeds each: the tick labels read '10', '20', ... (not '1e+01'), and the range over the
    members at each value is one bar per value, all in one collection, from the members' least to greatest."""
    rng = np.random.default_rng(0)
    rows = [{"member": 4 * i + s, "nu": nu, "seed": s, "est_dK": -0.4 + 0.01 * rng.standard_normal(),
             "truth_dK": -0.4, "status": "converged"} for i, nu in enumerate(range(5, 69)) for s in range(4)]
    for r in rows:
        r["err_dK"] = r["est_dK"] - r["truth_dK"]
    fig = sweep_figures(rows, ["nu"], "sdof-stiffness")["sweep_nu"]
    FigureCanvasAgg(fig).draw()
    est = fig.axes[0]
    labels = [t.get_text() for t in fig.axes[-1].get_xticklabels() if t.get_text()]
    assert labels and all(text == f"{float(text):.0f}" for text in labels), labels
    assert "10" in labels or "20" in labels
    [bars] = [c for c in est.collections if c.get_label() == "range over members"]
    segments = bars.get_segments()
    assert len(segments) == 64
    for nu, seg in zip(range(5, 69), segments):
        v = [r["est_dK"] for r in rows if r["nu"] == nu]
        assert seg[0][0] == seg[1][0] == nu and (seg[0][1], seg[1][1]) == pytest.approx((min(v), max(v)))


def test_the_parents_uncollected_garbage_is_not_finalized_in_a_forked_drawing(tmp_path):
    """An object in a reference cycle that the caller has dropped but not yet collected (its finalizer would
    release a file of the caller's): the forked drawing collects nothing, so the finalizer runs once, in the
    caller, when it collects."""
    import gc

    from matplotlib.figure import Figure
    marker = tmp_path / "finalized"

    class Held:
        def __del__(self):
            with open(marker, "a") as f:
                f.write(f"{os.getpid()}\n")
    fig = Figure()
    fig.subplots().plot(np.arange(50_000.0), np.cos(np.arange(50_000.0)))      # enough allocation to collect
    gc.collect()                              # the count starts afresh: the few allocations below collect nothing
    a, b = Held(), Held()
    a.other, b.other = b, a
    del a, b
    apart = figures_module._DrawnApart(lambda: {"f": fig})
    assert apart.pid is not None
    apart()
    assert not apart.drawn_here and not marker.exists()
    gc.collect()
    assert marker.read_text().split() == [str(os.getpid())] * 2


def test_a_drawing_process_draws_the_same_bytes_and_the_run_draws_them_itself_where_it_failed(tmp_path):
    """The process ``rcotorch run`` starts first draws the figure data it is sent, the same PNG bytes as drawn in
    the run's own process; one that died before its data came, or that fails on them, leaves the run to draw them
    itself (the same bytes, and the same error where a figure cannot be drawn); one never sent data ends on
    ``close`` and is reaped."""
    from rcotorch.run.drawing import DrawingProcess
    from rcotorch.run.figure_data import run_figure_data

    run = Run("sdof-stiffness", steps=200, batch=3, out=tmp_path / "r", log_every=20)
    run.advance(progress=False)
    data = run_figure_data(run)
    expected = pngs(run_figures(data))
    drawing = DrawingProcess()
    assert drawing.started
    wait = drawing.draw(data)
    assert not drawing.started and wait() == expected and drawing.pid is None
    dead = DrawingProcess()
    os.kill(dead.pid, signal.SIGKILL)
    assert dead.draw(data)() == expected and dead.pid is None
    unused = DrawingProcess()
    pid = unused.pid
    unused.close()
    with pytest.raises(ChildProcessError):
        os.waitpid(pid, os.WNOHANG)
    # several jobs, drawn in the order sent; one that fails there, or a process that died, leaves the rest to the
    # run (a job sent after the failure never blocks on the pipe)
    import dataclasses
    first, second = (dataclasses.replace(data, only=names) for names in (("estimates",), ("model_error",)))
    two = DrawingProcess()
    waits = [two.draw(first, more=True), two.draw(second)]
    assert [w() for w in waits] == [{"estimates": expected["estimates"]}, {"model_error": expected["model_error"]}]
    assert two.pid is None
    broken = dataclasses.replace(first, series={"dK": np.zeros(3)})
    failing = DrawingProcess()
    waits = [failing.draw(second, more=True), failing.draw(broken, more=True), failing.draw(first)]
    assert waits[0]() == {"model_error": expected["model_error"]}
    with pytest.raises(IndexError):
        waits[1]()
    assert waits[2]() == {"estimates": expected["estimates"]} and failing.pid is None
    killed = DrawingProcess()
    wait_first = killed.draw(first, more=True)
    assert wait_first() == {"estimates": expected["estimates"]}
    os.kill(killed.pid, signal.SIGKILL)
    assert killed.draw(second)() == {"model_error": expected["model_error"]} and killed.pid is None
    data.series = {"dK": np.zeros(3)}              # one dimension where a path over time needs two
    with pytest.raises(IndexError):
        DrawingProcess().draw(data)()
    run.close()


# a command run in a fresh process (argv: its output folder, then 'process' or 'none'): with 'none' the command
# finds no drawing process (as off Linux) and draws its figures itself
WITHOUT_DRAWING = ("import sys\nfrom rcotorch.run.cli import main\n"
                   "import rcotorch.run.drawing as drawing\n"
                   "if sys.argv[2] == 'none':\n"
                   "    class Absent(drawing.DrawingProcess):\n"
                   "        def __init__(self):\n"
                   "            self.pid = self._jobs = self._results = None\n"
                   "    drawing.DrawingProcess = Absent\n")


def test_rcotorch_run_draws_its_figures_in_a_process_that_imports_matplotlib_beside_the_run(tmp_path):
    """``rcotorch run`` leaves its figures to the drawing process: the run's own process never imports
    matplotlib, and the figures are the bytes the run draws without that process."""
    import subprocess
    import sys
    script = (WITHOUT_DRAWING +
              "code = main(['run', 'sdof-stiffness', '--steps', '600', '--batch', '2', '--quiet',\n"
              "             '--out', sys.argv[1]])\n"
              "print(code, 'matplotlib' in sys.modules)\n")
    lines = {}
    for how in ("process", "none"):
        done = subprocess.run([sys.executable, "-c", script, str(tmp_path / how), how], capture_output=True,
                              text=True, timeout=300)
        lines[how] = done.stdout.strip().splitlines()[-1]
    code = lines["none"].split()[0]
    assert lines == {"process": f"{code} False", "none": f"{code} True"}
    names = sorted(p.name for p in (tmp_path / "process").glob("*.png"))
    assert names == ["estimates.png", "model_error.png", "output_fit.png", "residuals.png"]
    for name in names:
        assert (tmp_path / "process" / name).read_bytes() == (tmp_path / "none" / name).read_bytes()


def test_rcotorch_sweep_draws_its_figures_in_a_process_that_imports_matplotlib_beside_the_sweep(tmp_path):
    """``rcotorch sweep`` leaves its figures to the drawing process as ``rcotorch run`` does (drawn while the
    sweep writes its table and HParams sessions): the sweep's own process never imports matplotlib, and the
    figure is the bytes the sweep draws without that process, with the scenario's units and name."""
    import json
    import subprocess
    import sys
    config = tmp_path / "sweep.json"
    config.write_text(json.dumps({"scenario": "sdof-stiffness", "steps": 300, "seeds": 2,
                                  "grid": {"dK": [0.3, 0.5]}}))
    script = (WITHOUT_DRAWING +
              "code = main(['sweep', sys.argv[3], '--out', sys.argv[1]])\n"
              "print(code, 'matplotlib' in sys.modules)\n")
    lines = {}
    for how in ("process", "none"):
        done = subprocess.run([sys.executable, "-c", script, str(tmp_path / how), how, str(config)],
                              capture_output=True, text=True, timeout=300)
        lines[how] = done.stdout.strip().splitlines()[-1]
    assert lines == {"process": "0 False", "none": "0 True"}
    drawn = (tmp_path / "process" / "sweep_dK.png").read_bytes()
    assert drawn == (tmp_path / "none" / "sweep_dK.png").read_bytes()
    rows = json.loads((tmp_path / "process" / "sweep.json").read_text())
    assert png(sweep_figures(rows, ["dK"], "sdof-stiffness")["sweep_dK"]) == drawn


def test_the_drawing_process_yields_a_core_the_run_needs_and_gets_its_data_before_the_summary(tmp_path):
    """The drawing process runs at a lower priority (``NICE``): where the run's end still computes (validation,
    its summary, a scenario's own figures), the run keeps its core and the drawing takes what is idle. It is sent
    the figures that show no validation once the intervals are done (drawn while the run validates: without
    the held-out data, which the run has not measured yet), the figure of the held-out data after validation,
    both before the summary is made; the files are those of one job."""
    import time

    from rcotorch.run.drawing import NICE, DrawingProcess

    drawing = DrawingProcess()
    try:
        deadline = time.monotonic() + 30
        lower = min(19, os.getpriority(os.PRIO_PROCESS, 0) + NICE)
        while os.getpriority(os.PRIO_PROCESS, drawing.pid) != lower and time.monotonic() < deadline:
            time.sleep(0.01)
        assert os.getpriority(os.PRIO_PROCESS, drawing.pid) == lower
    finally:
        drawing.close()
    order = []
    run = Run("sdof-stiffness", steps=200, batch=2, out=tmp_path / "r", log_every=20)
    run.drawing = DrawingProcess()
    sent = run.drawing.draw
    run.drawing.draw = lambda data, **kw: (order.append((data.only, data.held_out is None)), sent(data, **kw))[1]
    made = run.summary
    run.summary = lambda: (order.append("summary"), made())[1]
    run.advance(progress=False)
    run.finish(progress=False)
    assert order == [(("estimates", "residuals", "output_fit"), True), (("model_error",), False), "summary"]
    names = ["estimates.png", "model_error.png", "output_fit.png", "residuals.png"]
    assert sorted(p.name for p in (tmp_path / "r").glob("*.png")) == names
    one = Run("sdof-stiffness", steps=200, batch=2, out=tmp_path / "one", log_every=20)
    one.advance(progress=False)
    one.finish(progress=False)                  # no drawing process: drawn here, in one go
    for name in names:
        assert (tmp_path / "r" / name).read_bytes() == (tmp_path / "one" / name).read_bytes(), name


def test_a_log_axis_over_decades_draws_its_minor_grid_as_lines_on_every_axes_that_shares_it():
    """On a log axis spanning more than a decade the minor grid is one set of lines at the places matplotlib's
    minor locator picks (2..9 times each power of ten inside the limits), on each of two axes sharing that axis,
    and no minor ticks; an axis within a decade (whose minor ticks are labelled) keeps its minor ticks."""
    from matplotlib.collections import LineCollection
    from matplotlib.figure import Figure
    fig = Figure(layout="constrained")
    top, bottom = fig.subplots(2, 1, sharex=True)
    for ax in (top, bottom):
        ax.plot([1.0, 2.0e3], [0.0, 1.0])
        ax.set_xscale("log")
        ax.grid(alpha=0.3, which="both")
    short = Figure()
    near = short.subplots()
    near.semilogy([0.0, 1.0], [2.0, 7.0])
    png(fig)
    png(short)
    lo, hi = top.get_xlim()
    expected = sorted(m * 10.0 ** e for e in range(-1, 5) for m in range(2, 10) if lo < m * 10.0 ** e < hi)
    for ax in (top, bottom):
        grids = [c for c in ax.collections if isinstance(c, LineCollection)]
        assert len(grids) == 1
        places = sorted(seg[0][0] for seg in grids[0].get_segments())
        np.testing.assert_allclose(places, expected, rtol=1e-12)
        assert grids[0].get_alpha() == 0.3
        assert len(ax.xaxis.get_minorticklocs()) == 0
    assert len(near.yaxis.get_minorticklocs()) > 0 and not any(isinstance(c, LineCollection) for c in near.collections)
