"""TensorBoard as written by runs and sweeps, read back with TensorBoard's own event readers (and, in one test,
served by TensorBoard and queried through its HParams API): the run and its sibling runs (truth, batch
quantiles), tags in engineering notation, wall times that read simulated seconds, Custom Scalars patterns,
HParams sessions, and the event files' checksum."""

import json
import re
import socket
import subprocess
import sys
import time
import urllib.parse
import urllib.request

import numpy as np
import pytest
import torch
from tensorboard.backend.event_processing.plugin_event_multiplexer import EventMultiplexer
from tensorboard.compat.tensorflow_stub.pywrap_tensorflow import masked_crc32c as tensorboards_crc
from tensorboard.plugins.custom_scalar import layout_pb2
from tensorboard.plugins.hparams import metadata as hp_metadata
from tensorboard.util import tensor_util

from rcotorch.run import event_file, monitor
from rcotorch.run import sweep as sweeps
from rcotorch.run.outputs import load_checkpoint
from rcotorch.run.runner import Run


def _log_steps(every: int, last: int) -> list[int]:
    """The steps a run logs at (the initial model at 0): every / 2, / 4, / 8, / 16 before the first interval
    (integer halves, at least 1), then every ``every`` steps, up to ``last``."""
    early = sorted({every >> j for j in range(1, 5)} - {0})
    return [0] + early + list(range(every, last + 1, every))


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


def _events(mux, run, tag) -> list:
    return list(mux.Tensors(run, tag))


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


def _matching(pattern: str, tags: set) -> set:
    return {t for t in tags if re.search(pattern, t)}


HPARAMS_SHOWN = 5     # TensorBoard's HParams table shows the first five hyperparameters of its list at first


def _hparams_order(mux) -> list[str]:
    """The hyperparameters in the order TensorBoard's HParams dashboard lists them (those that differ between
    sessions first, each part by name), computed by TensorBoard's own backend from the sessions read back."""
    from tensorboard.plugins.hparams import backend_context

    content = mux.PluginRunToTagToContent(hp_metadata.PLUGIN_NAME)
    experiment = backend_context.Context(None).experiment_from_metadata(None, "", False, content, [])
    return [h.name for h in experiment.hparam_infos]


def _hparams_table(logdir) -> dict[str, dict]:
    """TensorBoard's HParams table of ``logdir``, computed by its own backend from the event files (as its
    dashboard asks for it): session name -> {'hparams': {name: value}, 'metrics': {tag: value}}."""
    from tensorboard import context
    from tensorboard.backend.event_processing.data_provider import MultiplexerDataProvider
    from tensorboard.plugins import base_plugin
    from tensorboard.plugins.hparams import api_pb2, backend_context, list_session_groups

    mux = _mux(logdir)
    tb = base_plugin.TBContext(logdir=str(logdir), multiplexer=mux,
                               data_provider=MultiplexerDataProvider(mux, str(logdir)))
    request = api_pb2.ListSessionGroupsRequest(start_index=0, slice_size=1000, allowed_statuses=[
        api_pb2.STATUS_UNKNOWN, api_pb2.STATUS_SUCCESS, api_pb2.STATUS_FAILURE, api_pb2.STATUS_RUNNING])
    groups = list_session_groups.Handler(context.RequestContext(), backend_context.Context(tb), "", request).run()
    out = {}
    for g in groups.session_groups:
        for session in g.sessions:
            out[session.name] = {
                "hparams": {k: v.WhichOneof("kind") and getattr(v, v.WhichOneof("kind")) for k, v in g.hparams.items()},
                "metrics": {m.name.tag if not m.name.group else f"{m.name.group}.{m.name.tag}": m.value
                            for m in session.metric_values}}
    return out


# --- engineering notation and the checksum ------------------------------------------------------------------
def test_engineering_notation_puts_the_size_in_one_to_a_thousand():
    E, S = monitor.engineering, monitor.Scaled
    assert E(23.5e-6, "F") == S(1e-6, "uF") and E(0.055, "H") == S(1e-3, "mH") and E(250.0, "ohm") == S(1.0, "ohm")
    assert E(4.2e3, "N/m") == S(1e3, "kN/m") and E(0.5, "N s/m") == S(1e-3, "mN s/m")
    assert E(2e-3, "m/(N s)") == S(1e-3, "mm/(N s)") and E(1000.0, "V") == S(1e3, "kV")
    assert E(999.9, "V") == S(1.0, "V") and E(1e-3, "V") == S(1e-3, "mV") and E(0.99e-3, "V") == S(1e-6, "uV")
    # a unit that takes no prefix (a power, an already prefixed unit, none) gets a power of ten
    assert E(2e-3, "1/s^2") == S(1e-3, "1e-3 1/s^2") and E(5e-3, "m^2") == S(1e-3, "1e-3 m^2")
    assert E(4e3, "kg") == S(1e3, "1e3 kg") and E(0.2, "") == S(1e-3, "1e-3")
    for size in (0.0, None, float("nan")):
        assert E(size, "N") == S(1.0, "N")
    assert S(1.0, "").label == "[-]" and S(1e-6, "uF").label == "[uF]"


def test_each_estimate_is_sized_by_its_scenario_so_every_run_writes_the_same_tags():
    import rcotorch.run.scenario as scenarios
    rlc = monitor.estimate_scales(scenarios.get("rlc-circuit"), ["L", "C", "R"], {"C": 1e-3})
    assert {k: s.unit for k, s in rlc.items()} == {"L": "mH", "C": "uF", "R": "ohm"}   # the defaults' truths
    sdof = monitor.estimate_scales(scenarios.get("sdof-stiffness"), ["dK", "dC"])
    assert {k: s.unit for k, s in sdof.items()} == {"dK": "mN/m", "dC": "mN s/m"}       # its scales: K, C


