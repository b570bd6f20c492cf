"""Tuning from held-out data (rcotorch.run.tune): ranking over seeds, the sensitivity table, best.toml, a search
that recovers a scenario's requirements from a deliberately poor start without looking at the truth, TPE rounds
of batched candidates (resumable), and the Ray backend."""

import math
import tomllib

import numpy as np
import pytest

from rcotorch.errors import ConfigError, OutputError
from rcotorch.run.tune import Tuning, best_toml, rank, run_tune, sensitivity_table


def _row(p0, nu, seed, score, diverged=False):
    return {"p0": p0, "nu": nu, "seed": seed, "validation_rmse": score, "diverged": diverged,
            "validation_fit_percent": 90.0, "validation_fit_percent_initial": 50.0}


def test_candidates_are_ranked_by_their_mean_held_out_score_and_a_diverged_seed_disqualifies():
    rows = [_row(1.0, 10, 0, 0.5), _row(1.0, 10, 1, 0.7),          # mean 0.6
            _row(1e3, 10, 0, 0.2), _row(1e3, 10, 1, 0.4),          # mean 0.3: best
            _row(1e6, 10, 0, 0.1), _row(1e6, 10, 1, math.nan, diverged=True)]
    ranked = rank(rows, ["p0", "nu"])
    assert [c["settings"]["p0"] for c in ranked] == [1e3, 1.0, 1e6]
    assert ranked[0]["score"] == pytest.approx(0.3) and ranked[0]["spread"] == pytest.approx(0.1)
    assert ranked[2]["score"] == math.inf and ranked[2]["diverged"] == 1 and ranked[0]["rank"] == 1
    table = sensitivity_table(ranked, ["p0"])
    assert {r["value"]: r["best"] for r in table} == {"1000": pytest.approx(0.3), "1": pytest.approx(0.6),
                                                      "1e+06": math.inf}
    text = best_toml("sdof-stiffness", {"p0": 1e3, "nu": 10, "method": "x"}, ranked[0])
    assert tomllib.loads(text) == {"scenario": "sdof-stiffness", "settings": {"p0": 1e3, "nu": 10, "method": "x"}}


def test_a_continuous_setting_is_binned_by_quantiles_in_the_sensitivity_table():
    cands = [{"settings": {"p0": float(10 ** i)}, "score": float(i)} for i in range(8)]
    table = sensitivity_table(cands, ["p0"])
    assert len(table) == 4 and sum(r["candidates"] for r in table) == 8
    assert [r["best"] for r in table] == sorted(r["best"] for r in table)


def test_a_tuning_config_is_checked():
    with pytest.raises(ConfigError, match="space"):
        Tuning.from_dict({"scenario": "sdof-stiffness"})
    with pytest.raises(ConfigError, match="method"):
        Tuning.from_dict({"scenario": "sdof-stiffness", "space": {"p0": [1]}, "method": "anneal"})
    with pytest.raises(ConfigError, match="grid.*list"):
        Tuning.from_dict({"scenario": "sdof-stiffness", "space": {"p0": {"uniform": [1, 2]}},
                          "method": "grid"}).sweep()
    from rcotorch.run import scenario as scenarios
    unvalidated = type("Unvalidated", (type(scenarios.get("sdof-stiffness")),),
                       {"name": "unvalidated", "validation_steps": 0})()     # no held-out data, none declared
    with pytest.raises(ConfigError, match="no held-out validation"):
        Tuning(scenario=unvalidated, space={"p0": [1.0]}).sweep()


