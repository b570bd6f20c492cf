"""Runs end to end: CLI, summary.json keys, TensorBoard events, checkpoint/resume, float32, bad settings."""

import json

import numpy as np
import pytest
import torch

from rcotorch import ConfigError
from rcotorch.errors import CheckpointError
from rcotorch.run.cli import main
from rcotorch.run.runner import Run


def test_cli_run_writes_summary_events_and_figures(tmp_path, capsys):
    out = tmp_path / "run"
    rc = main(["run", "sdof-stiffness", "--steps", "400", "--out", str(out), "--quiet"])
    assert rc in (0, 1)  # 400 steps need not meet the requirement
    summary = json.loads((out / "summary.json").read_text())
    for key in ("scenario", "steps", "batch", "dtype", "device", "estimates", "truth", "metrics", "settings"):
        assert key in summary
    assert summary["scenario"] == "sdof-stiffness" and summary["steps"] == 400 and summary["batch"] == 1
    assert summary["dtype"] == "float64" and summary["device"] == "cpu"
    assert set(summary["estimates"]) == {"dK", "dC"} and summary["truth"] == {"dK": 0.5, "dC": 0.0}
    for key in ("Ts", "nc", "p0", "lam", "nu", "seed"):
        assert key in summary["settings"]
    assert (out / "estimates.png").stat().st_size > 1000
    # the requirement's reported error is the float64 difference of estimate and truth (not rounded to float32)
    assert summary["requirements"]["estimates.dK"]["value"] == abs(summary["estimates"]["dK"] - 0.5)
    printed = capsys.readouterr().out
    assert "estimates.dK" in printed and "truth" in printed


def _state(run):
    return {k: v.clone() for k, v in run.graph.state_dict().items()}


@pytest.mark.parametrize("name", ["sdof-dynamic-impedance", "sdof-stiffness-damping"])
def test_checkpoint_resume_is_bitwise_identical(name, tmp_path):
    full = Run(name, steps=1300, batch=2, out=tmp_path / "full")
    full.advance(progress=False)
    part = Run(name, steps=1300, batch=2, out=tmp_path / "part")
    part.advance(until=517, progress=False)   # not a multiple of the noise chunk or the log interval
    part.save()
    part.close()
    resumed = Run.resume(tmp_path / "part")
    assert resumed.k == 517
    resumed.advance(progress=False)
    a, b = _state(full), _state(resumed)
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), key
    assert full.summary()["estimates"] == resumed.summary()["estimates"]
    assert full.history.keys() == resumed.history.keys()
    for key, trace in full.history.items():
        assert len(trace) == len(resumed.history[key]) > 0, key
        for x, y in zip(trace, resumed.history[key]):
            assert torch.equal(torch.as_tensor(x), torch.as_tensor(y)), key