def test_the_event_checksum_is_tensorboards_crc32c():
    assert event_file.crc32c(b"123456789") == 0xE3069283                 # the CRC-32C check value
    rng = np.random.default_rng(0)
    for n in [*range(0, 40), 300, 1023, 1024, 1025, 1040, 2049, 100_000]:
        data = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        assert event_file.masked_crc32c(data) == tensorboards_crc(data), n


# --- a single run ------------------------------------------------------------------------------------------
def test_a_single_run_draws_estimate_truth_and_tolerance_band_under_one_tag(tmp_path):
    run, summary, mux = _run(tmp_path, steps=600, log_every=50)
    name = "sdof-stiffness"
    # the sibling runs: the band's edges, the truth and the HParams session
    assert sorted(mux.Runs()) == [name] + [f"{name}/{role}" for role in ("lower", "truth", "upper", "verdict")]
    tags = _tags(mux, name)
    assert {"Estimates/dK [mN/m]", "Estimates/dK |error| [mN/m]", "Estimates/dC [mN s/m]",
            "Estimates/dC |error| [mN s/m]", "Model error/z rms [dB re 1 m/s]", "theta/y0[0](k)",
            "theta/y0[1](k)"} <= tags
    assert not any(t.startswith(("members/", "quantiles/", "health/", "final/", "metrics/")) for t in tags)
    for role in ("lower", "truth", "upper"):
        assert _tags(mux, f"{name}/{role}") == {"Estimates/dK [mN/m]", "Estimates/dC [mN s/m]"}
    # the first two groups in TensorBoard's order (capitals first) are the estimates and the model error
    assert sorted({t.split("/")[0] for t in tags})[:2] == ["Estimates", "Model error"]
    steps = _log_steps(50, 600)                                         # the initial model at step 0, then logs
    truth = _values(mux, f"{name}/truth", "Estimates/dK [mN/m]")
    assert [s for s, _ in truth] == steps and all(v == 500.0 for _, v in truth)
    # the band is truth -+ the scenario's requirement on dK (|err| < 0.01 N/m = 10 mN/m), at every step
    assert _values(mux, f"{name}/lower", "Estimates/dK [mN/m]") == [(s, 490.0) for s in steps]
    assert _values(mux, f"{name}/upper", "Estimates/dK [mN/m]") == [(s, 510.0) for s in steps]
    est = _values(mux, name, "Estimates/dK [mN/m]")
    assert [s for s, _ in est] == steps and est[0][1] == 0.0             # theta starts at zero: dK = 0
    # the scaled value times its scale is the estimate; the error is |estimate - truth| in the same unit
    assert est[-1][1] * 1e-3 == pytest.approx(summary["estimates"]["dK"], rel=1e-6)
    err = _last(mux, name, "Estimates/dK |error| [mN/m]")
    assert err * 1e-3 == pytest.approx(abs(summary["estimates"]["dK"] - 0.5), rel=1e-5, abs=1e-9)
    assert _last(mux, name, "Estimates/dC [mN s/m]") * 1e-3 == pytest.approx(summary["estimates"]["dC"], rel=1e-5)
    th = _last(mux, name, "theta/y0[1](k)")
    assert th == pytest.approx(float(run.graph.blocks["identified"].theta[0, 0, 1]))
    # wall time = origin + k dt for the run and its siblings: TensorBoard's Relative axis reads simulated seconds
    origin = load_checkpoint(tmp_path / "runs" / name / "checkpoint.pt")["tb_origin"]
    for run_name in (name, f"{name}/truth", f"{name}/lower"):
        for e in _events(mux, run_name, "Estimates/dK [mN/m]"):
            assert e.wall_time - origin == pytest.approx(e.step * 0.01, abs=1e-5)
    # the settings card says what the x axis is
    text = mux.Tensors(name, "settings/text_summary")[0].tensor_proto.string_val[0].decode()
    assert "sample index" in text and "dt = 0.01 s" in text
    # the band over time at the logged steps of the run's history, about the estimate (the margin chart's three
    # tags, at the same steps), ending at the final interval, and wider early on (the RLS covariance shrinks)
    logged = steps[1:]
    centre = _values(mux, name, "intervals/dK [mN/m]")
    lower = _values(mux, name, "intervals/dK lower [mN/m]")
    upper = dict(_values(mux, name, "intervals/dK upper [mN/m]"))
    assert [s for s, _ in centre] == [s for s, _ in lower] == sorted(upper) == logged
    assert dict(centre) == pytest.approx({s: v for s, v in est if s in upper}, rel=1e-6)
    assert lower[-1][1] * 1e-3 == pytest.approx(summary["intervals"]["dK"]["lower"], rel=1e-6)
    assert upper[logged[-1]] * 1e-3 == pytest.approx(summary["intervals"]["dK"]["upper"], rel=1e-6)
    values = dict(est)
    assert all(v <= values[s] <= upper[s] for s, v in lower)
    assert upper[logged[0]] - lower[0][1] > 2 * (upper[logged[-1]] - lower[-1][1])
    assert "figures/estimates" in _tags(mux, name, "images")
    hp = _sessions(mux)[f"{name}/verdict"]
    assert hp["scenario"] == name and hp["p0"] == 1000.0 and hp["dK [N/m]"] == 0.5 and hp["Ts [s]"] == 0.01
    passed = all(c["pass"] for c in summary["requirements"].values())
    assert hp[monitor.STATUS_HPARAM].split(":")[0].split(" (")[0] == summary["health"]["status"]
    assert hp[monitor.REQUIREMENTS_HPARAM] == ("pass" if passed else "FAIL")


