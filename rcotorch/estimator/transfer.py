"""The identified subsystem as a transfer function: frequency response, DC gain and python-control export.

An RCO estimator's theta, split by lag (``RCOEstimator.coefficients``), gives the discrete system

    u(k) = sum_l N_l s(k-l) + sum_l M_l u(k-l),    H(z) = (I - sum_l M_l z^-l)^-1 sum_l N_l z^-l,

from the regressor signals s (n_sig) to u (n_u), with l over the estimator's ``lags`` for N and over
1..nc for M. The functions here take the estimator and read its coefficients, lags, ``sample_time`` and names;
the estimator's methods of the same names call them.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import torch

from ..errors import ConfigError

if TYPE_CHECKING:
    import control

    from ..blocks.base import Block


def _solve(A: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """A^-1 b per member, NaN for a member whose A is singular or not finite (a diverged member; CUDA's solver
    reports those as singular where LAPACK returns NaN)."""
    x, info = torch.linalg.solve_ex(A, b)
    bad = (info != 0).reshape(info.shape + (1,) * (x.dim() - info.dim()))
    return torch.where(bad, torch.full_like(x, math.nan), x)


def frequency_response(est: Block, omega) -> torch.Tensor:
    """The identified subsystem's frequency response at z = exp(j omega dt).

    Parameters
    ----------
    est : RCOEstimator
        The estimator.
    omega : array_like
        Angular frequencies [rad/s], (F,).

    Returns
    -------
    torch.Tensor
        Complex, (B, F, n_u, n_sig); NaN for a member whose denominator is singular or not finite.

    Raises
    ------
    ConfigError
        If the estimator has no sample time (``RCOEstimator.sample_time``).
    """
    dt = est.sample_time
    if not dt:
        raise ConfigError(f"block '{est.name}': dt is needed for a frequency response (give the estimator dt=, or "
                          "Markov parameters with their sample time: set_markov(..., dt=))")
    N, M = est.coefficients()
    omega = torch.as_tensor(omega, dtype=N.dtype, device=N.device)
    # z^-1 = exp(-j omega dt)
    zinv = torch.exp(-1j * omega * dt)                                  # (F,)
    lags = torch.as_tensor(est.lags, device=N.device)
    # sum_l N_l z^-l
    num = torch.einsum("fl,blij->bfij", zinv.unsqueeze(1) ** lags, N.to(zinv.dtype))
    ulags = torch.arange(1, M.shape[1] + 1, device=N.device)
    # I - sum_l M_l z^-l
    den = torch.eye(est.n_u, dtype=zinv.dtype, device=N.device) - \
        torch.einsum("fl,blij->bfij", zinv.unsqueeze(1) ** ulags, M.to(zinv.dtype))
    return _solve(den, num)


def dc_gain(est: Block) -> torch.Tensor:
    """DC gain of the identified subsystem, H(1) = (I - sum_l M_l)^-1 sum_l N_l.

    Without fed-back u (M = 0) it is sum_l N_l, with no linear solve.

    Parameters
    ----------
    est : RCOEstimator
        The estimator.

    Returns
    -------
    torch.Tensor
        (B, n_u, n_sig); NaN for a member whose I - sum_l M_l is singular or not finite.
    """
    N, M = est.coefficients()
    if not est.feed_u:
        return N.sum(1)
    eye = torch.eye(est.n_u, dtype=N.dtype, device=N.device)
    return _solve(eye - M.sum(1), N.sum(1))


def check_member(est: Block, member: int) -> None:
    """Check that the estimator has a batch member ``member``.

    Parameters
    ----------
    est : RCOEstimator
        The estimator.
    member : int
        The member (negative counts from the end).

    Raises
    ------
    ConfigError
        If the estimator has no members yet or ``member`` is out of range.
    """
    B = est.theta.shape[0]
    if B == 0:
        raise ConfigError(f"block '{est.name}': it has no members yet; build the graph (rt.refinement or "
                          "rt.Graph) before asking for its identified subsystem")
    if not -B <= member < B:
        raise ConfigError(f"block '{est.name}': member {member} out of range; the batch has {B} members")


def control_names(est: Block) -> dict:
    """python-control signal names: the regressor signals in, u out, the block's name as the system's.

    Parameters
    ----------
    est : RCOEstimator
        The estimator.

    Returns
    -------
    dict
        ``inputs`` ('y0', 'y0[1]' for a wide port, a feature's name), ``outputs`` ('u', or 'u[i]' for
        n_u > 1) and ``name``.
    """
    inputs = [f"{s}[{c}]" if w > 1 else s for s, w in est.signals.items() for c in range(w)]
    outputs = [f"u[{i}]" for i in range(est.n_u)] if est.n_u > 1 else ["u"]
    return dict(inputs=inputs, outputs=outputs, name=est.name)


def to_control(est: Block, member: int = 0) -> control.TransferFunction:
    """One member's identified subsystem as a discrete python-control ``TransferFunction`` with named signals.

    A SISO-denominator form (one u, or no fed-back u) is built directly; a MIMO controller with fed-back u
    shares its poles between channels and is built in state space (``state_space``) and converted.

    Parameters
    ----------
    est : RCOEstimator
        The estimator.
    member : int, optional
        The batch member (negative counts from the end).

    Returns
    -------
    control.TransferFunction
        Discrete, with the estimator's ``sample_time`` (True where it has none), signals named as by
        ``control_names``.

    Raises
    ------
    ConfigError
        If the estimator has no members yet or ``member`` is out of range.
    """
    import control
    check_member(est, member)
    names = control_names(est)
    if est.n_u != 1 and est.feed_u:
        return control.ss2tf(state_space(est, member), **names)
    N, M = (t[member].detach().cpu().numpy() for t in est.coefficients())
    L = est.nc if est.feed_u else max(est.lags)
    # den = 1 - M_1 z^-1 - ... - M_nc z^-nc, as the coefficients of z^0 .. z^-L
    den = np.zeros(L + 1)
    den[0] = 1.0
    if est.feed_u:
        den[1: est.nc + 1] = -M[: est.nc, 0, 0]
    nums, dens = [], []
    for i in range(est.n_u):
        row_n, row_d = [], []
        for j in range(est.n_sig):
            # num_ij: N_l[i, j] at z^-l
            num = np.zeros(L + 1)
            for li, lag in enumerate(est.lags):
                num[lag] = N[li, i, j]
            row_n.append(num)
            row_d.append(den)
        nums.append(row_n)
        dens.append(row_d)
    return control.tf(nums, dens, est.sample_time or True, **names)


def state_space(est: Block, member: int) -> control.StateSpace:
    """One member's identified subsystem in state space, the state holding past s and past u.

    x(k) = [s(k-1) .. s(k-nc), u(k-1) .. u(k-nc)]; u(k) = C x(k) + D s(k), the shift registers move s(k) and
    u(k) into x(k+1).

    Parameters
    ----------
    est : RCOEstimator
        The estimator.
    member : int
        The batch member.

    Returns
    -------
    control.StateSpace
        Discrete, with the estimator's ``sample_time`` (True where it has none), signals named as by
        ``control_names``.
    """
    import control
    N, M = (t[member].detach().cpu().numpy() for t in est.coefficients())
    nc, m, p = est.nc, est.n_sig, est.n_u
    n = nc * (m + p)
    A, Bm = np.zeros((n, n)), np.zeros((n, m))
    C, D = np.zeros((p, n)), np.zeros((p, m))
    # u(k) = D s(k) + sum_{l >= 1} N_l s(k-l) + sum_l M_l u(k-l)
    for li, lag in enumerate(est.lags):
        if lag == 0:
            D += N[li]
        else:
            C[:, (lag - 1) * m: lag * m] += N[li]
    for lag in range(1, nc + 1):
        C[:, nc * m + (lag - 1) * p: nc * m + lag * p] += M[lag - 1]
    # shift registers: s-part gets s(k), u-part gets u(k) = C x + D s
    Bm[:m] = np.eye(m)
    for lag in range(1, nc):
        A[lag * m:(lag + 1) * m, (lag - 1) * m: lag * m] = np.eye(m)
        A[nc * m + lag * p: nc * m + (lag + 1) * p, nc * m + (lag - 1) * p: nc * m + lag * p] = np.eye(p)
    A[nc * m: nc * m + p] += C
    Bm[nc * m: nc * m + p] += D
    return control.ss(A, Bm, C, D, est.sample_time or True, **control_names(est))
