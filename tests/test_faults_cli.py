"""Bad values on the command line and in configs, and faults met during a run, end with exit 2 and one line on
stderr that names the option, setting or file at fault (and, where a run can go on, it does).

Each test runs the command in this process (``rcotorch.run.cli.main``); a run that has to step is a short one.
"""

import json
import shutil
import time
from pathlib import Path

import pytest
from conftest import at_step

import rcotorch.run.limits
import rcotorch.run.runner
from rcotorch.errors import ConfigError, OutputError
from rcotorch.run.cli import main
from rcotorch.run.outputs import OutputFolder, load_checkpoint
from rcotorch.run.runner import MAX_STEPS, Run

QUICK = ["--steps", "300", "--quiet", "--no-figures"]
HUGE = str(10 ** 30)


def _one_line(err: str) -> str:
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return err


def _refused(capsys, args: list[str], out: Path | None = None) -> str:
    """Run ``args``; assert exit 2 within a few seconds, one line on stderr and no results; return the line."""
    start = time.monotonic()
    assert main(args) == 2
    err = _one_line(capsys.readouterr().err)
    assert time.monotonic() - start < 30, "refused only after it started to work"
    assert out is None or not (out / "summary.json").exists()
    return err


@pytest.fixture
def finished_run(tmp_path, capsys) -> Path:
    out = tmp_path / "done"
    assert main(["run", "sdof-stiffness", "--out", str(out), *QUICK]) in (0, 1)
    capsys.readouterr()
    return out


# --- --batch ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("batch", ["0", "-2"])
def test_a_batch_of_zero_or_below_exits_2_naming_batch_and_the_value(batch, tmp_path, capsys):
    out = tmp_path / "run"
    err = _refused(capsys, ["run", "sdof-stiffness", "--batch", batch, "--out", str(out), *QUICK], out)
    assert f"--batch must be a positive integer, got {batch}" in err


# --- --steps ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("steps", [HUGE, str(2 ** 63), str(MAX_STEPS + 1)])
def test_steps_beyond_the_bound_exit_2_at_once_naming_steps_and_why(steps, tmp_path, capsys):
    out = tmp_path / "run"
    err = _refused(capsys, ["run", "sdof-stiffness", "--out", str(out), "--quiet", "--no-figures", "--steps", steps],
                   out)
    assert f"--steps {steps}: a run takes at most {MAX_STEPS} steps" in err and "hours" in err
    assert not out.exists()


@pytest.mark.parametrize("steps", ["0", "-5"])
def test_zero_or_negative_steps_exit_2_naming_steps(steps, tmp_path, capsys):
    out = tmp_path / "run"
    err = _refused(capsys, ["run", "sdof-stiffness", "--out", str(out), "--quiet", "--steps", steps], out)
    assert f"--steps must be a positive integer, got {steps}" in err


def test_a_resume_asked_to_run_to_a_huge_number_of_steps_exits_2_and_leaves_the_checkpoint(finished_run, capsys):
    checkpoint = finished_run / "checkpoint.pt"
    before = checkpoint.read_bytes()
    err = _refused(capsys, ["run", "--resume", str(finished_run), "--steps", HUGE, "--quiet", "--no-figures"])
    assert f"--steps {HUGE}: a run takes at most {MAX_STEPS} steps" in err
    assert checkpoint.read_bytes() == before


def test_a_run_or_sweep_made_from_python_refuses_steps_beyond_the_bound_too(tmp_path):
    with pytest.raises(ConfigError, match=f"steps must be at most {MAX_STEPS}"):
        Run("sdof-stiffness", steps=MAX_STEPS + 1, out=tmp_path / "run")
    cfg = tmp_path / "sweep.toml"
    cfg.write_text(f'scenario = "sdof-stiffness"\nsteps = {10 ** 15}\n')
    assert main(["sweep", str(cfg), "--out", str(tmp_path / "sweep")]) == 2
    assert not (tmp_path / "sweep").exists()