def test_each_role_keeps_its_place_in_the_run_list_and_so_its_colour(tmp_path):
    """TensorBoard colours each run by its place in its run list, which is ordered by start time, then by name:
    truth was the second colour beside one run and the fourth beside a batch (after q10 and q90). The estimate,
    lower, truth and upper now take the same places in every run, one member or many, whichever order the list
    is built in: by the exact start times (TensorBoard's Python loader) or by name (its default loader holds
    start times coarsely, so that runs started together tie)."""
    _run(tmp_path, "sdof-stiffness", steps=100, log_every=50)
    _run(tmp_path, "twodof-stiffness", steps=100, batch=4, log_every=50)
    mux = _mux(tmp_path / "runs")
    start = {r: mux.GetAccumulator(r).FirstEventTimestamp() for r in mux.Runs()}
    roles = ["", "/lower", "/truth", "/upper", "/verdict"]
    for name in ("sdof-stiffness", "twodof-stiffness"):
        own = [r for r in mux.Runs() if r.split("/")[0] == name]
        expected = [name + role for role in roles]
        assert sorted(own, key=lambda r: (start[r], r)) == expected
        assert sorted(own) == expected
    # the two runs are not interleaved: each run's roles follow one another in the whole list
    listed = sorted(mux.Runs(), key=lambda r: (start[r], r))
    assert [r.split("/")[0] for r in listed] == ["sdof-stiffness"] * 5 + ["twodof-stiffness"] * 5


def test_a_change_detection_shows_beside_the_model_error_and_explains_the_status(tmp_path):
    """A change's detection was hard to see: the share of alarmed members was a card in the collapsed group
    "detection", and HParams read "pass" beside "not_converged" without saying why. The card is now in the
    expanded "Model error" group (and in the Custom Scalars model error category), and the session's status
    says why and when the detector alarmed, its first alarm also a metric."""
    import rcotorch as rt

    known = rt.LTI.continuous([[0, 1], [-0.6, -0.8]], [[0, 0], [1, 1]], [[0, 1], [1, 0], [0, 1]], np.zeros((3, 2)),
                              inputs=["w", "u"], outputs={"y": 1, "y0": 2}, dt=0.01, name="known")
    ident = rt.RCOEstimator.static_gain({"y0": 2}, p0=1e3, lam=0.998)
    det = rt.ChangeDetector(1, warmup=1000, window=500, holdoff=1000, threshold=30.0)
    g = rt.refinement(known, ident, truth=rt.Gain(np.zeros((1, 2)), name="unknown"),
                      excitation=rt.WhiteNoise(1, seed=3), nu=15, batch_size=1,
                      noise=rt.WhiteNoise(1, std=0.005, seed=4), blocks=[det],
                      connections=[("error.out", "detector.z")])
    g.add_hook(rt.at_step(2000, lambda gr: gr.blocks["unknown"].K.copy_(torch.tensor([[-0.5, 0.0]]))))
    out = tmp_path / "change"
    result = rt.refine(g, 2600, {"dK": lambda gr: -gr.role("estimator").theta[:, 0, 0]},
                       truth_history={"dK": [(0.0, 0.0), (20.0, 0.5)]}, scales={"dK": 1.0}, out=out,
                       intervals=False, validation=False, figures=False, progress=False)
    summary = result.summary
    first = summary["changes"]["detector"]["first_alarm_s"]
    assert 20.0 < first < 25.0
    mux = _mux(out)
    tags = _tags(mux, ".")
    groups = sorted({t.split("/")[0] for t in tags})
    tag = "Model error/detector alarmed members [%]"
    assert tag in tags and tag.split("/")[0] in groups[:2]               # the two groups TensorBoard expands
    alarmed = _values(mux, ".", tag)
    assert alarmed[0][1] == 0.0 and alarmed[-1][1] == 100.0
    charts = {c.title: c for category in _layout(mux, ".").category for c in category.chart}
    assert _matching(charts["detector: alarmed members [%]"].multiline.tag[0], tags) == {tag}
    # the truth run steps at the change, under the estimate's tag
    truth = dict(_values(mux, "truth", "Estimates/dK [-]"))
    assert truth[min(truth)] == 0.0 and truth[max(truth)] == 0.5
    table = _hparams_table(out)
    status = table["verdict"]["hparams"][monitor.STATUS_HPARAM]
    assert status.startswith(summary["status"])
    if summary["status"] != "converged":
        assert summary["health"]["why"] in status
    assert f"detector alarm at {first:g} s" in status
    assert table["verdict"]["metrics"]["verdict/detector first alarm [s]"] == pytest.approx(first)
    # a graph built in Python: HParams names it as its figures do (its folder), the settings text says why it
    # has no table, and the model error's dB say their reference where y has no unit
    assert table["verdict"]["hparams"]["scenario"] == "change"
    text = mux.Tensors(".", "settings/text_summary")[0].tensor_proto.string_val[0].decode()
    assert text.startswith("No settings: the graph was built in Python") and "| setting |" not in text
    assert "Model error/z rms [dB re 1 unit of y]" in tags


def test_custom_scalars_patterns_are_anchored_and_each_draws_only_its_own_tags(tmp_path):
    _run(tmp_path, steps=300, log_every=50)
    _run(tmp_path, "twodof-stiffness", steps=200, batch=4, log_every=50)
    mux = _mux(tmp_path / "runs")
    every = set().union(*(_tags(mux, r) for r in mux.Runs()))
    layout = _layout(mux, "sdof-stiffness")
    assert [c.title for c in layout.category] == [
        "sdof-stiffness: estimates", "sdof-stiffness: |estimate - truth|",
        "sdof-stiffness: estimate within truth ± tolerance", "sdof-stiffness: estimate within its confidence band",
        "sdof-stiffness: model error z = y - y_hat"]
    charts = {c.title: c for category in layout.category for c in category.chart}
    assert list(charts["dK [mN/m]"].multiline.tag) == [r"^Estimates/dK\ \[mN/m\]$"]
    assert _matching(charts["dK [mN/m]"].multiline.tag[0], every) == {"Estimates/dK [mN/m]"}
    assert _matching(charts["dK: |estimate - truth| [mN/m]"].multiline.tag[0], every) == {
        "Estimates/dK |error| [mN/m]"}
    # which runs hold the one tag: the estimate, the band's edges and the truth, four series in four colours
    assert {r for r in mux.Runs() if "Estimates/dK [mN/m]" in _tags(mux, r)} == {
        f"sdof-stiffness{role}" for role in ("", "/lower", "/truth", "/upper")}
    margin = charts["dK: estimate within truth ± 10 mN/m"].margin.series[0]
    assert (margin.value, margin.lower, margin.upper) == ("bands/dK [mN/m]", "bands/dK low [mN/m]",
                                                          "bands/dK high [mN/m]")
    assert _values(mux, "sdof-stiffness", "bands/dK low [mN/m]")[-1][1] == pytest.approx(490.0)
    batch = {c.title: c for category in _layout(mux, "twodof-stiffness").category for c in category.chart}
    pattern, members = batch["dk1 [mN/m]"].multiline.tag
    assert _matching(pattern, every) == {"Estimates/dk1 [mN/m]"}
    assert _matching(members, every) == {f"members/dk1 m{b} [mN/m]" for b in range(4)}
    for category in layout.category:
        for chart in category.chart:
            for p in chart.multiline.tag:
                assert p.startswith("^") and p.endswith("$"), p


