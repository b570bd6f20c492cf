"""TensorBoard as written by runs and sweeps, read back with TensorBoard's own event readers (and, in one test,
served by TensorBoard and queried through its HParams API): one run per run, tag counts, values, Custom Scalars
layout and HParams sessions."""

import json
import socket
import subprocess
import sys
import time
import urllib.request

import pytest
import torch
from tensorboard.backend.event_processing.plugin_event_multiplexer import EventMultiplexer
from tensorboard.plugins.custom_scalar import layout_pb2
from tensorboard.plugins.hparams import metadata as hp_metadata
from tensorboard.util import tensor_util

from rcotorch import monitor
from rcotorch import sweep as sweeps
from rcotorch.runner import Run


def _mux(logdir) -> EventMultiplexer:
    mux = EventMultiplexer(size_guidance={"scalars": 0, "histograms": 0, "images": 0, "tensors": 0})
    mux.AddRunsFromDirectory(str(logdir))
    mux.Reload()
    return mux


def _run(tmp_path, name="sdof-stiffness", **kw) -> tuple[Run, dict, EventMultiplexer]:
    run = Run(name, out=tmp_path / "runs" / name, **kw)
    run.advance(progress=False)
    summary = run.finish(figures=kw.get("batch", 1) <= 2)
    return run, summary, _mux(tmp_path / "runs")


def _tags(mux, run, plugin="scalars") -> set:
    return set(mux.PluginRunToTagToContent(plugin).get(run, {}))


def _values(mux, run, tag) -> list[tuple[int, float]]:
    return [(e.step, float(tensor_util.make_ndarray(e.tensor_proto))) for e in mux.Tensors(run, tag)]


def _last(mux, run, tag) -> float:
    return _values(mux, run, tag)[-1][1]


def _sessions(mux) -> dict:
    """run -> hparams of its session start info."""
    out = {}
    for run, tags in mux.PluginRunToTagToContent(hp_metadata.PLUGIN_NAME).items():
        assert hp_metadata.EXPERIMENT_TAG not in tags          # TensorBoard builds the table from all sessions
        if hp_metadata.SESSION_START_INFO_TAG in tags:
            info = hp_metadata.parse_session_start_info_plugin_data(tags[hp_metadata.SESSION_START_INFO_TAG])
            out[run] = {k: v.WhichOneof("kind") and getattr(v, v.WhichOneof("kind")) for k, v in info.hparams.items()}
    return out


def _layout(mux, run) -> layout_pb2.Layout:
    event = mux.Tensors(run, "custom_scalars__config__")[0]
    return layout_pb2.Layout.FromString(event.tensor_proto.string_val[0])


HPARAMS_SHOWN = 5     # TensorBoard's HParams table shows the first five hyperparameters of its list at first


def _hparams_order(mux) -> list[str]:
    """The hyperparameters in the order TensorBoard's HParams dashboard lists them (those that differ between
    sessions first, each part by name), computed by TensorBoard's own backend from the sessions read back."""
    from tensorboard.plugins.hparams import backend_context

    content = mux.PluginRunToTagToContent(hp_metadata.PLUGIN_NAME)
    experiment = backend_context.Context(None).experiment_from_metadata(None, "", False, content, [])
    return [h.name for h in experiment.hparam_infos]