def test_tune_recovers_the_requirements_from_a_poor_start_on_held_out_data_only(tmp_path):
    """sdof-stiffness from p0 = 1 (too small to move theta in 3000 steps): the search over p0 picks a value whose
    run meets the scenario's requirements on the truth, which the search never read."""
    from rcotorch.run.runner import Run
    t = Tuning(scenario="sdof-stiffness", method="grid", space={"p0": [1.0, 10.0, 1e3, 1e5]}, seeds=2,
               steps=3000, fixed={"dC": 0.0})
    result = run_tune(t, out=tmp_path / "tune", progress=False)
    assert result.members == 8 and len(result.candidates) == 4
    assert result.candidates[-1]["settings"]["p0"] == 1.0              # the poor start ranks last
    best = result.best
    assert best["p0"] >= 1e3
    for name in ("tune.csv", "best.toml", "sensitivity.csv"):
        assert (tmp_path / "tune" / name).stat().st_size > 0
    chosen = tomllib.loads((tmp_path / "tune" / "best.toml").read_text())["settings"]
    run = Run("sdof-stiffness", steps=3000, out=tmp_path / "check", overrides=chosen)
    run.advance(progress=False)
    summary = run.finish(figures=False)
    assert all(r["pass"] for r in summary["requirements"].values()), summary["requirements"]
    poor = Run("sdof-stiffness", steps=3000, out=tmp_path / "poor", overrides={"p0": 1.0, "dC": 0.0})
    poor.advance(progress=False)
    assert not all(r["pass"] for r in poor.finish(figures=False)["requirements"].values())


class _Room:
    """A problem of one's own, declared in a script: a room whose wall lost insulation (first-order thermal
    model, conductance 0.04 W/K known, 0.06 W/K true), its temperature measured with noise."""

    @staticmethod
    def scenario():
        import rcotorch as rt
        from rcotorch.run.scenario import Scenario

        class Room(Scenario):
            name = "my-room"
            steps = 3000
            settings = dict(p0=1e-4, lam=1.0, nu=60, seed=1)
            per_member = frozenset({"p0", "lam", "seed"})
            estimator_options = ()

            def build(self, s, batch, dtype, device):
                known = rt.LTI.continuous([[-0.04]], [[1.0, 1.0]], [[1.0], [1.0]], [[0, 0], [0, 0]],
                                          inputs=["w", "u"], outputs={"y": 1, "y0": 1}, dt=1.0, name="known")
                truth = rt.LTI.continuous([[-0.06]], [[1.0]], [[1.0]], [[0]], inputs=["w"], outputs=["y"], dt=1.0)
                ident = rt.RCOEstimator.static_gain({"y0": 1}, p0=s["p0"], lam=s["lam"])
                return rt.refinement(known, ident, physical=truth, excitation=rt.WhiteNoise(1, seed=s["seed"]),
                                     noise=rt.WhiteNoise(1, std=0.05, seed=np.add(s["seed"], 1000).tolist()),
                                     nu=s["nu"], batch_size=batch, dtype=dtype, device=device)

            def estimates(self, g, s):
                return {"g": 0.04 - g.role("estimator").theta[:, 0, 0]}
        return Room()


def test_a_scenario_declared_in_a_script_is_tuned_without_registering_it(tmp_path):
    room = _Room.scenario()
    t = Tuning(scenario=room, method="grid", space={"p0": [1e-4, 1e-2, 1.0]}, seeds=2)
    result = run_tune(t, out=tmp_path / "room", progress=False)
    assert result.best["p0"] >= 1e-2 and result.candidates[-1]["settings"]["p0"] == 1e-4
    assert tomllib.loads((tmp_path / "room" / "best.toml").read_text())["scenario"] == "my-room"


def test_a_p0_far_too_small_for_the_regressors_is_named_at_the_end_of_a_run(tmp_path):
    from rcotorch.run.runner import Run
    warned = []
    for p0 in (1e-3, 1e3):
        run = Run("sdof-stiffness", steps=2000, out=tmp_path / f"p0-{p0}", overrides={"p0": p0}, intervals=False,
                  validation=False)
        run.advance(progress=False)
        warned.append(run.finish(figures=False)["warnings"])
    assert len(warned[0]) == 1 and "p0 = 0.001 is small for the regressors of 2000 steps" in warned[0][0]
    assert warned[0][0].endswith("or a longer run (the data's weight grows with the steps)")
    suggested = float(warned[0][0].split("about ", 1)[1].split(",", 1)[0])
    assert 1e2 < suggested < 1e5 and warned[1] == []