def test_each_margin_chart_reads_one_run_and_the_charts_keep_the_estimates_order(tmp_path):
    """Each margin chart warned "Missing Tags": its value was the estimate's tag, which the truth run holds
    without the band's bounds. And the charts came jumbled: the dashboard draws a category's multiline charts
    first, then its margin charts in the reverse of the layout's order. Now a margin chart's three tags are in
    the run alone, a category holds charts of one kind, and margin charts are listed backwards."""
    _, summary, mux = _run(tmp_path, "twodof-stiffness", steps=300, batch=4, log_every=50)
    layout = _layout(mux, "twodof-stiffness")
    keys = list(summary["estimates"])
    assert len(keys) > 1
    for category in layout.category:
        kinds = {chart.WhichOneof("content") for chart in category.chart}
        assert len(kinds) == 1, category.title
        titles = [chart.title.split(":")[0].split(" ")[0] for chart in category.chart]
        if kinds == {"margin"}:
            assert titles == keys[::-1], category.title          # drawn in the order of the keys
        elif category.title.endswith(("estimates", "|estimate - truth|")):
            assert titles == keys
        for chart in category.chart:
            for series in chart.margin.series:
                tags = {series.value, series.lower, series.upper}
                held = {r: tags & _tags(mux, r) for r in mux.Runs()}
                assert {r for r, h in held.items() if h} == {"twodof-stiffness"}, held
                assert held["twodof-stiffness"] == tags
                steps = [[s for s, _ in _values(mux, "twodof-stiffness", t)] for t in sorted(tags)]
                assert steps[0] and steps[0] == steps[1] == steps[2]       # the chart pairs them by step


def test_a_resumed_run_continues_the_same_time_axis(tmp_path):
    out = tmp_path / "runs" / "r"
    run = Run("sdof-stiffness", steps=300, out=out, log_every=50)
    run.advance(until=150, progress=False)
    run.save()
    run.close()
    origin = load_checkpoint(out / "checkpoint.pt")["tb_origin"]
    again = Run.resume(out, steps=300)
    again.advance(progress=False)
    again.finish(figures=False)
    mux = _mux(tmp_path / "runs")
    for name in ("r", "r/truth"):
        events = sorted(_events(mux, name, "Estimates/dK [mN/m]"), key=lambda e: e.step)   # files in name order
        assert [e.step for e in events] == _log_steps(50, 300)
        assert all(e.wall_time - origin == pytest.approx(e.step * 0.01, abs=1e-5) for e in events)


# --- HParams ---------------------------------------------------------------------------------------------------
def test_hparams_has_the_metrics_of_a_run_opened_on_its_own_folder(tmp_path):
    """TensorBoard opened on one run's folder names that run "." and finds no metrics of a session there (it
    looks them up in "./."): every metric column was empty. The session is the run's ``verdict/`` folder, a run
    of its own, whose metrics it finds whether the logdir is the run's folder or the folder above it."""
    _, summary, _ = _run(tmp_path, steps=300, log_every=50)
    folder = tmp_path / "runs" / "sdof-stiffness"
    for logdir, session in ((folder, "verdict"), (folder.parent, "sdof-stiffness/verdict")):
        table = _hparams_table(logdir)
        assert list(table) == [session]
        hp, metrics = table[session]["hparams"], table[session]["metrics"]
        assert hp[monitor.STATUS_HPARAM].startswith(summary["health"]["status"])
        assert hp[monitor.REQUIREMENTS_HPARAM] in ("pass", "FAIL") and hp["scenario"] == "sdof-stiffness"
        assert metrics["final/dK [mN/m]"] * 1e-3 == pytest.approx(summary["estimates"]["dK"], rel=1e-6)
        assert metrics["verdict/dK truth [mN/m]"] == 500.0
        assert metrics["final/dK |error| [mN/m]"] * 1e-3 == pytest.approx(abs(summary["estimates"]["dK"] - 0.5),
                                                                         rel=1e-5, abs=1e-9)
        assert metrics["verdict/dK lower [mN/m]"] * 1e-3 == pytest.approx(summary["intervals"]["dK"]["lower"],
                                                                         rel=1e-6)
        assert metrics["metrics/z_rms_final"] == pytest.approx(summary["metrics"]["z_rms_final"], rel=1e-6)
        passed = all(c["pass"] for c in summary["requirements"].values())
        assert metrics["verdict/requirements passed"] == float(passed) and metrics["verdict/diverged"] == 0
        # the metric columns (sorted by tag; the first five shown) open on the estimates and their errors
        assert sorted(metrics)[:4] == ["final/dC [mN s/m]", "final/dC |error| [mN s/m]", "final/dK [mN/m]",
                                       "final/dK |error| [mN/m]"]


