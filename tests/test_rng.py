"""Counter-based random numbers and the WhiteNoise source: distribution, per-member streams, checkpoints."""

import numpy as np
import pytest
import torch
from scipy import stats

import rcotorch as rt
from rcotorch.engine import rng


def _draw(block, steps):
    return torch.stack([block.step()["out"] for _ in range(steps)], dim=1)     # (B, steps, width)


def test_normal_distribution():
    x = rng.normal(7, 0, torch.arange(30_000)).numpy()      # below torch's parallel grain size (32768)
    assert x.dtype == np.float64
    n = x.size
    assert abs(x.mean()) < 4 / np.sqrt(n)
    assert abs(x.std() - 1.0) < 4 * np.sqrt(0.5 / n)
    assert stats.kstest(x, "norm").pvalue > 1e-3
    # Higher moments of a normal: skewness 0, excess kurtosis 0.
    assert abs(stats.skew(x)) < 4 * np.sqrt(6 / n)
    assert abs(stats.kurtosis(x)) < 4 * np.sqrt(24 / n)


def test_uniform_distribution_and_independent_keys():
    u = rng.uniform(3, torch.arange(20_000)).numpy()
    assert (u > 0).all() and (u < 1).all()
    assert stats.kstest(u, "uniform").pvalue > 1e-3
    # Neighbouring seeds, members and components give uncorrelated streams.
    k = torch.arange(20_000)
    a, b, c, d = (rng.normal(*keys).numpy() for keys in ((1, 0, k), (2, 0, k), (1, 1, k), (1, 0, k, 1)))
    for other in (b, c, d):
        assert abs(np.corrcoef(a, other)[0, 1]) < 4 / np.sqrt(k.numel())
    assert abs(np.corrcoef(a[:-1], a[1:])[0, 1]) < 4 / np.sqrt(k.numel())


def test_pure_function_of_keys():
    k = torch.arange(1000)
    assert torch.equal(rng.normal(5, 2, k), rng.normal(5, 2, k))
    assert torch.equal(rng.normal(5, 2, k)[700:], rng.normal(5, 2, k[700:]))
    assert not torch.equal(rng.normal(5, 2, k), rng.normal(5, 3, k))
    assert rng.normal(5, 2, k, dtype=torch.float32).dtype == torch.float32


def test_white_noise_statistics():
    blk = rt.WhiteNoise(2, std=[[0.5], [2.0]], mean=[[1.0], [-3.0]], seed=[4, 5])
    blk.reset(2)
    x = _draw(blk, 4000).numpy()
    for b, (m, s) in enumerate(((1.0, 0.5), (-3.0, 2.0))):
        v = x[b].reshape(-1)
        assert stats.kstest(v, "norm", args=(m, s)).pvalue > 1e-3


@pytest.mark.parametrize("b", [0, 2, 4])
def test_seed_list_member_equals_single_run(b):
    seeds = [101, 7, 55, 0, 2**31 + 3]
    batch = rt.WhiteNoise(3, seed=seeds)
    batch.reset(len(seeds))
    xb = _draw(batch, 600)
    single = rt.WhiteNoise(3, seed=seeds[b])
    single.reset(1)
    assert torch.equal(_draw(single, 600)[0], xb[b])


def test_int_seed_members_differ():
    blk = rt.WhiteNoise(1, seed=9)
    blk.reset(3)
    x = _draw(blk, 100)
    assert not torch.equal(x[0], x[1]) and not torch.equal(x[1], x[2])
    one = rt.WhiteNoise(1, seed=9)
    one.reset(1)
    assert torch.equal(_draw(one, 100)[0], x[0])


def test_same_samples_across_checkpoint_at_non_chunk_boundary():
    n1, n2 = 700, 900
    assert n1 % rt.WhiteNoise.CHUNK != 0
    ref = rt.WhiteNoise(2, seed=[3, 4, 5])
    ref.reset(3)
    full = _draw(ref, n1 + n2)

    first = rt.WhiteNoise(2, seed=[3, 4, 5])
    first.reset(3)
    part1 = _draw(first, n1)
    state = {k: v.clone() for k, v in first.state_dict().items()}
    # A fresh block, reset, then loaded.
    second = rt.WhiteNoise(2, seed=[3, 4, 5])
    second.reset(3)
    second.load_state_dict(state)
    part2 = _draw(second, n2)
    assert torch.equal(torch.cat([part1, part2], dim=1), full)
    # The same block reset and rewound: reset starts over, loading goes back to step n1.
    first.reset(3)
    assert torch.equal(_draw(first, 5), full[:, :5])
    first.load_state_dict(state)
    assert torch.equal(_draw(first, n2), full[:, n1:])


def test_load_state_dict_with_other_seed_replaces_cached_samples():
    n1 = 300
    ref = rt.WhiteNoise(1, seed=[1, 2])
    ref.reset(2)
    full = _draw(ref, n1 + 100)
    state = {k: v.clone() for k, v in ref.state_dict().items()}
    state["k"] = torch.tensor(n1)
    other = rt.WhiteNoise(1, seed=[8, 9])         # same chunk window [256, 512), other streams
    other.reset(2)
    _draw(other, 280)
    other.load_state_dict(state)
    assert torch.equal(_draw(other, 100), full[:, n1:])


def test_white_noise_in_graph_state_dict_roundtrip(sdof_known, zoh_first_order):
    """A whole Figure-1 graph restored from a checkpoint at a non-chunk step continues identically."""
    def build():
        est = rt.RCOEstimator({"y0": 1}, nc=2, p0=100.0)
        return rt.refinement(sdof_known(0.1), est, truth=zoh_first_order(0.1),
                             excitation=rt.WhiteNoise(1, seed=[1, 2]), nu=5, batch_size=2)

    g = build()
    full = g.run(300, record={"w": "excitation.out", "z": "error.out"})
    g1 = build()
    g1.run(130)
    state = {k: v.clone() for k, v in g1.state_dict().items()}
    g2 = build()
    g2.load_state_dict(state)
    rest = g2.run(170, record={"w": "excitation.out", "z": "error.out"})
    assert torch.equal(rest["w"], full["w"][130:])
    assert torch.equal(rest["z"], full["z"][130:])
    assert torch.equal(g2.blocks["identified"].theta, g.blocks["identified"].theta)
