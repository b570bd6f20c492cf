"""How a sweep or a tuning is driven, one record (``RunControl``): its checks hold on every path, ``run_sweep`` and
``run_tune`` take it or their keywords (not both), and a tuning hands its sweeps copies, never changing the
caller's."""

import dataclasses

import pytest

from rcotorch.errors import ConfigError
from rcotorch.run import tune as tune_module
from rcotorch.run.control import RunControl
from rcotorch.run.sweep import Sweep, run_sweep
from rcotorch.run.tune import Tuning, run_tune

SPEC = {"scenario": "sdof-stiffness", "steps": 200, "grid": {"dK": [-0.2, 0.2]}, "seeds": 1}


def test_overwrite_and_resume_together_are_refused_by_the_record_itself():
    with pytest.raises(ConfigError, match="choose one of --overwrite and --resume"):
        RunControl(overwrite=True, resume=True)
    with pytest.raises(ConfigError, match="choose one of --overwrite and --resume"):
        dataclasses.replace(RunControl(resume=True), overwrite=True)
    with pytest.raises(ConfigError, match="stop must be a function"):
        RunControl(stop=True)
    assert [RunControl().mode, RunControl(overwrite=True).mode, RunControl(resume=True).mode] == \
        ["new", "overwrite", "resume"]


@pytest.mark.parametrize("run", ["sweep", "tune"])
def test_the_keywords_and_the_record_are_checked_before_the_folder_is_touched(run, tmp_path):
    go = (lambda **kw: run_sweep(Sweep.from_dict(SPEC), out=tmp_path / "out", **kw)) if run == "sweep" else \
        (lambda **kw: run_tune(Tuning(scenario="sdof-stiffness", method="grid", space={"p0": [1e3]}, seeds=1,
                                      steps=200), out=tmp_path / "out", **kw))
    with pytest.raises(ConfigError, match="choose one of --overwrite and --resume"):
        go(overwrite=True, resume=True, progress=False)
    with pytest.raises(ConfigError, match="give progress, stop in control= or as keywords, not both"):
        go(control=RunControl(), progress=False, stop=lambda: False)
    assert not (tmp_path / "out").exists()


def test_a_sweep_runs_with_the_record_as_with_the_keywords(tmp_path):
    by_keywords = run_sweep(Sweep.from_dict(SPEC), out=tmp_path / "a", progress=False)
    by_record = run_sweep(Sweep.from_dict(SPEC), out=tmp_path / "b", control=RunControl(progress=False))
    assert [r["est_dK"] for r in by_keywords] == [r["est_dK"] for r in by_record]
    again = run_sweep(Sweep.from_dict(SPEC), out=tmp_path / "b", control=RunControl(progress=False,
                                                                                     overwrite=True))
    assert [r["est_dK"] for r in again] == [r["est_dK"] for r in by_record]


def test_a_tuning_hands_its_sweep_a_copy_of_its_record(tmp_path, monkeypatch):
    seen = []
    real = tune_module.run_sweep

    def spy(*args, control, **kwargs):
        seen.append(control)
        return real(*args, control=control, **kwargs)
    monkeypatch.setattr(tune_module, "run_sweep", spy)
    stop = lambda: False                                         # noqa: E731
    control = RunControl(progress=False, stop=stop)
    t = Tuning(scenario="sdof-stiffness", method="grid", space={"p0": [1e3]}, seeds=1, steps=200)
    run_tune(t, out=tmp_path / "t", control=control)
    resumed = RunControl(progress=False, resume=True)
    run_tune(t, out=tmp_path / "t", control=resumed)
    (first,), second = seen[:1], seen[1]
    assert first == RunControl(progress=False, stop=stop) and first.folder is None
    assert second.resume and second is not resumed                # the tuning's sweep is there: resumed
    assert control == RunControl(progress=False, stop=stop) and resumed.resume   # the callers' as they were
