"""The numba peer of the speed comparison (numba_loop.py) computes the refinement of the NumPy loop: every variant
(one member, prange over members, 16-lane chunks) against numpy_loop.py to 1e-9. Without numba these checks are
skipped."""

import numpy as np
import pytest

pytest.importorskip("numba")
import numba_loop  # noqa: E402
import numpy_loop as nr  # noqa: E402

STEPS = 1500


@pytest.mark.parametrize("variant", ["one", "prange", "lanes"])
def test_every_variant_matches_the_numpy_loop(variant):
    """Members 0 and 17 of a batch of 19 (a second, partly filled lane chunk), each from its own stream."""
    theta, P = numba_loop.run(variant, STEPS, 19)
    for b in (0, 17):
        ref = nr.refine(STEPS, member=b)
        np.testing.assert_allclose(theta[b], ref["theta"][0], rtol=1e-9, atol=0)
        np.testing.assert_allclose(P[b], ref["P"], rtol=0, atol=1e-9 * np.abs(ref["P"]).max())


def test_batch_of_one_uses_the_stream_of_a_single_run():
    theta, _ = numba_loop.run("one", STEPS, 1)
    np.testing.assert_allclose(theta[0], nr.refine(STEPS)["theta"][0], rtol=1e-9, atol=0)


def test_other_settings_reach_the_loop():
    settings = {"dK": 0.3, "lam": 0.999, "nu": 8}
    theta, _ = numba_loop.run("lanes", STEPS, 1, settings)
    np.testing.assert_allclose(theta[0], nr.refine(STEPS, settings)["theta"][0], rtol=1e-9, atol=0)


def test_nc_other_than_one_is_refused():
    with pytest.raises(ValueError, match="nc = 1"):
        numba_loop.model({"nc": 2})


def test_normals_drawn_two_at_a_time_give_the_same_refinement_and_standard_normals():
    """Normals drawn two at a time (one log and square root, a cosine and a sine for two steps) are the stream's
    own: every variant computes the NumPy loop's refinement from them, and the pairs have the moments of N(0, 1)
    (200,000 draws: mean and variance within 5 standard errors, the two halves of a pair uncorrelated)."""
    for variant in ("one", "prange", "lanes"):
        theta, _ = numba_loop.run(variant, STEPS, 19, pairs=True)
        for b in (0, 17):
            np.testing.assert_allclose(theta[b], nr.refine(STEPS, member=b)["theta"][0], rtol=1e-9, atol=0)
    h0 = numba_loop._stream(1, 0)
    z = np.array([numba_loop._normal_pair(h0, p) for p in range(100_000)])
    n = z.size
    assert abs(z.mean()) < 5 / np.sqrt(n) and abs(z.var() - 1.0) < 5 * np.sqrt(2.0 / n)
    assert abs(np.corrcoef(z[:, 0], z[:, 1])[0, 1]) < 5 / np.sqrt(len(z))
    np.testing.assert_array_equal(z[:3].reshape(-1), [numba_loop._normal(h0, k) for k in range(6)])
