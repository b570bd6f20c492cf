"""The speed work keeps results exact, and the benchmark scripts run (tiny sizes; the numbers themselves are
measured by the scripts in benchmarks/, not here)."""

import json

import numpy as np
import pytest
import torch
from bench_scripts import ROOT, run_script

import rcotorch as rt
from rcotorch.blocks.sources import _normal_grid
from rcotorch.engine import rng
from rcotorch.run import scenario as scenarios


@pytest.mark.parametrize("start,length,width", [(0, 512, 1), (517, 3, 2), (2**33 + 5, 4, 3)])
def test_noise_grid_equals_rng_normal_bitwise(start, length, width):
    seeds = torch.tensor([1, 5, 2**31 + 3, 0, -7])
    members = torch.tensor([0, 4, 2**33, 9, 1])
    fast = _normal_grid(seeds, members, start, length, width, torch.float64)
    ref = rng.normal(seeds.reshape(-1, 1, 1), members.reshape(-1, 1, 1),
                     torch.arange(start, start + length).reshape(1, -1, 1), torch.arange(width).reshape(1, 1, -1))
    assert torch.equal(fast, ref)


def test_white_noise_chunk_length_does_not_change_samples():
    """A large batch draws shorter chunks; the samples are the same functions of (seed, member, step)."""
    big = rt.WhiteNoise(2, seed=3)
    big.reset(3000)                                   # 2**18 / 6000 -> chunks of 43 steps
    small = rt.WhiteNoise(2, seed=3)
    small.reset(3)                                    # chunks of 512 steps
    for _ in range(100):
        a, b = big.step()["out"], small.step()["out"]
    assert torch.equal(a[:3], b)


@pytest.mark.parametrize("name", ["sdof-stiffness-damping", "sdof-dynamic-impedance"])
def test_large_batch_members_equal_small_batch_runs_bitwise(name):
    """Every operation of a step acts on each member separately, so member b of a batch of 1000 is bit for
    bit the member b of a batch of 3 (and member 0 the batch-of-one run)."""
    sc = scenarios.get(name)
    s = sc.resolve()
    thetas = {}
    for B in (1, 3, 1000):
        g = sc.build(s, B, torch.float64, "cpu")
        g.run(300)
        est = g.blocks["identified"]
        thetas[B] = (est.theta.clone(), est.P.clone())
    assert torch.equal(thetas[1000][0][:3], thetas[3][0]) and torch.equal(thetas[1000][1][:3], thetas[3][1])
    assert torch.equal(thetas[3][0][:1], thetas[1][0]) and torch.equal(thetas[3][1][:1], thetas[1][1])


@pytest.mark.parametrize("lam", [1.0, 0.97])
def test_rls_inplace_equals_functional_bitwise(lam):
    g = torch.Generator().manual_seed(3)
    B, n = 7, 4
    theta = torch.randn(B, n, generator=g, dtype=torch.float64)
    M = torch.randn(B, n, n, generator=g, dtype=torch.float64)
    P = M @ M.mT + torch.eye(n, dtype=torch.float64)
    psi = torch.randn(B, n, 1, generator=g, dtype=torch.float64)
    z_r = torch.randn(B, 1, generator=g, dtype=torch.float64)
    active = torch.tensor([True, True, False, True, True, False, True])
    th_f, P_f, ok_f = rt.rls_update(theta, P, psi, z_r, lam, 1.0, active)
    th_i, P_i = theta.clone(), P.clone()
    out = rt.rls_update(th_i, P_i, psi, z_r, lam, 1.0, active, inplace=True)
    assert out[0] is th_i and out[1] is P_i
    assert torch.equal(th_i, th_f) and torch.equal(P_i, P_f) and torch.equal(out[2], ok_f)
    assert torch.equal(P_i[~active], P[~active]) and torch.equal(th_i[~active], theta[~active])


def test_throughput_script_quick(tmp_path):
    out = tmp_path / "t.json"
    run_script("throughput", "--quick", "--batches", "1,8", "--no-memory", "--out", str(out))
    res = json.loads(out.read_text())
    assert [r["B"] for r in res["torch"]] == [1, 8]
    assert all(r["refinement_steps_per_s"] > 0 and r["ratio_vs_numpy"] > 0 for r in res["torch"])
    assert res["numpy"]["refinement_steps_per_s"] > 0
    assert "B=1: no slower than the NumPy loop" in res["goals"]