def test_a_tuning_resumed_in_its_folder_reuses_the_finished_candidates(tmp_path):
    t = Tuning(scenario="sdof-stiffness", method="grid", space={"p0": [1.0, 1e3]}, seeds=1, steps=1500)
    first = run_tune(t, out=tmp_path / "t", progress=False)
    shard = next((tmp_path / "t" / "runs").glob("shard_*")) / "summary.json"
    stamp = shard.stat().st_mtime_ns
    again = run_tune(t, out=tmp_path / "t", progress=False, resume=True)
    assert shard.stat().st_mtime_ns == stamp                     # the finished shard was not run again
    assert [c["score"] for c in again.candidates] == [c["score"] for c in first.candidates]
    with pytest.raises(OutputError, match="already holds a tune"):     # nor is a tuning overwritten unasked
        run_tune(t, out=tmp_path / "t", progress=False)
    replaced = run_tune(t, out=tmp_path / "t", progress=False, overwrite=True)    # but when asked
    assert [c["score"] for c in replaced.candidates] == [c["score"] for c in first.candidates]


def test_a_tuning_with_a_bad_candidate_is_refused_before_its_folder_is_made(tmp_path):
    t = Tuning(scenario="sdof-stiffness", method="grid", space={"p0": [1e3, -1.0]}, seeds=1, steps=100)
    with pytest.raises(ConfigError, match="p0"):
        run_tune(t, out=tmp_path / "t", progress=False)
    assert not (tmp_path / "t").exists()


# --- tpe: rounds of batched candidates -------------------------------------------------------------------------
TPE = dict(scenario="sdof-stiffness", method="tpe", space={"p0": {"loguniform": [1e-2, 1e8]}, "lam": [0.99, 1.0]},
           samples=4, rounds=2, seeds=1, steps=600)


def test_tpe_rounds_ask_where_the_told_scores_are_low():
    """Told a known score (lowest at p0 = 1e7, lam = 1, nu = 15) round by round, the sampler's batches move to
    it: the last round's median score is well below the first (random) round's, and the best found beats as
    many random draws, over three search seeds."""
    pytest.importorskip("optuna")
    import numpy as np

    def score(c):
        return 0.3 * abs(math.log10(c["p0"]) - 7) + 200 * (1 - c["lam"]) + (c["nu"] != 15)
    space = {"p0": {"loguniform": [1e-2, 1e10]}, "lam": {"uniform": [0.98, 1.0]}, "nu": [5, 15, 45]}
    best_tpe, best_random = 0.0, 0.0
    for seed in range(3):
        t = Tuning(scenario="sdof-stiffness", method="tpe", space=space, samples=32, rounds=4, seed=seed)
        assert t.ask([], 0) == t.ask([], 0)                              # seeded: the same batch again
        history, medians = [], []
        for r in range(4):
            batch = t.ask(history, r)
            assert len(batch) == 8 and len({c["p0"] for c in batch}) == 8     # a batch, not one point 8 times
            assert all(1e-2 <= c["p0"] <= 1e10 and 0.98 <= c["lam"] <= 1 and c["nu"] in (5, 15, 45) for c in batch)
            history += [(c, score(c)) for c in batch]
            medians.append(np.median([score(c) for c in batch]))
        assert medians[-1] < 0.6 * medians[0], medians
        best_tpe += min(s for _, s in history)
        random = Tuning(scenario="sdof-stiffness", method="random", space=space, samples=32, seeds=1, seed=seed)
        best_random += min(score(m) for m in random.sweep().members())
    assert best_tpe < 0.7 * best_random


def test_tpe_candidates_are_members_of_batched_runs_and_an_interrupted_search_resumes_to_the_same_result(tmp_path):
    pytest.importorskip("optuna")
    import json

    from rcotorch.run.runner import Interrupted
    whole = run_tune(Tuning(**TPE), out=tmp_path / "whole", progress=False)
    assert whole.members == 4 and len(whole.candidates) == 4
    scores = {}
    for r in (0, 1):                 # one sweep per round; p0 and lam are per member: one batch of two
        folder = tmp_path / "whole" / "runs" / f"round_{r:03d}"
        rows = json.loads((folder / "sweep.json").read_text())
        assert len(rows) == 2 and {row["shard"] for row in rows} == {0}
        assert json.loads((folder / "shard_0000" / "summary.json").read_text())["batch"] == 2
        scores.update({(row["p0"], row["lam"]): row["validation_rmse"] for row in rows})
    assert {(c["settings"]["p0"], c["settings"]["lam"]): c["score"] for c in whole.candidates} == scores
    assert [c["score"] for c in whole.candidates] == sorted(scores.values())
    assert tomllib.loads((tmp_path / "whole" / "best.toml").read_text())["settings"] == whole.best

    def stop():                      # a stop request during the second round
        return (tmp_path / "cut" / "runs" / "round_001").exists()
    with pytest.raises(Interrupted):
        run_tune(Tuning(**TPE), out=tmp_path / "cut", progress=False, stop=stop)
    assert not (tmp_path / "cut" / "tune.csv").exists()
    shard = tmp_path / "cut" / "runs" / "round_000" / "shard_0000" / "summary.json"
    stamp = shard.stat().st_mtime_ns
    resumed = run_tune(Tuning(**TPE), out=tmp_path / "cut", progress=False, resume=True)
    assert shard.stat().st_mtime_ns == stamp                    # the finished round was read, not run again
    assert [(c["settings"], c["score"]) for c in resumed.candidates] == \
        [(c["settings"], c["score"]) for c in whole.candidates]