def test_a_single_run_is_one_run_with_estimates_beside_truth(tmp_path):
    run, summary, mux = _run(tmp_path, steps=600, log_every=50)
    assert list(mux.Runs()) == ["sdof-stiffness"]                 # no second run for HParams
    tags = _tags(mux, "sdof-stiffness")
    assert {"Estimates/dK", "Estimates/dK truth", "Estimates/dC", "Estimates/dC truth", "Model error/z rms",
            "errors/dK", "theta/y0[0](k)", "theta/y0[1](k)", "health/diverged", "final/z_rms_final", "final/dK",
            "final/|error| dK", "final/diverged"} <= tags
    assert not any(t.startswith(("members/", "quantiles/")) for t in tags)
    # the final interval as a band over the logged steps, and its margin chart
    lower = _values(mux, "sdof-stiffness", "intervals/dK lower")
    assert [st for st, _ in lower] == list(range(50, 601, 50))
    assert all(v == pytest.approx(summary["intervals"]["dK"]["lower"]) for _, v in lower)
    assert _last(mux, "sdof-stiffness", "intervals/dK upper") == pytest.approx(summary["intervals"]["dK"]["upper"])
    margins = {c.title: c.margin.series[0] for c in _layout(mux, "sdof-stiffness").category[0].chart
               if c.HasField("margin")}
    band = margins["dK: estimate within its final 95% interval"]
    assert (band.value, band.lower, band.upper) == ("Estimates/dK", "intervals/dK lower", "intervals/dK upper")
    # the first two groups in TensorBoard's order (capitals first) are the estimates and the model error
    assert sorted({t.split("/")[0] for t in tags})[:2] == ["Estimates", "Model error"]
    truth = _values(mux, "sdof-stiffness", "Estimates/dK truth")
    assert [step for step, _ in truth] == list(range(50, 601, 50)) and all(v == 0.5 for _, v in truth)
    assert _last(mux, "sdof-stiffness", "Estimates/dK") == pytest.approx(summary["estimates"]["dK"])
    th = _last(mux, "sdof-stiffness", "theta/y0[1](k)")
    assert th == pytest.approx(float(run.graph.blocks["identified"].theta[0, 0, 1]))
    assert "figures/estimates" in _tags(mux, "sdof-stiffness", "images")
    hp = _sessions(mux)["sdof-stiffness"]
    assert hp["scenario"] == "sdof-stiffness" and hp["p0"] == 1000.0
    assert summary["health"]["status"] in ("converged", "not_converged")
    passed = all(c["pass"] for c in summary["requirements"].values())
    assert hp[monitor.STATUS_HPARAM] == summary["health"]["status"] + (", requirements pass" if passed else
                                                                       ", requirements FAIL")
    charts = {c.title: list(c.multiline.tag) for c in _layout(mux, "sdof-stiffness").category[0].chart}
    assert charts["dK"] == ["Estimates/dK", "Estimates/dK truth"]


def test_the_status_is_among_the_hparams_columns_shown_by_default(tmp_path):
    """TensorBoard shows the first five hyperparameters of its list until others are ticked. The status leads
    the list: in a run whose settings have capital names (rlc-circuit: C, C0_rel, L, L0_rel, R, R0_rel, which
    sort before a lower-case 'status'), and beside runs of other scenarios with a status that differs."""
    _run(tmp_path, "rlc-circuit", steps=200, log_every=50)
    order = _hparams_order(_mux(tmp_path / "runs"))
    assert order[0] == monitor.STATUS_HPARAM, order[:HPARAMS_SHOWN]
    assert sorted(order[1:HPARAMS_SHOWN]) == ["C", "C0_rel", "L", "L0_rel"]       # a plain 'status' came later
    _run(tmp_path, "sdof-stiffness", steps=2000, members=[{"p0": 1e6}, {"p0": 1e-5}])    # one not converged
    mux = _mux(tmp_path / "runs")
    statuses = {hp[monitor.STATUS_HPARAM] for hp in _sessions(mux).values()}
    assert len(statuses) == 2, statuses
    assert _hparams_order(mux)[0] == monitor.STATUS_HPARAM