def test_peak_memory_in_a_subprocess():
    done = run_script("throughput", "--_memory", "sdof-stiffness-damping", "16", "3", "--device", "cpu",
                      "--threads", "1")
    m = json.loads(done.stdout.strip().splitlines()[-1])
    assert m["B"] == 16 and m["n_theta"] == 3 and m["peak_bytes"] >= 0 and m["state_bytes"] > 0


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_user_function_script_quick(tmp_path):
    out = tmp_path / "uf.json"
    run_script("user_function", "--quick", "--batches", "1", "--seconds", "0.1", "--out", str(out))
    row = json.loads(out.read_text())["results"][0]
    assert row["batch"] == 1 and row["compiled_ns"] > 0 and row["gain_ns"] > 0


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_duffing_script_quick(tmp_path):
    out = tmp_path / "duffing.json"
    run_script("duffing", "--quick", "--batches", "1", "--seconds", "0.1", "--out", str(out))
    row = json.loads(out.read_text())["results"][0]
    assert row["batch"] == 1 and row["engine_ns"] > 0 and row["numba_loop_ns"] > 0


def test_thermosphere_native_script_quick(tmp_path):
    out = tmp_path / "th.json"
    run_script("thermosphere_native", "--quick", "--no-figures", "--out", str(out))
    res = json.loads(out.read_text())
    assert res["steps"] == 48 and res["run_ratio"] > 0 and res["metrics_relative_difference"] < 1e-6
    assert res["native"]["run_s"] > 0 and res["torch"]["process_s"] > res["torch"]["run_s"]


def test_rls_kernel_script_quick(tmp_path):
    out = tmp_path / "r.json"
    run_script("rls_kernel", "--quick", "--batches", "64", "--n", "3", "--no-compile", "--out", str(out))
    res = json.loads(out.read_text())
    v = res["results"][0]["variants"]
    assert set(v) == {"inplace", "inplace_torch", "functional", "before"}
    assert res["memcpy_bytes_per_s"] > 0 and v["inplace"]["effective_P_bytes_per_s"] > 0


def test_csv_memory_script_quick(tmp_path):
    out = tmp_path / "c.json"
    run_script("csv_memory", "--quick", "--out", str(out))
    res = json.loads(out.read_text())
    assert res["values_equal"] and res["file"]["rows"] == 20000 and res["asked_bytes"] == 8 * 20000 * 2
    assert res["rcotorch"]["seconds"] > 0 and res["loadtxt"]["seconds"] > 0


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the no-CUDA path")
def test_cuda_request_is_skipped_cleanly_without_cuda(tmp_path):
    out = tmp_path / "x.json"
    for script in ("throughput", "rls_kernel"):
        assert "no CUDA device" in run_script(script, "--device", "cuda", "--quick", "--out", str(out)).stdout
    assert not out.exists()


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_benchmarks_run_on_cuda(tmp_path):
    out = tmp_path / "g.json"
    run_script("throughput", "--device", "cuda", "--quick", "--batches", "1,64", "--out", str(out))
    assert json.loads(out.read_text())["machine"]["device"].startswith("cuda")
    run_script("rls_kernel", "--device", "cuda", "--quick", "--batches", "1024", "--n", "3", "--no-compile",
               "--out", str(out))


def test_the_batched_unscented_filter_is_filterpys():
    """The batched unscented filter that benchmarks/ukf_peer.py runs (ukf_filters.py) computes what filterpy's
    UnscentedKalmanFilter does, step for step, on the damaged building's data."""
    pytest.importorskip("filterpy")
    import numpy as np
    import ukf_filters
    sc = scenarios.get(ukf_filters.NAME)
    s = sc.resolve(ukf_filters.VELOCITY)
    A, Bw, Bu, Cy, Cd = ukf_filters.model(sc, s)
    R = np.eye(Cy.shape[0]) * s["noise"] ** 2
    w, y = ukf_filters.record(sc, s, 2, [sc.steps])[:2]
    steps = 600
    batched = ukf_filters.batched_ukf(A, Bw, Bu, Cy, Cd, s["k"], w[:steps], y[:steps], R)[0]
    for b in range(2):
        one = ukf_filters.filterpy_run(A, Bw, Bu, Cy, Cd, s["k"], w[:steps, b], y[:steps, b], R)[0]
        # the first steps divide tiny innovations by tiny variances (P0 of the states 1e-8): rounding grows to 1e-8
        np.testing.assert_allclose(batched[:, b], one, rtol=1e-6, atol=1e-7)
        assert np.abs(one).max() > 0.01