# --- --seed -------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", [str(2 ** 70), str(2 ** 32), "-1"])
def test_a_seed_outside_the_range_of_the_random_streams_exits_2_naming_seed_and_the_range(seed, tmp_path, capsys):
    out = tmp_path / "run"
    err = _refused(capsys, ["run", "sdof-stiffness", "--seed", seed, "--out", str(out), *QUICK], out)
    assert f"--seed {seed}: a seed must be an integer in 0..4294967295" in err
    err = _refused(capsys, ["run", "sdof-stiffness", "--set", f"seed={seed}", "--out", str(out), *QUICK], out)
    assert f"--set seed={seed}:" in err and "0..4294967295" in err


def test_the_largest_seed_runs(tmp_path, capsys):
    assert main(["run", "sdof-stiffness", "--seed", str(2 ** 32 - 1), "--out", str(tmp_path / "run"),
                 *QUICK]) in (0, 1)


# --- tune configs -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("text, message", [
    ('steps = "200"', "steps must be an integer, got '200'"),
    ("seeds = 2.5", "seeds must be an integer count or a list of integers, got 2.5"),
    ('samples = "8"', "samples must be an integer, got '8'"),
    ('rounds = "4"', "rounds must be an integer, got '4'"),
    ('shard_size = 1.5', "shard_size must be an integer, got 1.5"),
    ("method = 3", "method must be one of"),
    ('dtype = "float16"', "dtype must be 'float64' or 'float32', got 'float16'"),
    ('seed = "1"', "seed must be an integer, got '1'"),
    ('fixed = 3', "fixed must be a table of settings, got 3"),
])
def test_a_tune_config_value_of_the_wrong_type_exits_2_naming_the_file_and_key(text, message, tmp_path, capsys):
    cfg = tmp_path / "tune.toml"
    cfg.write_text(f'scenario = "sdof-stiffness"\n{text}\n[space]\np0 = [1.0, 10.0]\n')
    out = tmp_path / "tune"
    err = _refused(capsys, ["tune", str(cfg), "--out", str(out)])
    assert f"{cfg}: {message}" in err
    assert not out.exists()