def test_a_batch_logs_aggregates_and_a_few_members(tmp_path):
    _, summary, mux = _run(tmp_path, steps=300, batch=8, log_every=30)
    tags = _tags(mux, "sdof-stiffness")
    checks = {f"final/{k}" for k in ("fit_percent", "fit_percent_initial", "z_autocorr_max", "z_whiteness_p",
                                     "z_w_xcorr_max", "residual_bound", "dK lower", "dK upper", "dC lower",
                                     "dC upper", "requirements passed", "validation_rmse",
                                     "validation_rmse_initial", "validation_fit_percent",
                                     "validation_fit_percent_initial")}
    bands = {f"intervals/{k} {side}" for k in ("dK", "dC") for side in ("lower", "upper")}
    assert len(tags - checks - bands) <= 40, sorted(tags)   # residual checks, validation, intervals on top
    members = sorted(t for t in tags if t.startswith("members/"))
    assert members == sorted(f"members/{k} m{b}" for k in ("dK", "dC", "z rms") for b in range(3))
    assert {"Estimates/dK mean", "Estimates/dK truth", "quantiles/dK q10", "quantiles/dK q50", "quantiles/dK q90",
            "quantiles/z rms q50", "Model error/z rms"} <= tags
    dK = torch.tensor(summary["estimates"]["dK"], dtype=torch.float64)
    assert _last(mux, "sdof-stiffness", "quantiles/dK q50") == pytest.approx(float(dK.quantile(0.5)))
    assert _last(mux, "sdof-stiffness", "Estimates/dK mean") == pytest.approx(float(dK.mean()))
    assert _last(mux, "sdof-stiffness", "members/dK m2") == pytest.approx(float(dK[2]))
    layout = _layout(mux, "sdof-stiffness")
    charts = {c.title: c for c in layout.category[0].chart}
    assert list(charts["dK"].multiline.tag) == ["Estimates/dK mean", "quantiles/dK q10", "quantiles/dK q50",
                                                 "quantiles/dK q90", "Estimates/dK truth", "members/dK m0",
                                                 "members/dK m1", "members/dK m2"]
    band = charts["dK: mean within the 10-90% band"].margin.series[0]
    assert (band.value, band.lower, band.upper) == ("Estimates/dK mean", "quantiles/dK q10", "quantiles/dK q90")
    counts = summary["health"]["counts"]
    expected = ", ".join(f"{s} {n}" for s, n in sorted(counts.items()) if n)
    per = [all(m) for m in zip(*(c["member_pass"] for c in summary["requirements"].values()))]
    expected += f"; requirements pass {sum(per)} of {len(per)}"
    assert _sessions(mux)["sdof-stiffness"][monitor.STATUS_HPARAM] == expected


def test_large_batches_trace_the_chosen_members_and_histograms(tmp_path):
    _, summary, mux = _run(tmp_path, steps=100, batch=20, log_every=10, trace=[4, 11])
    tags = _tags(mux, "sdof-stiffness")
    assert {t for t in tags if t.startswith("members/z rms")} == {"members/z rms m4", "members/z rms m11"}
    assert _last(mux, "sdof-stiffness", "members/dK m11") == pytest.approx(summary["estimates"]["dK"][11])
    buckets = tensor_util.make_ndarray(mux.Tensors("sdof-stiffness", "spread/dK")[-1].tensor_proto)
    assert buckets[:, 2].sum() == 20 and "spread/z rms" in _tags(mux, "sdof-stiffness", "histograms")


def test_a_truth_per_member_puts_the_error_beside_the_estimate(tmp_path):
    run = Run("sdof-stiffness", steps=200, out=tmp_path / "r", log_every=50,
              members=[{"dK": 0.2}, {"dK": 0.4}, {"dK": 0.6}])
    run.advance(progress=False)
    summary = run.finish(figures=False)
    tags = _tags(_mux(tmp_path / "r"), ".")
    assert "Estimates/dK |error| mean" in tags and "Estimates/dK truth" not in tags and "Estimates/dC truth" in tags
    err = sum(abs(e - t) for e, t in zip(summary["estimates"]["dK"], (0.2, 0.4, 0.6))) / 3
    assert _last(_mux(tmp_path / "r"), ".", "errors/dK") == pytest.approx(err)


def test_setting_text_summarizes_long_per_member_lists():
    assert monitor.setting_text([0.1, 0.2]) == "[0.1, 0.2]" and monitor.setting_text(0.5) == "0.5"
    assert monitor.setting_text([3, 1, 2, 5, 4]) == "per member (1..5, 5 values)"
    assert monitor.setting_text(["a"] * 6) == "per member (6 values)"


def test_member_status_from_the_summary():
    assert monitor.member_status({"batch": 2, "diverged": [{"member": 1, "step": 9}]}) == ["finished", "diverged"]
    assert monitor.member_status({"batch": 2, "status": ["converged", "not_converged"]}) == ["converged",
                                                                                           "not_converged"]
    assert monitor.member_status({"batch": 1, "status": [{"status": "converged", "step": 3}]}) == ["converged"]
    assert monitor.status_text({"batch": 3, "status": ["converged", "diverged", "converged"]}) == \
        "converged 2, diverged 1"
    with_checks = {"batch": 2, "status": ["converged", "undetermined"],
                   "requirements": {"estimates.dK": {"pass": False, "member_pass": [True, False]}}}
    assert monitor.status_text(with_checks) == "converged 1, undetermined 1; requirements pass 1 of 2"
    assert monitor.status_text({"batch": 1, "status": "converged", "requirements": {"a": {"pass": True}}}) == \
        "converged, requirements pass"
    assert monitor.session_status({"batch": 2, "status": ["converged", "converged"]}) == "STATUS_SUCCESS"
    assert monitor.session_status({"batch": 2, "status": ["converged", "diverged"]}) == "STATUS_FAILURE"
    assert monitor.session_status({"batch": 1, "status": "not_converged"}) == "STATUS_UNKNOWN"