def test_tpe_without_optuna_says_how_to_install(tmp_path, monkeypatch):
    import sys
    monkeypatch.setitem(sys.modules, "optuna", None)
    with pytest.raises(ConfigError, match=r"pip install 'rcotorch\[tune\]'"):
        run_tune(Tuning(**TPE), out=tmp_path / "t", progress=False)
    assert not (tmp_path / "t").exists()


def test_a_tpe_config_is_checked():
    pytest.importorskip("optuna")
    with pytest.raises(ConfigError, match="rounds .3. cannot exceed samples .2."):
        Tuning.from_dict(dict(TPE, samples=2, rounds=3)).ask([], 0)
    with pytest.raises(ConfigError, match="'p0'.*normal"):
        Tuning.from_dict(dict(TPE, space={"p0": {"normal": [1.0, 0.1]}})).ask([], 0)
    with pytest.raises(ConfigError, match=r"tune space .*lam must lie in \(0, 1\]"):
        run_tune(Tuning.from_dict(dict(TPE, space={"lam": {"uniform": [0.9, 2.0]}})), out=None, progress=False)


def test_ray_backend_tunes_as_the_local_one(tmp_path):
    """The same candidates, scores and ranking from Ray tasks as from this process, for a grid search and for a
    tpe search, whose later rounds follow the earlier rounds' scores."""
    ray = pytest.importorskip("ray")
    searches = [Tuning(scenario="sdof-stiffness", method="grid", space={"p0": [1.0, 1e3], "nu": [5, 15]}, seeds=1,
                       steps=400)]
    try:
        import optuna  # noqa: F401
        searches.append(Tuning(**TPE))
    except ImportError:
        pass
    local = [run_tune(t, out=tmp_path / f"local{i}", progress=False) for i, t in enumerate(searches)]
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        remote = [run_tune(t, out=tmp_path / f"ray{i}", backend="ray", progress=False)
                  for i, t in enumerate(searches)]
    finally:
        ray.shutdown()
    for a, b in zip(local, remote):
        assert [(c["settings"], c["score"], c["rank"]) for c in a.candidates] == \
            [(c["settings"], c["score"], c["rank"]) for c in b.candidates]
        assert a.best == b.best and a.members == b.members


def test_a_tuning_whose_scenario_validates_nothing_for_its_settings_says_so(tmp_path):
    """The thermosphere validates on held-out data only when asked (validate_h > 0): a tuning without it
    stops with an error naming the scenario, instead of ranking candidates that all score infinity."""
    t = Tuning(scenario="thermosphere-no-cooling", method="grid", space={"p0": [1.0]}, seeds=1, steps=10,
               fixed={"dz_km": 10.0, "nu": 8, "refresh_every": 0, "spinup_days": 1.0})
    with pytest.raises(ConfigError, match="no candidate of scenario 'thermosphere-no-cooling' was validated"):
        run_tune(t, out=tmp_path / "t", progress=False)


# --- a second run, an aborted run, the declared space, and best.toml of a scenario declared in a script ---------
def test_a_second_tuning_into_its_folder_is_refused_in_the_words_of_run_tune(tmp_path):
    t = Tuning(scenario="sdof-stiffness", method="grid", space={"p0": [1e3]}, seeds=1, steps=300)
    run_tune(t, out=tmp_path / "t", progress=False)
    with pytest.raises(OutputError, match="pass resume=True to continue it, overwrite=True to replace it, or choose "
                                          "another out") as refused:
        run_tune(t, out=tmp_path / "t", progress=False)
    assert "--" not in str(refused.value)                     # no command-line option in a Python caller's message