# --- a sweep resumed over a damaged shard -------------------------------------------------------------------
@pytest.mark.parametrize("checkpoint", ["kept", "deleted"])
def test_a_sweep_resumed_over_a_shard_whose_summary_is_truncated_runs_that_shard_again(checkpoint, tmp_path,
                                                                                        capsys):
    cfg = tmp_path / "sweep.toml"
    cfg.write_text('scenario = "sdof-stiffness"\nsteps = 60\nseeds = 2\nshard_size = 1\n')
    out = tmp_path / "sweep"
    assert main(["sweep", str(cfg), "--out", str(out)]) == 0
    rows = json.loads((out / "sweep.json").read_text())
    summary = out / "shard_0001" / "summary.json"
    text = summary.read_text()
    summary.write_text(text[:len(text) // 2])
    if checkpoint == "deleted":
        (out / "shard_0001" / "checkpoint.pt").unlink()
    capsys.readouterr()
    assert main(["sweep", str(cfg), "--out", str(out), "--resume"]) == 0
    err = capsys.readouterr().err
    assert f"{summary}: not a complete summary" in err and "runs the shard again" in err
    assert json.loads(summary.read_text())["steps"] == 60

    def estimates(rows):
        return [{k: v for k, v in r.items() if k.startswith("est_")} for r in rows]
    assert estimates(json.loads((out / "sweep.json").read_text())) == estimates(rows)


# --- an output folder replaced during a run -----------------------------------------------------------------
def test_an_output_folder_moved_away_and_replaced_by_an_empty_one_is_reported_replaced(tmp_path, monkeypatch,
                                                                                        capsys):
    out, moved = tmp_path / "run", tmp_path / "moved"

    def replace(folder):
        folder.rename(moved)
        folder.mkdir()
    at_step(monkeypatch, 100, replace)
    assert main(["run", "sdof-stiffness", "--out", str(out), *QUICK, "--checkpoint-every", "50"]) == 2
    err = _one_line(capsys.readouterr().err)
    assert f"the output folder {out} was replaced by another folder while rcotorch was writing to it" in err
    assert f"the original is now {moved}" in err and "move the original back and resume" in err
    assert "deleted" not in err and "lost" not in err
    assert load_checkpoint(moved / "checkpoint.pt")["graph"]["k"] == 50
    assert not any(p.name in ("summary.json", "checkpoint.pt") for p in out.iterdir())


def test_a_folder_check_tells_a_moved_folder_from_a_deleted_one(tmp_path):
    path, moved = tmp_path / "run", tmp_path / "moved"
    folder = OutputFolder(path, "run")
    folder.open("new", info={"scenario": "x"})
    path.rename(moved)
    with pytest.raises(OutputError, match=f"{path} was moved away .*it is now {moved}.*move it back and resume"):
        folder.check()
    path.mkdir()
    (path / "events.out.tfevents.1.host").write_bytes(b"")        # TensorBoard's writer, which writes by path
    with pytest.raises(OutputError, match=f"{path} was replaced by another folder.*the original is now {moved}"):
        folder.check()
    shutil.rmtree(path)
    moved.rename(path)                                               # moved back: the run may go on
    folder.check()
    folder.close()


# --- memory -------------------------------------------------------------------------------------------------
GIB = 2 ** 30


def test_a_run_that_needs_more_memory_than_is_available_is_refused_before_it_starts(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(rcotorch.run.limits, "available_memory", lambda: (2 * GIB, "MemAvailable in /proc/meminfo"))
    built = []
    monkeypatch.setattr(type(rcotorch.run.scenario.get("sdof-stiffness")), "build",
                        lambda *a: built.append(a) or pytest.fail("built"))
    out = tmp_path / "run"
    err = _refused(capsys, ["run", "sdof-stiffness", "--set", "nu=5000000", "--out", str(out), *QUICK], out)
    assert err.startswith("rcotorch: error: --set nu=5000000: scenario 'sdof-stiffness' with nu = 5000000 and "
                          "batch 1 needs at least")
    assert "GB of memory" in err and "but 2.1 GB is available (MemAvailable in /proc/meminfo)" in err
    err = _refused(capsys, ["run", "sdof-stiffness", "--batch", "100000000", "--out", str(out), *QUICK], out)
    assert err.startswith("rcotorch: error: --batch 100000000: scenario 'sdof-stiffness' with nu = 15 and batch "
                          "100000000 needs at least")
    assert not built and not out.exists()


def test_the_available_memory_is_the_least_of_meminfo_the_cgroup_and_the_address_space_limit(tmp_path):
    meminfo = tmp_path / "meminfo"
    meminfo.write_text("MemTotal:       24683784 kB\nMemAvailable:    8388608 kB\n")
    cgroup = tmp_path / "cgroup"
    cgroup.mkdir()
    (cgroup / "memory.max").write_text("max\n")
    assert rcotorch.run.limits.available_memory(meminfo, [cgroup], None) == (8 * GIB, f"MemAvailable in {meminfo}")
    (cgroup / "memory.max").write_text(f"{3 * GIB}\n")
    (cgroup / "memory.current").write_text(f"{GIB}\n")
    found = rcotorch.run.limits.available_memory(meminfo, [cgroup], None)
    assert found == (2 * GIB, f"the limit {cgroup / 'memory.max'} less what the cgroup uses")
    assert rcotorch.run.limits.available_memory(meminfo, [cgroup], GIB // 2)[0] == GIB // 2
    assert rcotorch.run.limits.available_memory(tmp_path / "none", [], None) is None


@pytest.mark.parametrize("raised", [MemoryError(), RuntimeError("std::bad_alloc")])
def test_memory_that_runs_out_anyway_exits_2_naming_the_settings_that_drive_it(raised, tmp_path, monkeypatch,
                                                                               capsys):
    def advance(self, *a, **k):
        raise raised
    monkeypatch.setattr(rcotorch.run.runner.Run, "advance", advance)
    out = tmp_path / "run"
    assert main(["run", "sdof-stiffness", "--set", "nu=40", "--batch", "3", "--out", str(out), *QUICK]) == 2
    err = _one_line(capsys.readouterr().err)
    assert err.startswith("rcotorch: error: out of memory")
    assert "the run's memory grows with the batch and nu (here --batch 3, --set nu=40)" in err
    assert f"traceback in {out / 'rcotorch.log'}" in err


# --- scenario settings --------------------------------------------------------------------------------------
@pytest.mark.parametrize("setting, message", [
    ("m=0", "setting m must be positive, got 0"),
    ("noise=-1", "setting noise must be non-negative, got -1"),
    ("w_std=-0.5", "setting w_std must be non-negative, got -0.5"),
    ("Ts=0", "setting Ts must be positive, got 0"),
    ("nu=0", "setting nu must be positive, got 0"),
    ("nc=-1", "setting nc must be non-negative, got -1"),
    ("p0=-1e3", "setting p0 must be positive, got -1000"),
    ("lam=0", "setting lam must lie in (0, 1], got 0"),
])
def test_a_setting_outside_its_declared_range_exits_2_naming_the_setting(setting, message, tmp_path, capsys):
    out = tmp_path / "run"
    err = _refused(capsys, ["run", "sdof-stiffness", "--set", setting, "--out", str(out), *QUICK], out)
    assert err.startswith(f"rcotorch: error: --set {setting}: scenario 'sdof-stiffness': {message}")


def test_a_setting_out_of_range_in_a_sweep_names_the_member_and_the_setting(tmp_path, capsys):
    cfg = tmp_path / "sweep.toml"
    cfg.write_text('scenario = "sdof-stiffness"\n[grid]\nm = [1.0, 0.0]\n')
    err = _refused(capsys, ["sweep", str(cfg), "--out", str(tmp_path / "sweep")])
    assert "sweep member 1" in err and "setting m must be positive, got 0" in err


def test_every_shipped_default_lies_in_its_declared_range():
    from rcotorch.run import scenario as scenarios
    for sc in scenarios.available().values():
        assert sc.resolve(dict(sc.settings)) == dict(sc.settings)


SCENARIO_FILE = '''
import rcotorch as rt
from rcotorch.run.scenario import Scenario


class Fragile(Scenario):
    name = "fragile"
    settings = dict(x=1.0, y=2.0)
    estimator_options = ()

    def build(self, s, batch, dtype, device):
        if s["x"] > 2:
            raise ValueError("x over 2 makes the model unstable")
        raise rt.ConfigError("block 'known': the matrices do not fit")


SCENARIO = Fragile()
'''


def test_a_scenario_that_fails_to_build_from_the_settings_given_names_them(tmp_path, monkeypatch, capsys):
    (tmp_path / "fragile.py").write_text(SCENARIO_FILE)
    monkeypatch.setenv("RCOTORCH_SCENARIOS", str(tmp_path))
    out = tmp_path / "run"
    err = _refused(capsys, ["run", "fragile", "--set", "x=3", "--set", "y=2", "--out", str(out), *QUICK], out)
    assert err.startswith("rcotorch: error: --set x=3: scenario 'fragile': x over 2 makes the model unstable")
    err = _refused(capsys, ["run", "fragile", "--set", "x=1.5", "--out", str(out), *QUICK], out)
    assert err.startswith("rcotorch: error: --set x=1.5: scenario 'fragile': block 'known': the matrices do not fit")
    with pytest.raises(ConfigError, match=r"^scenario 'fragile' with x = 3: x over 2"):
        Run(rcotorch.run.scenario.get("fragile"), overrides={"x": 3}, out=out)