def test_requirements_and_status_lead_the_hparams_columns_and_settings_carry_units(tmp_path):
    """TensorBoard shows the first five hyperparameters of its list until others are ticked. The requirements
    and the status lead it: in a run whose settings have capital names (rlc-circuit: C, L, R, ... sort before
    lower case), and beside runs of other scenarios with a status that differs. Settings that share a name and
    not a unit (C: farads, N s/m) are separate columns."""
    _run(tmp_path, "rlc-circuit", steps=200, log_every=50)
    order = _hparams_order(_mux(tmp_path / "runs"))
    assert order[:2] == [monitor.REQUIREMENTS_HPARAM, monitor.STATUS_HPARAM], order[:HPARAMS_SHOWN]
    assert {"C [F]", "L [H]", "R [ohm]", "Ts [s]"} <= set(order)
    _run(tmp_path, "sdof-stiffness", steps=2000, members=[{"p0": 1e6}, {"p0": 1e-5}])    # one not converged
    mux = _mux(tmp_path / "runs")
    statuses = {hp[monitor.STATUS_HPARAM] for hp in _sessions(mux).values()}
    assert len(statuses) == 2, statuses
    assert _hparams_order(mux)[:2] == [monitor.REQUIREMENTS_HPARAM, monitor.STATUS_HPARAM]
    assert {"C [F]", "C [N s/m]"} <= set(_hparams_order(mux))


def test_status_and_requirements_texts():
    assert monitor.member_status({"batch": 2, "diverged": [{"member": 1, "step": 9}]}) == ["finished", "diverged"]
    assert monitor.member_status({"batch": 2, "status": ["converged", "not_converged"]}) == ["converged",
                                                                                           "not_converged"]
    assert monitor.member_status({"batch": 1, "status": [{"status": "converged", "step": 3}]}) == ["converged"]
    assert monitor.status_text({"batch": 3, "status": ["converged", "diverged", "converged"]}) == \
        "converged 2, diverged 1"
    with_checks = {"batch": 2, "status": ["converged", "undetermined"],
                   "requirements": {"estimates.dK": {"pass": False, "member_pass": [True, False]}}}
    assert monitor.requirements_text(with_checks) == "pass 1 of 2"
    assert monitor.requirements_text({"batch": 1, "requirements": {"a": {"pass": True}}}) == "pass"
    assert monitor.requirements_text({"batch": 1, "requirements": {"a": {"pass": False}}}) == "FAIL"
    assert monitor.requirements_text({"batch": 1}) == "none"
    assert monitor.session_status({"batch": 2, "status": ["converged", "converged"]}) == "STATUS_SUCCESS"
    assert monitor.session_status({"batch": 2, "status": ["converged", "diverged"]}) == "STATUS_FAILURE"
    assert monitor.session_status({"batch": 1, "status": "not_converged"}) == "STATUS_UNKNOWN"
    # one member's status says why, and when a change detector alarmed (HParams read "pass" beside
    # "not_converged" with no explanation for a run that tracked a change)
    changed = {"batch": 1, "status": "not_converged", "health": {"why": "theta_change above 0.02"},
               "changes": {"detector": {"first_alarm_s": 60.02, "first_alarm_step": 6002.0}}}
    assert monitor.status_text(changed) == "not_converged (theta_change above 0.02; detector alarm at 60.02 s)"
    assert monitor.status_text({"batch": 1, "status": "biased", "health": {"why": "biased: dC"}}) == "biased: dC"
    quiet = {"batch": 1, "status": "converged", "changes": {"detector": {"first_alarm_s": float("nan")}}}
    assert monitor.status_text(quiet) == "converged"


def test_setting_text_summarizes_long_per_member_lists():
    assert monitor.setting_text([0.1, 0.2]) == "[0.1, 0.2]" and monitor.setting_text(0.5) == "0.5"
    assert monitor.setting_text([3, 1, 2, 5, 4]) == "per member (1..5, 5 values)"
    assert monitor.setting_text(["a"] * 6) == "per member (6 values)"


# --- batches -------------------------------------------------------------------------------------------------
def test_a_batch_draws_mean_band_and_truth_under_one_tag(tmp_path):
    run, summary, mux = _run(tmp_path, steps=300, batch=8, log_every=30)
    name = "sdof-stiffness"
    assert sorted(mux.Runs()) == [name] + [f"{name}/{role}" for role in ("lower", "truth", "upper", "verdict")]
    for sibling in ("lower", "upper"):
        assert _tags(mux, f"{name}/{sibling}") == {"Estimates/dK [mN/m]", "Estimates/dC [mN s/m]",
                                                   "Model error/z rms [dB re 1 m/s]"}
    tags = _tags(mux, name)
    members = sorted(t for t in tags if t.startswith("members/"))
    assert members == sorted([f"members/dK m{b} [mN/m]" for b in range(8)] + [f"members/dC m{b} [mN s/m]"
                                                                               for b in range(8)]
                             + [f"members/z rms m{b} [dB re 1 m/s]" for b in range(8)])   # those the PNG draws
    # the model error in dB: 20 log10 of the rms over the batch, of each member's, and of their quantiles
    z = np.array([float(v) for v in run.history["z_rms"][-1]])
    assert _last(mux, name, "Model error/z rms [dB re 1 m/s]") == pytest.approx(
        20 * np.log10(np.sqrt(np.mean(z ** 2))), abs=1e-4)
    assert _last(mux, name, "members/z rms m3 [dB re 1 m/s]") == pytest.approx(20 * np.log10(z[3]), abs=1e-4)
    assert _last(mux, f"{name}/upper", "Model error/z rms [dB re 1 m/s]") == pytest.approx(
        20 * np.log10(np.quantile(z, 0.9)), abs=1e-4)
    dK = np.array(summary["estimates"]["dK"])
    assert _last(mux, name, "Estimates/dK [mN/m]") * 1e-3 == pytest.approx(dK.mean(), rel=1e-6)
    assert _last(mux, f"{name}/lower", "Estimates/dK [mN/m]") * 1e-3 == pytest.approx(np.quantile(dK, 0.1),
                                                                                      rel=1e-6)
    assert _last(mux, f"{name}/upper", "Estimates/dK [mN/m]") * 1e-3 == pytest.approx(np.quantile(dK, 0.9),
                                                                                      rel=1e-6)
    assert _last(mux, name, "members/dK m2 [mN/m]") * 1e-3 == pytest.approx(dK[2], rel=1e-6)
    assert _last(mux, name, "Estimates/dK |error| [mN/m]") * 1e-3 == pytest.approx(np.abs(dK - 0.5).mean(),
                                                                                    rel=1e-5, abs=1e-9)
    counts = summary["health"]["counts"]
    for status, n in counts.items():
        if n or status not in ("undetermined", "biased"):
            assert _last(mux, name, f"health/{status}") == n
    per = [all(m) for m in zip(*(c["member_pass"] for c in summary["requirements"].values()))]
    hp = _sessions(mux)[f"{name}/verdict"]
    assert hp[monitor.STATUS_HPARAM] == ", ".join(f"{s} {n}" for s, n in sorted(counts.items()) if n)
    assert hp[monitor.REQUIREMENTS_HPARAM] == f"pass {sum(per)} of {len(per)}"


