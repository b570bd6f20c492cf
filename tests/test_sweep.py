"""Parameter sweeps: members equal their separate runs, Ray equals local, bad configs fail before work."""

import csv
import json
import sys

import numpy as np
import pytest

from rcotorch import ConfigError
from rcotorch.cli import main
from rcotorch.runner import Run
from rcotorch.sweep import Sweep, run_sweep

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
