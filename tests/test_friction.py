"""The scenario mass-friction: Coulomb and viscous friction identified with the basis [sign(v), v], against the
truth's constants, and the verdict when the excitation leaves the mass stuck most of the time."""

import numpy as np
import pytest
import torch
from rcotorch.scenarios.mass_friction import friction_law

from rcotorch.run import scenario as scenarios
from rcotorch.run.runner import Run

pytest.importorskip("numba")


def _summary(tmp_path, steps, members):
    run = Run("mass-friction", steps=steps, members=members, out=tmp_path / "run", overwrite=True)
    run.advance(progress=False)
    return run.finish(figures=False)


def test_the_friction_law_is_coulomb_plus_viscous():
    law = friction_law(2.0, 0.5)
    v = np.array([[-3.0], [-0.1], [0.0], [0.1], [3.0]])
    assert np.allclose(law(v)[:, 0], [2.0 + 1.5, 2.0 + 0.05, 0.0, -2.0 - 0.05, -2.0 - 1.5])


def test_meets_its_requirements_against_the_truth_constants(tmp_path):
    sc = scenarios.get("mass-friction")
    Fc, c = sc.settings["Fc"], sc.settings["c"]
    summary = _summary(tmp_path, 6000, members=[{"seed": 1}, {"seed": 2}])
    assert summary["engine"] == "native", summary["engine_reason"]
    est = {k: np.asarray(v, dtype=float) for k, v in summary["estimates"].items()}
    assert np.all(np.abs(est["Fc"] - Fc) < 0.02 * Fc), est            # the truth's constants: Fc = 2, c = 0.5
    assert np.all(np.abs(est["c"] - c) < 0.05 * c), est
    assert summary["status"] == ["converged", "converged"]
    assert all(r["pass"] for r in summary["requirements"].values())
    # the default excitation keeps the mass sliding most of the time
    assert min(summary["metrics"]["sliding_fraction"]) > 0.85


def test_a_mass_stuck_most_of_the_time_is_not_reported_converged(tmp_path):
    summary = _summary(tmp_path, 4000, members=[{"w_std": 1.0, "seed": 1}, {"w_std": 1.0, "seed": 2}])
    assert max(summary["metrics"]["sliding_fraction"]) < 0.4             # stuck most of the time
    assert not any(any(r["member_pass"]) for r in summary["requirements"].values())    # and the estimates are wrong
    assert "converged" not in summary["status"], summary["health"]


def test_sliding_fraction_counts_samples_that_keep_the_velocity_sign():
    from rcotorch.scenarios.mass_friction import sliding_fraction
    sc = scenarios.get("mass-friction")
    s = sc.resolve_members({}, [{"w_std": 0.5}, {"w_std": 200.0}])
    frac = sliding_fraction(s, 2, 4000, torch.float64)
    assert frac[0] < 0.2 < 0.95 < frac[1]       # a weak push barely breaks the mass loose, a strong one keeps it going