def test_large_batches_trace_the_chosen_members_and_histograms(tmp_path):
    run, summary, mux = _run(tmp_path, steps=100, batch=20, log_every=10, trace=[4, 11])
    tags = _tags(mux, "sdof-stiffness")
    assert {t for t in tags if t.startswith("members/z rms")} == {"members/z rms m4 [dB re 1 m/s]",
                                                                   "members/z rms m11 [dB re 1 m/s]"}
    assert _last(mux, "sdof-stiffness", "members/dK m11 [mN/m]") * 1e-3 == pytest.approx(summary["estimates"]["dK"][11],
                                                                                          rel=1e-6)
    assert run.history_members == [4, 11]                           # the figures draw the traced members
    spread = sorted(mux.Tensors("sdof-stiffness", "spread/dK [mN/m]"), key=lambda e: e.step)
    assert len(spread) == 2                          # every tenth log: 13 logs (steps 1, 2, 5, then every 10)
    first = spread[0]
    buckets = tensor_util.make_ndarray(first.tensor_proto)
    assert buckets[:, 2].sum() == 20 and "spread/z rms [dB re 1 m/s]" in _tags(mux, "sdof-stiffness", "histograms")
    for b in (4, 11):                                 # the histogram spans the members' values, in the same unit
        value = dict(_values(mux, "sdof-stiffness", f"members/dK m{b} [mN/m]"))[first.step]
        assert buckets[0, 0] <= value <= buckets[-1, 1]


def test_a_small_model_error_does_not_read_zero(tmp_path):
    """z rms of 7e-7 m/s, logged in m/s, read "0" in TensorBoard's data tables (four decimals). It is logged in
    dB re 1 m/s: -123.1, for the run, its members and its quantiles."""
    run = Run("sdof-stiffness", steps=100, batch=2, out=tmp_path / "r", log_every=50)
    run.advance(until=50, progress=False)
    est = {k: v.detach().to(torch.float64).cpu() for k, v in run.scenario.estimates(run.graph, run.settings).items()}
    z = torch.tensor([7e-7, 7e-7], dtype=torch.float64)
    run.monitor.log(60, z, est)
    run.monitor.flush()
    mux = _mux(tmp_path)
    assert round(7e-7, 4) == 0.0                                     # as the tables showed it
    for name, tag in (("r", "Model error/z rms [dB re 1 m/s]"), ("r", "members/z rms m1 [dB re 1 m/s]"),
                      ("r/upper", "Model error/z rms [dB re 1 m/s]")):
        value = dict(_values(mux, name, tag))[60]
        assert value == pytest.approx(20 * np.log10(7e-7), abs=1e-3) and round(value, 4) != 0.0
    assert monitor.db(0.0) == monitor.DB_FLOOR and np.isnan(monitor.db(float("nan")))
    run.close()


def test_a_truth_per_member_puts_the_mean_error_beside_the_estimate(tmp_path):
    run = Run("sdof-stiffness", steps=200, out=tmp_path / "r", log_every=50,
              members=[{"dK": 0.2}, {"dK": 0.4}, {"dK": 0.6}])
    run.advance(progress=False)
    summary = run.finish(figures=False)
    mux = _mux(tmp_path)
    assert _tags(mux, "r/truth") == {"Estimates/dC [mN s/m]"}       # dK has no single truth to draw
    err = sum(abs(e - t) for e, t in zip(summary["estimates"]["dK"], (0.2, 0.4, 0.6))) / 3
    assert _last(mux, "r", "Estimates/dK |error| [mN/m]") * 1e-3 == pytest.approx(err, rel=1e-5)


# --- sweeps --------------------------------------------------------------------------------------------------
SWEEP = dict(scenario="sdof-stiffness", steps=200, seeds=2, grid={"dK": [0.3, 0.5, 0.7]}, fixed={"nu": 10},
             shard_size=4)