SWEEP = dict(scenario="sdof-stiffness", steps=200, seeds=2, grid={"dK": [0.3, 0.5, 0.7]}, fixed={"nu": 10},
             shard_size=4)


def test_a_sweep_writes_one_session_per_member(tmp_path):
    rows = sweeps.run_sweep(sweeps.Sweep.from_dict(SWEEP), out=tmp_path / "sw", progress=False)
    mux = _mux(tmp_path / "sw")
    assert sorted(mux.Runs()) == [f"members/member_{m:06d}" for m in range(6)] + ["shard_0000", "shard_0001"]
    sessions = _sessions(mux)
    assert sorted(sessions) == [f"members/member_{m:06d}" for m in range(6)]      # the shards are not rows
    for r in rows:
        run = f"members/member_{r['member']:06d}"
        assert sessions[run]["dK"] == r["dK"] and sessions[run]["seed"] == r["seed"]
        passed = all(v for k, v in r.items() if k.startswith("pass_"))
        assert r["status"] in ("converged", "undetermined", "not_converged")   # never diverged
        assert sessions[run][monitor.STATUS_HPARAM] == r["status"] + (", requirements pass" if passed else
                                                                      ", requirements FAIL")
        assert _last(mux, run, "final/dK") == pytest.approx(r["est_dK"])
        assert _last(mux, run, "final/|error| dK") == pytest.approx(abs(r["err_dK"]))
        assert _last(mux, run, "final/z_rms_final") == pytest.approx(r["z_rms_final"])
        assert _last(mux, run, "final/diverged") == 0.0 and "final/Ts" not in _tags(mux, run)


def test_a_large_sweep_makes_one_session_per_shard_and_says_why(tmp_path, monkeypatch):
    monkeypatch.setattr(sweeps, "HPARAMS_MEMBERS_MAX", 5)
    rows = sweeps.run_sweep(sweeps.Sweep.from_dict(SWEEP), out=tmp_path / "sw", progress=False)
    mux = _mux(tmp_path / "sw")
    assert sorted(mux.Runs()) == ["shard_0000", "shard_0001"]
    sessions = _sessions(mux)
    last = [r["status"] for r in rows if r["shard"] == 1]
    assert sessions["shard_0000"]["members"] == "0..3" and len(last) == 2
    passed = sum(all(v for k, v in r.items() if k.startswith("pass_")) for r in rows if r["shard"] == 1)
    assert sessions["shard_0001"][monitor.STATUS_HPARAM] == \
        ", ".join(f"{s} {last.count(s)}" for s in sorted(set(last))) + f"; requirements pass {passed} of 2"
    assert sessions["shard_0000"]["Ts"] == 0.01 and sessions["shard_0000"]["nu"] == 10
    assert sessions["shard_0000"]["dK"] == "[0.3, 0.3, 0.5, 0.5]"             # per member, short: as it is
    assert "final/dK" in _tags(mux, "shard_0000")
    note = mux.Tensors("shard_0000", "sweep/text_summary")[0].tensor_proto.string_val[0].decode()
    assert "6 members" in note and "sweep.csv" in note and "500 runs" in note


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _post(url: str, body: dict) -> dict:
    req = urllib.request.Request(url, data=json.dumps(body).encode(), headers={"Content-Type": "application/json",
                                                                               "X-TensorBoard-Feature-Flags": "{}"})
    with urllib.request.urlopen(req, timeout=10) as r:
        return json.loads(r.read())


