"""Parameter sweeps: members equal their separate runs, Ray equals local, bad configs fail before work."""

import csv
import json
import sys

import numpy as np
import pytest

from rcotorch import ConfigError
from rcotorch.run.cli import main
from rcotorch.run.runner import Run
from rcotorch.run.sweep import Sweep, local_workers, run_sweep

SPEC = dict(scenario="sdof-stiffness-damping", steps=400, seeds=[5, 9], shard_size=3,
            grid={"dK": [-0.4, 0.3], "Ts": [0.01, 0.02]}, random={"dC": {"uniform": [0.0, 1.0]}}, samples=1,
            fixed={"nu": 10})


def test_members_grid_random_and_seeds():
    sweep = Sweep.from_dict(SPEC)
    members = sweep.members()
    assert len(members) == 2 * 2 * 1 * 2
    assert [m["seed"] for m in members[:2]] == [5, 9]
    assert {m["dK"] for m in members} == {-0.4, 0.3} and {m["Ts"] for m in members} == {0.01, 0.02}
    dC = {m["dC"] for m in members}
    assert len(dC) == 1 and 0.0 <= dC.pop() <= 1.0          # one random draw, shared by the grid points
    shards = sweep.shards()
    # Ts fixes the structure: two groups of 4 members, each cut into shards of at most 3
    assert [len(s["members"]) for s in shards] == [3, 1, 3, 1]
    assert all(s["common"]["Ts"] in (0.01, 0.02) and s["common"]["nu"] == 10 for s in shards)


def test_sweep_members_equal_separate_runs(tmp_path):
    rows = run_sweep(Sweep.from_dict(SPEC), out=tmp_path, progress=False)
    assert [r["member"] for r in rows] == list(range(8))
    members = Sweep.from_dict(SPEC).members()
    for r, m in zip(rows, members):
        single = Run("sdof-stiffness-damping", steps=400, seed=m["seed"], out=tmp_path / f"single{r['member']}",
                     overrides=dict({k: v for k, v in m.items() if k != "seed"}, nu=10))
        single.advance(progress=False)
        est = single.summary()["estimates"]
        np.testing.assert_allclose([r["est_dK"], r["est_dC"]], [est["dK"], est["dC"]], rtol=1e-8, atol=1e-12)
        assert r["truth_dK"] == m["dK"] and r["err_dK"] == pytest.approx(r["est_dK"] - m["dK"])
        assert r["diverged"] is False and r["diverged_at"] is None and r["reason"] is None
        assert r["status"] == single.summary()["health"]["status"]
    table = list(csv.DictReader(open(tmp_path / "sweep.csv")))
    assert len(table) == 8 and {"member", "dK", "Ts", "dC", "seed", "est_dK", "err_dC", "diverged"} <= set(table[0])
    assert json.loads((tmp_path / "sweep.json").read_text()) == rows
    assert (tmp_path / "shard_0000").is_dir() and (tmp_path / "members" / "member_000007").is_dir()


def test_shards_in_worker_processes_equal_shards_run_here(tmp_path, capsys):
    """The local backend's forked workers give the same table, bit for bit, as the shards run one after another
    in this process, and what each shard printed reaches this process's output."""
    here = run_sweep(Sweep.from_dict(SPEC), out=tmp_path / "here", progress=False, workers=1)
    apart = run_sweep(Sweep.from_dict(SPEC), out=tmp_path / "apart", progress=True, workers=2)
    assert apart == here and len({r["shard"] for r in apart}) == 4
    assert (tmp_path / "apart" / "sweep.csv").read_text() == (tmp_path / "here" / "sweep.csv").read_text()
    out = capsys.readouterr().out
    assert all(f"shard {i}/4: done in" in out for i in (1, 2, 3, 4))


def test_the_workers_default_to_one_per_core_and_never_outnumber_the_shards(monkeypatch):
    monkeypatch.setattr("os.sched_getaffinity", lambda pid: {0, 1, 2, 3})
    assert local_workers(None, 10, "cpu") == 4 and local_workers(None, 3, "cpu") == 3
    assert local_workers(8, 5, "cpu") == 5 and local_workers(1, 5, "cpu") == 1
    assert local_workers(None, 10, "cuda") == 1 and local_workers(4, 10, "cuda:0") == 1