def test_a_sweep_writes_one_session_per_member(tmp_path):
    """A sweep's Scalars and Custom Scalars tabs opened blank: TensorBoard ticks no run there once a logdir holds
    more than 40, and a sweep of 36 members made 41 (its members, its shard and the shard's three siblings, and
    its own folder, for the figures). And each member's final values were logged at step 0 under the estimates'
    own tags: a dot at the start of each estimate's card and a row per member in its table. The figures are now
    in the first shard's run, and the members' values under tags of their own, at the shard's last step."""
    rows = sweeps.run_sweep(sweeps.Sweep.from_dict(SWEEP), out=tmp_path / "sw", progress=False)
    mux = _mux(tmp_path / "sw")
    members = [f"members/member_{m:06d}" for m in range(6)]
    shards = [f"shard_{s:04d}{sub}" for s in range(2) for sub in ("", "/lower", "/truth", "/upper")]
    # one run per member and four per shard: a sweep of up to 36 members in one shard holds at most 40
    assert sorted(mux.Runs()) == sorted(members + shards)
    assert _tags(mux, "shard_0000", "images") == {"figures/sweep_dK"}
    shard_tags = set().union(*(_tags(mux, r) for r in shards))
    sessions = _sessions(mux)
    assert sorted(sessions) == members                              # the shards are not rows
    whys = {}                                                       # each member's why, from its shard's summary
    for shard in range(2):
        health = json.loads((tmp_path / "sw" / f"shard_{shard:04d}" / "summary.json").read_text())["health"]
        whys.update(zip(sorted(r["member"] for r in rows if r["shard"] == shard), health["why"]))
    for r in rows:
        run = f"members/member_{r['member']:06d}"
        assert sessions[run]["dK [N/m]"] == r["dK"] and sessions[run]["seed"] == r["seed"]
        passed = all(v for k, v in r.items() if k.startswith("pass_"))
        assert r["status"] in ("converged", "undetermined", "not_converged", "biased")   # never diverged
        why = whys[r["member"]]
        assert sessions[run][monitor.STATUS_HPARAM] == (
            r["status"] if not why else why if why.startswith(r["status"]) else f"{r['status']} ({why})")
        assert sessions[run][monitor.REQUIREMENTS_HPARAM] == ("pass" if passed else "FAIL")
        tags = _tags(mux, run)
        assert not tags & shard_tags and all(t.startswith(("final/", "metrics/", "verdict/")) for t in tags)
        assert {s for t in tags for s, _ in _values(mux, run, t)} == {SWEEP["steps"]}
        (est,) = [t for t in tags if t.startswith("final/dK [")]     # dK of sdof-stiffness in thousandths
        assert _last(mux, run, est) * 1e-3 == pytest.approx(r["est_dK"], rel=1e-6)
        (err,) = [t for t in tags if t.startswith("final/dK |error| [")]
        assert _last(mux, run, err) * 1e-3 == pytest.approx(abs(r["err_dK"]), rel=1e-5, abs=1e-9)
        assert _last(mux, run, "metrics/z_rms_final") == pytest.approx(r["z_rms_final"])
        assert _last(mux, run, "verdict/diverged") == 0.0 and "metrics/Ts" not in tags


def test_a_member_session_given_its_scenario_has_the_columns_of_a_run(tmp_path):
    _, summary, mux = _run(tmp_path, steps=200, log_every=50)
    member = {"batch": 1, "estimates": summary["estimates"], "truth": summary["truth"], "metrics": {},
              "intervals": summary["intervals"], "status": summary["status"]}
    values = monitor.final_values(member, scenario="sdof-stiffness")
    session = _tags(mux, "sdof-stiffness/verdict")
    assert {"final/dK [mN/m]", "final/dK |error| [mN/m]", "verdict/dK lower [mN/m]"} <= set(values) <= session
    for tag, value in values.items():
        assert value == pytest.approx(_last(mux, "sdof-stiffness/verdict", tag), rel=1e-6), tag
    assert values["final/dK [mN/m]"] == pytest.approx(_last(mux, "sdof-stiffness", "Estimates/dK [mN/m]"))


def test_a_large_sweep_makes_one_session_per_shard_and_says_why(tmp_path, monkeypatch):
    monkeypatch.setattr(sweeps, "HPARAMS_MEMBERS_MAX", 5)
    rows = sweeps.run_sweep(sweeps.Sweep.from_dict(SWEEP), out=tmp_path / "sw", progress=False)
    mux = _mux(tmp_path / "sw")
    assert sorted(r for r in mux.Runs() if "/" not in r) == ["shard_0000", "shard_0001"]
    sessions = _sessions(mux)
    assert sorted(sessions) == ["shard_0000/verdict", "shard_0001/verdict"]
    last = [r["status"] for r in rows if r["shard"] == 1]
    assert sessions["shard_0000/verdict"]["members"] == "0..3" and len(last) == 2
    passed = sum(all(v for k, v in r.items() if k.startswith("pass_")) for r in rows if r["shard"] == 1)
    assert sessions["shard_0001/verdict"][monitor.STATUS_HPARAM] == \
        ", ".join(f"{s} {last.count(s)}" for s in sorted(set(last)))
    assert sessions["shard_0001/verdict"][monitor.REQUIREMENTS_HPARAM] == f"pass {passed} of 2"
    assert sessions["shard_0000/verdict"]["Ts [s]"] == 0.01 and sessions["shard_0000/verdict"]["nu"] == 10
    assert sessions["shard_0000/verdict"]["dK [N/m]"] == "[0.3, 0.3, 0.5, 0.5]"   # per member, short: as it is
    assert "metrics/z_rms_final" in _tags(mux, "shard_0000/verdict")
    note = mux.Tensors("shard_0000", "sweep/text_summary")[0].tensor_proto.string_val[0].decode()
    assert "6 members" in note and "sweep.csv" in note and "500 runs" in note
    # the shards of a sweep share one Custom Scalars category, named after the sweep
    assert _layout(mux, "shard_0001").category[0].title == "sw (shards): estimates"
    # each shard's manifest lists the session and the note the sweep wrote into it: --overwrite replaces them
    # (unlisted, they made the same sweep refuse to run again: "holds results that no rcotorch manifest lists")
    again = sweeps.run_sweep(sweeps.Sweep.from_dict(SWEEP), out=tmp_path / "sw", progress=False, overwrite=True)
    assert [r["est_dK"] for r in again] == [r["est_dK"] for r in rows]
    assert sorted(_sessions(_mux(tmp_path / "sw"))) == ["shard_0000/verdict", "shard_0001/verdict"]