@pytest.mark.slow
def test_tensorboard_serves_one_run_per_run_and_every_member_in_hparams(tmp_path):
    """A real TensorBoard on 127.0.0.1 over a mixed folder: a single run, a batch run and a sweep of 6 members.
    Its run list holds each run once; its HParams table holds the two runs and the six members, with the
    settings of both scenarios (the union) and the final estimates as metrics."""
    _run(tmp_path, steps=200, log_every=50)
    _run(tmp_path, "sdof-dynamic-impedance", steps=200, batch=2, log_every=50)
    sweeps.run_sweep(sweeps.Sweep.from_dict(SWEEP), out=tmp_path / "runs" / "sweep", progress=False)
    port = _free_port()
    server = subprocess.Popen([sys.executable, "-m", "tensorboard.main", "--logdir", str(tmp_path / "runs"),
                               "--host", "127.0.0.1", "--port", str(port), "--load_fast", "false"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        base = f"http://127.0.0.1:{port}"
        expected = sorted(["sdof-stiffness", "sdof-dynamic-impedance"] + [f"sweep/members/member_{m:06d}"
                                                                          for m in range(6)])
        sessions: list = []
        for _ in range(240):                  # until TensorBoard has loaded every run (it loads in the background)
            time.sleep(0.5)
            try:
                groups = _post(f"{base}/data/plugin/hparams/session_groups", {
                    "experimentName": "", "startIndex": 0, "sliceSize": 100, "colParams": [],
                    "allowedStatuses": ["STATUS_UNKNOWN", "STATUS_SUCCESS", "STATUS_FAILURE", "STATUS_RUNNING"]})
            except OSError:
                continue
            sessions = sorted(s["name"] for g in groups.get("sessionGroups", []) for s in g["sessions"])
            if sessions == expected:
                break
        assert sessions == expected
        with urllib.request.urlopen(f"{base}/data/runs", timeout=5) as r:
            runs = json.loads(r.read())
        assert sorted(runs) == sorted(expected + ["sweep/shard_0000", "sweep/shard_0001"])
        experiment = _post(f"{base}/data/plugin/hparams/experiment", {"experimentName": ""})
        hparams = {h["name"] for h in experiment["hparamInfos"]}
        assert {"scenario", monitor.STATUS_HPARAM, "p0", "dK", "gain", "seed"} <= hparams, ", ".join(sorted(hparams))
        shown = [h["name"] for h in experiment["hparamInfos"]][:HPARAMS_SHOWN]      # the columns shown at first
        assert monitor.STATUS_HPARAM in shown, shown
        metrics = {m["name"]["tag"] for m in experiment["metricInfos"]}
        assert {"final/dK", "final/dc_gain", "final/|error| dK", "final/freq_rel_err_max"} <= metrics
    finally:
        server.terminate()
        server.wait(timeout=30)


def test_run_figures_carry_units_and_legends(tmp_path):
    from rcotorch.figures import run_figures
    run = Run("sdof-stiffness", steps=200, out=tmp_path / "r", log_every=20)
    run.advance(progress=False)
    figs = run_figures(run)
    axes = figs["estimates"].axes[::2]                  # the left column: the whole run (right: the window)
    assert [a.get_ylabel() for a in axes] == ["dK [N/m]", "dC [N s/m]"] and axes[-1].get_xlabel() == "time [s]"
    assert figs["estimates"].axes[-1].get_xlabel() == "time [s]" and len(figs["estimates"].axes) == 4
    assert [t.get_text() for t in axes[0].get_legend().get_texts()] == ["estimate", "truth", "initial model",
                                                                       "95% interval at the end"]
    initial = [ln for ln in axes[0].get_lines() if ln.get_label() == "initial model"][0]
    assert initial.get_ydata()[0] == 0.0                                     # theta starts at zero: dK = 0
    assert figs["model_error"].axes[0].get_ylabel() == "rms of z = y - y_hat [m/s]"
    batch = Run("sdof-stiffness", steps=100, batch=3, out=tmp_path / "b", log_every=20)
    batch.advance(progress=False)
    labels = [t.get_text() for t in run_figures(batch)["estimates"].axes[0].get_legend().get_texts()]
    assert labels == ["member 0", "member 1", "member 2", "truth", "initial model",
                      "95% interval at the end"]


def test_figures_drawn_meanwhile_are_the_same_bytes_and_errors_reach_the_caller(tmp_path):
    import threading

    from rcotorch.figures import draw_meanwhile, pngs, run_figures
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
    assert all(png.startswith(b"\x89PNG\r\n\x1a\n") for png in drawn.values())

    def broken():
        raise ValueError("no history to draw")
    with pytest.raises(ValueError, match="no history to draw"):
        draw_meanwhile(broken)()
    run.close()