def test_cli_resume_extends_a_finished_run(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    main(["run", "sdof-stiffness", "--steps", "800", "--out", str(a), "--quiet", "--no-figures"])
    main(["run", "sdof-stiffness", "--steps", "400", "--out", str(b), "--quiet", "--no-figures"])
    main(["run", "--resume", str(b), "--steps", "800", "--quiet", "--no-figures"])
    sa = json.loads((a / "summary.json").read_text())
    sb = json.loads((b / "summary.json").read_text())
    assert sb["steps"] == 800
    assert sa["estimates"] == sb["estimates"] and sa["metrics"] == sb["metrics"]


def test_float32_is_an_explicit_option(tmp_path):
    run = Run("sdof-stiffness", steps=2000, dtype="float32", out=tmp_path)
    run.advance(progress=False)
    for name, t in run.graph.state_dict().items():
        if t.is_floating_point():
            assert t.dtype == torch.float32, name
    summary = run.finish(figures=False)
    assert summary["dtype"] == "float32"
    assert abs(summary["estimates"]["dK"] - 0.5) < 0.05


def test_bad_settings_are_rejected_before_work(tmp_path, capsys):
    with pytest.raises(ConfigError, match="unknown setting 'p00'"):
        Run("sdof-stiffness", overrides={"p00": 1.0}, out=tmp_path)
    with pytest.raises(ConfigError, match="no scenario named 'sdof-stifness'.*did you mean 'sdof-stiffness'"):
        Run("sdof-stifness", out=tmp_path)
    with pytest.raises(ConfigError, match="must be an integer"):
        Run("sdof-stiffness", overrides={"nc": "1.5"}, out=tmp_path)
    with pytest.raises(ConfigError, match="dtype"):
        Run("sdof-stiffness", dtype="float16", out=tmp_path)
    assert main(["run", "sdof-stiffness", "--set", "lam=2", "--out", str(tmp_path)]) == 2
    assert "lam must lie in (0, 1]" in capsys.readouterr().err
    if not torch.cuda.is_available():
        assert main(["run", "sdof-stiffness", "--device", "cuda", "--out", str(tmp_path)]) == 2


def test_overrides_reach_the_graph(tmp_path):
    run = Run("sdof-stiffness-damping", steps=10, overrides={"p0": "1e4", "nu": "7"}, out=tmp_path)
    ident = run.graph.blocks["identified"]
    assert float(ident.P[0, 0, 0]) == 1e4 and ident.nu == 7
    assert np.isclose(run.settings["p0"], 1e4)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu(tmp_path):
    cpu = Run("sdof-stiffness", steps=500, batch=4, out=tmp_path / "c")
    cpu.advance(progress=False)
    gpu = Run("sdof-stiffness", steps=500, batch=4, device="cuda", out=tmp_path / "g")
    gpu.advance(progress=False)
    np.testing.assert_allclose(gpu.graph.blocks["identified"].theta.cpu().numpy(),
                               cpu.graph.blocks["identified"].theta.numpy(), rtol=1e-9, atol=1e-12)
    on_cpu, on_gpu = cpu.finish(figures=False), gpu.finish(figures=True)   # intervals, validation, health
    for key, value in on_cpu["estimates"].items():
        np.testing.assert_allclose(on_gpu["estimates"][key], value, rtol=1e-9, atol=1e-12)


def test_a_diverging_member_is_frozen_and_reported(tmp_path):
    run = Run("sdof-stiffness", steps=600, batch=3, out=tmp_path)
    run.advance(until=250, progress=False)
    known = run.graph.blocks["known"]
    x = known.x.clone()
    x[1] = float("nan")                     # member 1's simulated model breaks down
    known.set_state(x=x)
    run.advance(progress=False)
    summary = run.finish(figures=False)
    assert summary["diverged"] == [{"member": 1, "step": 250, "reason": "non_finite"}]
    assert summary["health"]["status"][1] == "diverged" and summary["health"]["reason"][1] == "non_finite"
    dK = summary["estimates"]["dK"]
    assert dK[1] is not None and dK[0] is not None and dK[2] is not None  # frozen at its last finite value
    ident = run.graph.blocks["identified"]
    assert ident.alive.tolist() == [True, False, True]
    assert torch.isfinite(ident.theta).all() and torch.isfinite(ident.P).all()
    # the healthy members are untouched: equal to a run without the fault
    clean = Run("sdof-stiffness", steps=600, batch=3, out=tmp_path / "clean")
    clean.advance(progress=False)
    th, th_clean = ident.theta, clean.graph.blocks["identified"].theta
    assert torch.equal(th[[0, 2]], th_clean[[0, 2]])


def test_a_checkpoint_of_another_format_is_refused_with_exit_2(tmp_path, capsys):
    """A checkpoint written with the doubled regressor ring (format 2) does not fit this version's state: a
    resume refuses it, naming the file and its format, and leaves it as it was."""
    from rcotorch.run.outputs import load_checkpoint, save_checkpoint
    run = Run("sdof-stiffness", steps=40, out=tmp_path / "old")
    run.advance(progress=False)
    path = run.save()
    run.close()
    state = load_checkpoint(path)
    state["format"] = 2
    save_checkpoint(path, state)
    before = path.read_bytes()
    with pytest.raises(CheckpointError, match=r"checkpoint\.pt: written by another version of rcotorch \(format 2\)"):
        Run.resume(tmp_path / "old")
    assert main(["run", "--resume", str(tmp_path / "old"), "--quiet"]) == 2
    assert "format 2" in capsys.readouterr().err
    assert path.read_bytes() == before


def test_a_refined_model_that_fits_worse_than_the_initial_one_is_warned_about():
    """fit_warnings: a member whose refined fit is more than FIT_WORSE points below the initial model's, on the
    last window or on held-out data, is named with both fits; one within the margin or better is not."""
    from rcotorch.run.end_checks import FIT_WORSE, fit_warnings
    met = {"fit_percent": torch.tensor([90.0, 50.0, 76.0]), "fit_percent_initial": torch.tensor([80.0, 70.0, 80.0])}
    assert 80.0 - 76.0 < FIT_WORSE
    (w,) = fit_warnings(met)
    assert "over the run's last window in member 1 (fit 50.0 % against 70.0 %)" in w
    met.update(validation_fit_percent=torch.tensor([10.0, 20.0, 99.0]),
               validation_fit_percent_initial=torch.tensor([60.0, 60.0, 60.0]))
    assert "on the held-out data in 2 of 3 members (fit 10.0..20.0 % against 60.0..60.0 %)" in fit_warnings(met)[1]
    assert fit_warnings({"fit_percent": torch.tensor([90.0]), "fit_percent_initial": torch.tensor([90.0])}) == []


def test_a_member_whose_refined_model_fits_worse_is_not_converged(tmp_path, monkeypatch):
    """The fault reproduced: member 0's refined fit over the last window made 10 points worse than its initial
    model's. That member is not_converged (it was converged), flagged in health.fits_worse and warned about;
    member 1 keeps its status."""
    import rcotorch.run.runner as runner
    real = runner.residual_metrics

    def lowered(res):
        out = real(res)
        out["fit_percent"] = out["fit_percent"].clone()
        out["fit_percent"][0] = out["fit_percent_initial"][0] - 10.0
        return out
    honest = Run("sdof-stiffness", batch=2, overrides={"truth": "discrete"}, out=tmp_path / "a", validation=False)
    honest.advance(progress=False)
    assert honest.summary()["health"]["status"] == ["converged", "converged"]
    monkeypatch.setattr(runner, "residual_metrics", lowered)
    run = Run("sdof-stiffness", batch=2, overrides={"truth": "discrete"}, out=tmp_path / "b", validation=False)
    run.advance(progress=False)
    summary = run.summary()
    assert summary["health"]["status"] == ["not_converged", "converged"]
    assert summary["health"]["fits_worse"] == [True, False]
    assert any("worse than the initial model over the run's last window in member 0" in w
               for w in summary["warnings"])


def _softening_spring(nu: int):
    """A mass on a spring (k = 3, c = 0.4, Ts = 0.01 s: a decay time of 5 s) that softens by 0.5 at step 3000,
    refined with forgetting at 0.997 from its position."""
    import rcotorch as rt
    known = rt.LTI.continuous(*rt.models.sdof_matrices(1.0, 0.4, 3.0, measured=["position"], sees=["position"]),
                              inputs=["w", "u"], outputs={"y": 1, "y0": 1}, dt=0.01, name="known")
    ident = rt.RCOEstimator.static_gain({"y0": 1}, p0=100.0, lam=0.997)
    g = rt.refinement(known, ident, truth=rt.Gain(0.0, name="unknown"), excitation=rt.WhiteNoise(1, seed=[1, 2, 3]),
                      noise=rt.WhiteNoise(1, std=1e-3, seed=[7, 8, 9]), nu=nu, batch_size=3)
    g.add_hook(rt.at_step(3000, lambda gr: gr.blocks["unknown"].K.fill_(0.5)))
    return g


def test_a_refinement_that_went_astray_is_told_so_and_a_good_one_is_not(tmp_path):
    """A Markov window of 0.4 s on a spring whose response lasts 5 s, with forgetting: after the change the
    adaptation goes astray (theta far below -1 against 0.5) and the refined model fits worse than the initial
    one; the run says not converged and warns, on the last window and on held-out data. With nu = 100 it finds
    0.5 (within 0.05 after 30 s) and nothing is said."""
    import rcotorch as rt
    est = {"dK": lambda g: g.role("estimator").theta[:, 0, 0]}
    bad = rt.refine(_softening_spring(40), 6000, est, truth={"dK": 0.5}, scales={"dK": 1.0}, out=tmp_path / "bad",
                    progress=False)
    assert max(bad.summary["estimates"]["dK"]) < -1.0
    assert set(bad.summary["health"]["status"]) == {"not_converged"}
    worse = [w for w in bad.summary["warnings"] if "fits the data worse than the initial model" in w]
    assert len(worse) == 2 and "last window in 3 of 3 members" in worse[0] and "held-out data" in worse[1]
    good = rt.refine(_softening_spring(100), 6000, est, truth={"dK": 0.5}, scales={"dK": 1.0}, out=tmp_path / "good",
                     progress=False)
    assert good.summary["estimates"]["dK"] == pytest.approx([0.5] * 3, abs=0.05)   # 30 s after the change
    assert not any("fits the data worse" in w for w in good.summary["warnings"])


def test_no_p0_warning_for_members_that_forget(tmp_path):
    """With lam < 1 P is renewed from the data, so P_ii / p0 says nothing about p0: a run with p0 = 1 and
    lam = 0.98 whose P ends above p0 is not told that p0 is small; with lam = 1 the same p0 is (P stays near p0 I
    when p0 sum psi^2 < 1)."""
    forgetting = Run("sdof-stiffness", steps=3000, out=tmp_path / "a", overrides={"p0": 1.0, "lam": 0.98},
                     intervals=False, validation=False)
    forgetting.advance(progress=False)
    P = forgetting.graph.role("estimator").P
    assert float(torch.diagonal(P[0]).max()) > 0.5             # the share the check would have flagged
    assert forgetting.summary()["warnings"] == []
    remembering = Run("sdof-stiffness", steps=3000, out=tmp_path / "b", overrides={"p0": 1e-6, "lam": 1.0},
                      intervals=False, validation=False)
    remembering.advance(progress=False)
    assert "p0 = 1e-06 is small" in remembering.summary()["warnings"][0]


def test_a_batchs_estimates_are_summarized_over_the_members_that_did_not_diverge():
    """A diverged member's parameters are frozen where it failed (here 1e300): the printed range and median
    half-width leave it out and say so; the metrics are printed as they are."""
    from rcotorch.run.report import result_table
    summary = {"batch": 3, "estimates": {"k": [1.0, 1e300, 2.0]}, "truth": {"k": 1.5},
               "metrics": {"z_rms_final": [0.1, 1e10, 0.2]}, "requirements": {}, "warnings": [],
               "intervals": {"k": {"level": 0.95, "lower": [0.9, 1e300, 1.8], "upper": [1.1, 1e300, 2.2]}},
               "health": {"status": ["converged", "diverged", "converged"],
                          "counts": {"converged": 2, "not_converged": 0, "diverged": 1, "undetermined": 0}},
               "diverged": [{"member": 1, "step": 5, "reason": "non_finite"}]}
    lines = result_table(summary).splitlines()
    row = next(line for line in lines if line.startswith("estimates.k"))
    assert "1..2 (± 0.2 median)" in row and "e+300" not in row
    assert "(estimates: the 2 members that did not diverge)" in lines
    assert "1e+10" in next(line for line in lines if line.startswith("metrics.z_rms_final"))
    assert lines[-1].startswith("health: 2 converged") and "member 1 at step 5 (non_finite)" in lines[-1]
    every = {**summary, "health": {**summary["health"], "status": ["diverged"] * 3}}
    assert "1..1e+300" in next(line for line in result_table(every).splitlines() if line.startswith("estimates.k"))


def test_an_interval_to_one_side_of_its_estimate_is_printed_with_its_ends():
    """A one-member interval about the window's output-error optimum need not hold the estimate: the table prints
    its ends (an 'estimate -below +above' would print a negative side), a symmetric one as '± half-width' and a
    lopsided one that holds the estimate by its two sides."""
    from rcotorch.run.report import result_table
    base = {"batch": 1, "truth": {}, "metrics": {}, "requirements": {}, "warnings": [],
            "health": {"status": "converged", "counts": {"converged": 1}, "theta_change": 0.0, "z_ratio": 0.01}}

    def row(lower, upper):
        s = {**base, "estimates": {"k": 1.0}, "intervals": {"k": {"level": 0.95, "lower": lower, "upper": upper}}}
        return next(line for line in result_table(s).splitlines() if line.startswith("estimates.k"))
    assert "1 [1.02, 1.1]" in row(1.02, 1.1)
    assert "1 [0.9, 0.99]" in row(0.9, 0.99)
    assert "1 ± 0.1" in row(0.9, 1.1)
    assert "1 -0.1 +0.3" in row(0.9, 1.3)


def test_refine_into_a_folder_that_holds_a_run_names_its_own_arguments(tmp_path):
    """The Python call is told what to pass (overwrite=True, another out), not the command's options."""
    import rcotorch as rt
    est = {"dK": lambda g: g.role("estimator").theta[:, 0, 0]}
    rt.refine(_softening_spring(40), 20, est, out=tmp_path / "r", progress=False, figures=False, intervals=False,
              validation=False)
    with pytest.raises(rt.OutputError) as e:
        rt.refine(_softening_spring(40), 20, est, out=tmp_path / "r", progress=False)
    assert "overwrite=True" in str(e.value) and "another out" in str(e.value) and "--" not in str(e.value)
    again = rt.refine(_softening_spring(40), 20, est, out=tmp_path / "r", overwrite=True, progress=False,
                      figures=False, intervals=False, validation=False)
    assert again.summary["steps"] == 20


@pytest.mark.parametrize("steps,batch", [(20000, 1), (2_000_000, 1), (20000, 4096), (2000, 65536), (8232, 200),
                                         (8232, 1), (35000, 64), (12000, 1), (300, 3), (10**7, 1)])
def test_the_log_interval_is_a_multiple_or_divisor_of_the_checks_and_a_change_gets_its_logs(steps, batch):
    """Logs fall on health-check steps or checks on logs; the interval is never shorter than the budget asks
    (at most MAX_LOGS logs); a run that follows a change logs at least MIN_LOGS_CHANGE times where its steps
    and the member-value budget allow."""
    from rcotorch.run.cadence import LOG_BUDGET, MAX_LOGS, MIN_LOGS_CHANGE, default_log_every
    from rcotorch.verdict.health import check_every
    check = check_every(steps)
    for follows in (False, True):
        every = default_log_every(steps, batch, follows)
        assert every % (2 * check) == 0 or check % every == 0
        assert steps // every <= MAX_LOGS
        if follows:
            assert steps // every >= min(MIN_LOGS_CHANGE, LOG_BUDGET // batch, steps // 2) / 2
    assert default_log_every(steps, batch, True) <= default_log_every(steps, batch, False)