def test_worker_processes_load_nothing_a_shard_needs_again(tmp_path):
    """``preload`` imports what a shard's run imports as it steps and ends, so that a forked worker loads none
    of it again: in a fresh process, a shard run after it imports no module (without it, TensorBoard's records
    and validation, about 0.1 s in every worker)."""
    import subprocess
    script = f"""
import sys
from rcotorch.run.runner import preload
from rcotorch.run.sweep import Sweep, make_run, run_shard
sweep = Sweep.from_dict({dict(SPEC, shard_size=8)!r})
shard = sweep.shards()[0]
out = {str(tmp_path)!r} + "/" + sys.argv[1]
run = make_run(sweep.scenario, shard, 400, sweep.dtype, "cpu", out)
if sys.argv[1] == "preload":
    preload()
before = set(sys.modules)
run_shard(sweep.scenario, shard, 400, sweep.dtype, "cpu", out, run=run)
print(sorted(set(sys.modules) - before))
"""
    def loaded(how):
        done = subprocess.run([sys.executable, "-c", script, how], capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr
        return done.stdout.strip()
    assert loaded("preload") == "[]"
    assert "rcotorch.verdict.validation" in loaded("no")          # what the preload spares each worker


@pytest.mark.parametrize("fault", ["config", "internal", "killed"])
def test_a_shard_that_fails_in_its_worker_fails_the_sweep_with_its_error(fault, tmp_path, monkeypatch):
    """A shard's error comes back from its process as the same exception (an internal one with the traceback
    of where it was raised as a note); a process that dies without a word is named with its signal."""
    import os
    import signal

    import rcotorch.run.sweep as sweep_module
    real = sweep_module.run_shard

    def failing(scenario, shard, *args, **kwargs):
        if shard["index"] == 1:
            if fault == "config":
                raise ConfigError("shard 1: a setting it cannot take")
            if fault == "internal":
                raise ZeroDivisionError("inside shard 1")
            os.kill(os.getpid(), signal.SIGKILL)
        return real(scenario, shard, *args, **kwargs)
    monkeypatch.setattr(sweep_module, "run_shard", failing)
    expected = {"config": (ConfigError, "a setting it cannot take"), "internal": (ZeroDivisionError, "inside"),
                "killed": (RuntimeError, "its process was killed by signal 9 before it sent its result")}[fault]
    with pytest.raises(expected[0], match=expected[1]) as caught:
        run_sweep(Sweep.from_dict(SPEC), out=tmp_path / "sweep", progress=False, workers=2)
    if fault == "internal":
        assert any("in its process" in note and "failing" in note for note in caught.value.__notes__)
    assert (tmp_path / "sweep" / "shard_0000").is_dir()


def test_a_worker_that_dies_between_its_shards_fails_the_sweep_naming_the_shard_it_was_given(tmp_path, monkeypatch):
    """A worker runs shard after shard; one killed after its first shard, as it waits for the next (here by its
    own hand as it reads the job), leaves that next shard unfinished: the sweep fails naming it and the signal,
    as for a worker killed within a shard, and never waits for it."""
    import os
    import signal

    import rcotorch.run.sweep as sweep_module
    real, calls = sweep_module.read_frame, []
    parent = os.getpid()

    def dying(fd):
        if os.getpid() != parent:        # in a worker: its second job read kills it
            calls.append(fd)             # this list is the worker's own copy after the fork
            if len(calls) == 2:
                os.kill(os.getpid(), signal.SIGKILL)
        return real(fd)
    monkeypatch.setattr(sweep_module, "read_frame", dying)
    with pytest.raises(RuntimeError, match="its process was killed by signal 9 before it sent its result"):
        run_sweep(Sweep.from_dict(SPEC), out=tmp_path / "sweep", progress=False, workers=2)


def test_a_stop_before_a_shard_has_started_in_a_worker_stops_the_sweep(tmp_path):
    """A stop request that comes before any worker runs a shard (or once the running ones ended without being
    stopped) leaves shards unstarted: the sweep is interrupted, never finished with part of its members."""
    from rcotorch.run.runner import Interrupted
    with pytest.raises(Interrupted):
        run_sweep(Sweep.from_dict(SPEC), out=tmp_path / "sweep", progress=False, workers=2, stop=lambda: True)
    assert not (tmp_path / "sweep" / "sweep.csv").exists() and not (tmp_path / "sweep" / "shard_0000").exists()


def test_workers_must_be_a_positive_integer(tmp_path, capsys):
    with pytest.raises(ConfigError, match="workers must be a positive integer"):
        run_sweep(Sweep.from_dict(SPEC), out=tmp_path / "s", progress=False, workers=0)
    cfg = tmp_path / "sweep.toml"
    cfg.write_text('scenario = "sdof-stiffness"\nsteps = 20\n')
    assert main(["sweep", str(cfg), "--out", str(tmp_path / "cli"), "--workers", "0"]) == 2
    assert "--workers must be a positive integer, got 0" in capsys.readouterr().err
    assert not (tmp_path / "cli").exists()


def test_ray_backend_equals_local(tmp_path):
    ray = pytest.importorskip("ray")
    spec = dict(SPEC, steps=200)
    local = run_sweep(Sweep.from_dict(spec), out=tmp_path / "local", progress=False)
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        remote = run_sweep(Sweep.from_dict(spec), backend="ray", out=tmp_path / "ray", progress=False)
    finally:
        ray.shutdown()
    # bitwise: the same shards, each one batched run on CPU float64; the confidence intervals come from LAPACK
    # solves whose last bits may follow the worker's thread count, so they agree to rounding
    def split(rows):
        exact = [{k: v for k, v in r.items() if not k.startswith(("lower_", "upper_"))} for r in rows]
        return exact, [[v for k, v in r.items() if k.startswith(("lower_", "upper_"))] for r in rows]
    (r_exact, r_iv), (l_exact, l_iv) = split(remote), split(local)
    assert r_exact == l_exact
    assert np.allclose(np.array(r_iv, dtype=float), np.array(l_iv, dtype=float), rtol=1e-9, equal_nan=True)
    assert (tmp_path / "ray" / "shard_0003").is_dir()


def test_missing_ray_says_how_to_install(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)
    with pytest.raises(ConfigError, match=r"pip install 'rcotorch\[ray\]'"):
        run_sweep(Sweep.from_dict(dict(SPEC, steps=5)), backend="ray", out=tmp_path, progress=False)


@pytest.mark.parametrize("change, message", [
    (dict(grid={"dKK": [0.1]}), "no setting 'dKK' .*did you mean 'dK'"),
    (dict(grid={"dK": []}), "'dK' needs a non-empty list"),
    (dict(grid={"dK": 0.3}), "'dK' needs a non-empty list"),
    (dict(grid={"dK": ["abc"]}), "setting dK must be a number"),
    (dict(grid={"nc": [1.5]}), "setting nc must be an integer"),
    (dict(random={"dC": {"gauss": [0, 1]}}, samples=2), "needs one of"),
    (dict(random={"dC": {"uniform": [1.0, 0.0]}}, samples=2), "low <= high"),
    (dict(random={"dC": {"uniform": [0.0, 1.0]}}, samples=0), "samples >= 1"),
    (dict(seeds=0), "seeds must be at least 1"),
    (dict(steps=0), "steps must be positive"),
    (dict(grid={"seed": [1, 2]}), "set seeds with 'seeds'"),
    (dict(grid={"dK": [0.1]}, fixed={"dK": 0.2}), "more than one of"),
    (dict(grid={"lam": [0.99, 2.0]}), "lam must lie in \\(0, 1\\]"),
])
def test_bad_configs_fail_before_any_work(change, message, tmp_path):
    spec = {"scenario": "sdof-stiffness", "steps": 50, **change}
    with pytest.raises(ConfigError, match=message):
        run_sweep(Sweep.from_dict(spec), out=tmp_path / "out", progress=False)
    assert not (tmp_path / "out").exists()


def test_config_files(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text('scenario = "sdof-stiffness"\nstep = 10\n')
    with pytest.raises(ConfigError, match="unknown key.*'step'"):
        Sweep.from_file(bad)
    broken = tmp_path / "broken.toml"
    broken.write_text("scenario = \n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        Sweep.from_file(broken)
    good = tmp_path / "sweep.toml"
    good.write_text('scenario = "sdof-stiffness"\nsteps = 100\nseeds = 2\n[grid]\ndK = [0.1, 0.5]\n')
    assert main(["sweep", str(good), "--out", str(tmp_path / "out")]) == 0
    assert "4 members" in capsys.readouterr().out
    assert len(list(csv.DictReader(open(tmp_path / "out" / "sweep.csv")))) == 4
    assert main(["sweep", str(tmp_path / "none.toml")]) == 2


@pytest.mark.parametrize("text, message", [
    ('steps = "200"', "steps must be an integer, got '200'"),
    ("seeds = 2.5", "seeds must be an integer count or a list of integers, got 2.5"),
    ("[grid]\ndK = [0.1, nan]", "setting dK must be a finite number"),
    ("[fixed]\np0 = inf", "setting p0 must be a finite number"),
])
def test_sweep_values_of_the_wrong_type_exit_2_naming_the_setting(text, message, tmp_path, capsys):
    cfg = tmp_path / "sweep.toml"
    cfg.write_text(f'scenario = "sdof-stiffness"\n{text}\n')
    assert main(["sweep", str(cfg), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1 and "Traceback" not in err
    assert not (tmp_path / "out").exists()


def test_a_sweep_never_deletes_what_it_did_not_write_and_never_merges_old_shards(tmp_path, capsys):
    out = tmp_path / "out"
    cfg = tmp_path / "sweep.toml"
    cfg.write_text('scenario = "sdof-stiffness"\nsteps = 60\nseeds = 2\nshard_size = 1\n')
    assert main(["sweep", str(cfg), "--out", str(out)]) == 0
    assert sorted(p.name for p in out.glob("shard_*")) == ["shard_0000", "shard_0001"]
    (out / "notes.txt").write_text("mine")
    (out / "shard_0001" / "mine.txt").write_text("mine too")
    before = sorted(str(p) for p in out.rglob("*"))
    capsys.readouterr()
    # Another run in the folder: refused, nothing touched.
    cfg.write_text('scenario = "sdof-stiffness"\nsteps = 60\nseeds = 1\n')
    assert main(["sweep", str(cfg), "--out", str(out)]) == 2
    assert "already holds a sweep" in capsys.readouterr().err
    assert sorted(str(p) for p in out.rglob("*")) == before
    # --overwrite: the old sweep's shards go (no merging), the user's files stay.
    assert main(["sweep", str(cfg), "--out", str(out), "--overwrite"]) == 0
    assert (out / "notes.txt").read_text() == "mine"
    assert (out / "shard_0001" / "mine.txt").read_text() == "mine too"
    assert not (out / "shard_0001" / "summary.json").exists()
    rows = list(csv.DictReader(open(out / "sweep.csv")))
    assert len(rows) == 1 and rows[0]["status"] in ("converged", "undetermined", "not_converged")
    assert sorted(p.name for p in (out / "members").iterdir()) == ["member_000000"]


class _Deterministic:
    """A scenario without a seed setting (recorded data: nothing random), whose default steps follow a setting."""

    @staticmethod
    def make():
        import numpy as np

        import rcotorch as rt
        from rcotorch.run.scenario import Scenario

        class Replay(Scenario):
            name = "replay-gain"
            steps = 999
            settings = dict(rows=300, p0=1e3)
            per_member = frozenset({"p0"})
            estimator_options = ()

            def default_steps(self, s):
                return int(s["rows"])

            def build(self, s, batch, dtype, device):
                t = np.arange(400) * 0.01
                w = np.sin(3 * t) + 0.5 * np.sin(11 * t)
                known = rt.LTI.continuous([[-1.0]], [[1.0, 1.0]], [[1.0], [1.0]], [[0, 0], [0, 0]],
                                          inputs=["w", "u"], outputs={"y": 1, "y0": 1}, dt=0.01, name="known")
                a = np.exp(-1.5 * 0.01)                         # the true system: pole at -1.5, ZOH
                y = np.zeros_like(w)
                for k in range(len(w) - 1):
                    y[k + 1] = a * y[k] + (1 - a) / 1.5 * w[k]
                data = rt.Recorded(np.c_[w, y][: int(s["rows"])], {"w": 0, "y": 1}, name="data")
                ident = rt.RCOEstimator.static_gain({"y0": 1}, p0=s["p0"])
                return rt.refinement(known, ident, data=data, nu=20, batch_size=batch, dtype=dtype, device=device)

            def estimates(self, g, s):
                return {"dk": -g.role("estimator").theta[:, 0, 0]}

        return Replay()


def test_a_scenario_without_seeds_sweeps_without_them(tmp_path):
    sc = _Deterministic.make()
    with pytest.raises(ConfigError, match="no setting 'seed'.*set seeds = 1"):
        Sweep(scenario=sc, grid={"p0": [1e2, 1e4]}, seeds=2).members()
    sweep = Sweep(scenario=sc, grid={"p0": [1e2, 1e4]}, seeds=1, fixed={"rows": 250})
    assert sweep.members() == [{"p0": 1e2}, {"p0": 1e4}]
    rows = run_sweep(sweep, out=tmp_path, progress=False)
    assert [r["p0"] for r in rows] == [1e2, 1e4] and all("seed" not in r or r["seed"] is None for r in rows)
    summary = json.loads((tmp_path / "shard_0000" / "summary.json").read_text())
    assert summary["steps"] == 250                        # the scenario's default for rows = 250, not its 999
    run = Run(sc, out=tmp_path / "one")
    assert run.steps == 300