def test_sweep_figures_are_written_as_png_and_tensorboard_images(tmp_path):
    rows = [{"member": m, "dK": dK, "p0": p0, "est_dK": dK + 0.01 * m, "truth_dK": dK, "err_dK": 0.01 * m,
             "status": "converged" if m % 2 else "not_converged"}
            for m, (dK, p0) in enumerate([(0.3, 1e1), (0.5, 1e3), (0.7, 1e5), (0.3, 1e5)])]
    written = monitor.write_sweep_figures(tmp_path, rows, ["dK", "p0"], "sdof-stiffness")
    assert sorted(p.name for p in written) == ["sweep_dK.png", "sweep_p0.png"]
    assert all(p.read_bytes().startswith(b"\x89PNG\r\n\x1a\n") for p in written)
    mux = _mux(tmp_path)
    assert _tags(mux, ".", "images") == {"figures/sweep_dK", "figures/sweep_p0"}


# --- what TensorBoard serves ---------------------------------------------------------------------------------
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
def test_tensorboard_serves_the_runs_their_siblings_and_every_member_in_hparams(tmp_path):
    """A real TensorBoard on 127.0.0.1 (its default loader) over a mixed folder: a single run, a batch run and a
    sweep of 6 members. Its run list holds each run followed by its sibling runs in the order of their roles;
    its HParams table holds the two runs and the six members, with the settings of both scenarios (the union)
    and the estimates, truths and errors as metrics; the scalars of a run read simulated seconds as their time
    since the first."""
    _run(tmp_path, steps=200, log_every=50)
    _run(tmp_path, "sdof-dynamic-impedance", steps=200, batch=2, log_every=50)
    sweeps.run_sweep(sweeps.Sweep.from_dict(SWEEP), out=tmp_path / "runs" / "sweep", progress=False)
    port = _free_port()
    server = subprocess.Popen([sys.executable, "-m", "tensorboard.main", "--logdir", str(tmp_path / "runs"),
                               "--host", "127.0.0.1", "--port", str(port)],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        base = f"http://127.0.0.1:{port}"
        expected = sorted(["sdof-stiffness/verdict", "sdof-dynamic-impedance/verdict"] +
                          [f"sweep/members/member_{m:06d}" for m in range(6)])
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
        roles = ("", "/lower", "/truth", "/upper")
        every = [f"sweep/members/member_{m:06d}" for m in range(6)]
        for run in ("sdof-stiffness", "sdof-dynamic-impedance", "sweep/shard_0000", "sweep/shard_0001"):
            own = [r for r in runs if r == run or r.startswith(run + "/")]
            listed = [run + role for role in roles] + ([f"{run}/verdict"] if "shard" not in run else [])
            assert own == listed                                 # each role at its place: its colour
            every += listed
        assert sorted(runs) == sorted(every)
        experiment = _post(f"{base}/data/plugin/hparams/experiment", {"experimentName": ""})
        hparams = [h["name"] for h in experiment["hparamInfos"]]
        assert {"scenario", "p0", "dK [N/m]", "gain [N/m]", "seed"} <= set(hparams), ", ".join(hparams)
        assert hparams[:2] == [monitor.REQUIREMENTS_HPARAM, monitor.STATUS_HPARAM]   # shown without ticking
        metrics = {(m["name"]["group"], m["name"]["tag"]) for m in experiment["metricInfos"]}
        assert {("", "final/dK [mN/m]"), ("", "verdict/dK truth [mN/m]"), ("", "final/dK |error| [mN/m]"),
                ("", "final/dc_gain [N s/m]"), ("", "metrics/freq_rel_err_max")} <= metrics
        values = {s["name"]: {(m["name"]["group"], m["name"]["tag"]) for m in s["metricValues"]}
                  for g in groups["sessionGroups"] for s in g["sessions"]}
        assert all(("", "final/dK [mN/m]") in values[s] for s in expected if "impedance" not in s)
        query = urllib.parse.urlencode({"run": "sdof-stiffness", "tag": "Estimates/dK [mN/m]"})
        with urllib.request.urlopen(f"{base}/data/plugin/scalars/scalars?{query}", timeout=5) as r:
            points = json.loads(r.read())                            # [wall time, step, value]
        assert [p[1] for p in points] == _log_steps(50, 200)
        assert [p[0] - points[0][0] for p in points] == pytest.approx([k * 0.01 for k in _log_steps(50, 200)],
                                                                      abs=1e-5)
    finally:
        server.terminate()
        server.wait(timeout=30)


def test_a_log_writes_one_event_per_writer(tmp_path, monkeypatch):
    """A log is one event in the run and one in each sibling run, whatever the number of tags."""
    run = Run("sdof-stiffness", steps=100, batch=4, out=tmp_path / "r", log_every=50)
    run.advance(until=50, progress=False)
    calls = []
    monkeypatch.setattr(monitor.EventFile, "scalars", lambda self, step, wall, values: calls.append(self))
    est = {k: v.detach().to(torch.float64).cpu() for k, v in run.scenario.estimates(run.graph, run.settings).items()}
    run.monitor.log(60, torch.ones(4, dtype=torch.float64), est)
    assert len(calls) == 4 and len(set(map(id, calls))) == 4          # the run, truth, q10, q90
    run.close()


def test_a_member_whose_values_lie_beyond_the_histograms_bins_is_counted_not_a_crash(tmp_path):
    """One member's z finite but enormous (2.9e136, beyond TensorBoard's outermost bin edge of 1e20) made every
    value of a histogram fall outside its bins and TensorBoard's writer raise 'The histogram is empty'."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    run = Run("sdof-stiffness", batch=16, steps=200, out=tmp_path / "run")
    run.advance(progress=False)
    values = np.full(16, 1e-3)
    values[3] = 2.9e136
    run.monitor._histograms(200, {"z rms": values, "dK": np.full(16, 3e30)})
    run.monitor.close(run.summary())
    run.close()
    acc = EventAccumulator(str(tmp_path / "run"), size_guidance={"histograms": 0}).Reload()
    tags = [t for t in acc.Tags()["histograms"] if t.startswith("spread/z rms") or t.startswith("spread/dK")]
    assert len(tags) == 2
    for tag in tags:
        assert acc.Histograms(tag)[-1].histogram_value.num == 16