@pytest.mark.parametrize("abort", [KeyboardInterrupt, RuntimeError])
def test_a_tuning_aborted_before_any_candidate_ran_leaves_nothing_that_blocks_the_next(abort, tmp_path,
                                                                                       monkeypatch):
    """Ctrl-C or an error after the folder was opened but before any candidate ran: the folder is left as it was
    found (no manifest), so the next tuning there starts without resume or overwrite."""
    import rcotorch.run.tune as tune_module
    t = Tuning(scenario="sdof-stiffness", method="grid", space={"p0": [1e3]}, seeds=1, steps=300)

    def aborted(*args, **kwargs):
        raise abort("stopped")
    with monkeypatch.context() as m:
        m.setattr(tune_module, "run_sweep", aborted)
        with pytest.raises(abort):
            run_tune(t, out=tmp_path / "t", progress=False)
    assert not (tmp_path / "t").exists()
    assert run_tune(t, out=tmp_path / "t", progress=False).best == {"p0": 1e3}


def test_a_tuning_whose_sweep_never_started_resumes(tmp_path):
    """A tuning folder whose manifest lists the candidates' sweep, which never opened its folder (a tuning
    stopped in between): resume runs the sweep afresh instead of refusing a sweep it cannot find."""
    import json

    from rcotorch.run.outputs import MANIFEST
    t = Tuning(scenario="sdof-stiffness", method="grid", space={"p0": [1e3]}, seeds=1, steps=300)
    (tmp_path / "t").mkdir()
    (tmp_path / "t" / MANIFEST).write_text(json.dumps({"scenario": "sdof-stiffness", "kind": "tune", "files": [],
                                                       "children": ["runs"]}))
    assert run_tune(t, out=tmp_path / "t", progress=False, resume=True).best == {"p0": 1e3}


def test_a_scenario_declares_the_space_that_tune_by_name_searches():
    from rcotorch.run import scenario as scenarios
    t = Tuning.declared("sdof-stiffness", samples=4, fixed={"noise": 0.05})
    assert t.space == {"p0": {"loguniform": [1e-2, 1e10]}, "lam": [0.98, 0.995, 0.999, 1.0], "nu": [5, 15, 45]}
    held = t.fixing({"lam": 1.0})
    assert set(held.space) == {"p0", "nu"} and held.fixed == {"noise": 0.05, "lam": 1.0}
    declared = [n for n, sc in scenarios.available().items() if sc.tuning_space]
    assert {"sdof-stiffness", "sdof-stiffness-damping", "twodof-stiffness", "sdof-dynamic-impedance", "rlc-circuit",
            "mass-friction"} <= set(declared)
    for name in declared:                               # every declared space draws candidates a sweep can run
        assert len(Tuning.declared(name, samples=3, seeds=1).sweep().members()) == 3
    with pytest.raises(ConfigError, match="scenario 'silverbox-cubic-stiffness' declares no search space"):
        Tuning.declared("silverbox-cubic-stiffness")


def test_best_toml_of_a_scenario_declared_in_a_script_says_how_to_run_it_from_that_script(tmp_path, monkeypatch):
    """The comment of best.toml gives the lines that run the chosen settings from the script that declares the
    scenario (`rcotorch run my-room` would not find it), and they run."""
    room = _Room.scenario()
    result = run_tune(Tuning(scenario=room, method="grid", space={"p0": [1e-2]}, seeds=1), out=tmp_path / "room",
                      progress=False)
    text = (tmp_path / "room" / "best.toml").read_text()
    assert "# run it: rcotorch run" not in text and "declared in a script, not registered" in text
    code = "\n".join(line[len("#     "):] for line in text.splitlines() if line.startswith("#     "))
    assert "Run(Room(), overrides=settings)" in code
    monkeypatch.chdir(tmp_path)
    namespace = {"Room": type(room)}
    exec(code, namespace)                                            # the lines as a user pastes them
    assert namespace["settings"] == result.best and namespace["run"].settings["p0"] == 1e-2
    assert (tmp_path / "runs" / "my-room" / "summary.json").exists()