def test_the_paired_comparison_of_errors_tells_apart_only_what_differs():
    """ukf_filters.compare: identical errors differ by 0 with an interval of 0; errors larger by 1e-3 in every member
    give median and largest differences of -1e-3 whose intervals exclude 0; two independent draws of one
    distribution have intervals that hold 0."""
    import numpy as np
    import ukf_filters
    e = np.random.default_rng(5).exponential(1e-3, 64)
    same = ukf_filters.compare(e, e)
    assert same["a_smaller_share"] == 0 and same["median_difference_95"] == [0.0, 0.0]
    better = ukf_filters.compare(e, e + 1e-3)
    assert better["a_smaller_share"] == 1
    assert better["median_difference"] == pytest.approx(-1e-3) and better["max_difference"] == pytest.approx(-1e-3)
    assert better["median_difference_95"][1] < 0 and better["max_difference_95"][1] < 0
    f = np.random.default_rng(6).exponential(1e-3, 64)
    tie = ukf_filters.compare(e, f)
    assert tie["median_difference_95"][0] < 0 < tie["median_difference_95"][1]


def test_the_coverage_table_in_the_docs_is_the_one_the_script_prints():
    """docs/intervals.md shows benchmarks/interval_coverage.py's table of the results on record, as printed."""
    from coverage_cases import CASES
    results = json.loads((ROOT / "benchmarks" / "results" / "interval_coverage.json").read_text())
    assert set(CASES) <= set(results)
    table = run_script("interval_coverage", "--table").stdout.rstrip("\n")
    assert table.startswith("| case |") and table in (ROOT / "docs" / "intervals.md").read_text()


def test_the_coverage_tables_interval_is_the_exact_binomial_one():
    """The coverage's 95% interval in the table is the Clopper-Pearson interval that scipy's binomial test gives,
    including at 0 and all of n."""
    from coverage_cases import clopper_pearson
    from scipy.stats import binomtest
    for k, n in ((950, 1000), (388, 394), (0, 12), (12, 12), (1, 2)):
        ci = binomtest(k, n).proportion_ci(confidence_level=0.95, method="exact")
        assert clopper_pearson(k, n) == pytest.approx([ci.low, ci.high], abs=1e-12), (k, n)


def test_the_coverage_of_a_case_built_in_python_is_measured(tmp_path):
    """The Duffing case (a graph built in Python with a continuous nonlinear truth) at a tiny size."""
    from coverage_cases import coverage
    r = coverage("duffing", 2, tmp_path)
    assert sum(r["shares"].values()) == pytest.approx(1.0) and "k3" in r["estimates"]


def test_the_cost_of_a_run_in_the_docs_is_the_table_the_script_prints():
    """docs/cli.md shows benchmarks/cli_cost.py's tables of the results on record (cli_cost.json and
    sweep_cost.json), as printed: the end of a run part by part, the member-step end to end, the sweeps."""
    table = run_script("cli_cost", "--table").stdout.rstrip("\n")
    assert table.startswith("| scenario |") and "| 4096 members in 64 shards, " in table
    assert "one after another in one process" in table
    assert table in (ROOT / "docs" / "cli.md").read_text()


@pytest.mark.parametrize("case", ["sdof-discrete", "sdof-continuous"])
def test_the_offline_copy_of_the_interval_rule_gives_the_runs_intervals(tmp_path, case):
    """benchmarks/interval_rules.py records every member's interval inputs and writes the rule again in NumPy:
    on the records it gives the run's own intervals and statuses, and so the coverage the case measured (a case
    with the output error's step only, and one with the model class's bias against the physics as well)."""
    import importlib.util
    spec = importlib.util.spec_from_file_location("interval_rules", ROOT / "benchmarks" / "interval_rules.py")
    rules = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(rules)
    rec = rules.capture(case, 12, tmp_path)
    assert rules.reproduces(rec)
    keys = rec["intervals"]["keys"]
    assert {"d", "sd_d", "sd_o", "model", "t"} <= set(keys["dC"])
    bias = float(np.median(np.abs(keys["dC"]["model"]) / keys["dC"]["sd_r"]))    # the physics' bias in sd of dC
    assert (bias > 0.5) if case == "sdof-continuous" else (bias < 0.05)
    scored = rules.score(rec, rules.shipped)
    for key, row in rec["coverage"]["estimates"].items():
        assert scored["estimates"][key]["coverage"] == pytest.approx(row["coverage"], abs=1e-3, nan_ok=True)
    assert scored["shares"]["converged"] == pytest.approx(rec["coverage"]["shares"]["converged"], abs=1e-3)
