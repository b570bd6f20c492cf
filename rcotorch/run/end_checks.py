"""The checks at the end of a run beyond its members' health, and the warnings they give: a refined model that fits
the data worse than the initial one (``fits_worse``, ``fit_warnings``), a p0 too small for the regressors
(``tuning_warnings``), how long the intervals' replay must settle (``loop_settle``) and the warning where it
settled less (``settle_note``), and the residual checks as per-member metrics (``residual_metrics``)."""

from __future__ import annotations

import math
from collections.abc import Mapping

import torch

from ..errors import ConfigError
from ..estimator.tracking import _closed_loop
from ..verdict import intervals as ci

PRIOR_SHARE = 0.5     # P_ii / p0 above this at the end: the data did less than the prior to fix parameter i
FIT_WORSE = 5.0        # percentage points: a refined model this much below the initial model's fit went astray
_FITS = (("over the run's last window", "fit_percent", "fit_percent_initial"),
         ("on the held-out data", "validation_fit_percent", "validation_fit_percent_initial"))


def loop_settle(graph) -> torch.Tensor | None:
    """Steps each member's frozen loop needs to forget its start, (B,): ``ci.SETTLE_TAUS`` time constants of the
    slowest decaying mode (|eigenvalue| < 1) of the known model with the estimator's loop closed at its present
    theta (the loop of ``rcotorch.estimator.tracking.closed_loop_markov``), at most ``ci.SETTLE_MAX``; None where
    that loop cannot be formed (a known model that is not an ``LTI``, features, a regressor fed through another
    block)."""
    est = graph.role("estimator")
    try:
        A = _closed_loop(graph, est.theta.detach(), None, None, "u", "y", None)[0]
    except (ConfigError, KeyError, AttributeError, TypeError, ValueError, RuntimeError):
        return None
    A = A.detach().to("cpu", torch.float64)
    A = torch.where(torch.isfinite(A).flatten(1).all(1).reshape(-1, 1, 1), A, 0.0)   # a diverged member: none
    mag = torch.linalg.eigvals(A).abs()
    rho = torch.where(mag < 1.0 - 1e-12, mag, 0.0).amax(-1) if mag.shape[-1] else torch.zeros(mag.shape[0])
    taus = torch.where(rho > 0, ci.SETTLE_TAUS / -torch.log(rho.clamp_min(1e-300)), 0.0)
    return taus.clamp_max(ci.SETTLE_MAX).ceil().to(torch.int64).to(est.theta.device)


def settle_note(settle: int, need: int | None, why: str, dt: float | None) -> list[str]:
    """The warning where the intervals' replay settled for ``settle`` steps but the slowest loop needs ``need``
    (``why`` it settled less; ``dt``: the sample time, to say it in seconds); none where it settled long enough."""
    if need is None or settle >= need:
        return []
    unit = (lambda n: f"{n * dt:.4g} s") if dt else (lambda n: f"{n} steps")
    return [f"the intervals' replay settled for {unit(settle)} where the refined loop's slowest mode needs "
            f"{unit(need)} ({ci.SETTLE_TAUS:g} time constants) to forget the window's start: {why}; the "
            "intervals and residual checks may carry that transient"]


def tuning_warnings(graph) -> list[str]:
    """Settings far off for the data, judged at the end of a run: a p0 so small against the regressors that
    the data barely moved P from p0 I (P_ii / p0 > ``PRIOR_SHARE``; with P^-1 = I / p0 + sum Psi Psi^T that
    means p0 sum psi_i^2 < 1, so theta stays near its initial value). Members that forget (lam < 1) are not
    judged: their P is renewed from the data, and p0 matters little."""
    est = graph.role("estimator") if "estimator" in graph.roles else None
    if est is None or not hasattr(est, "P") or est.P.shape[0] == 0:
        return []
    B = est.P.shape[0]
    p0 = est.p0.to(torch.float64).reshape(-1, 1).expand(B, 1)
    lam = torch.as_tensor(est.lam, dtype=torch.float64).reshape(-1, 1).expand(B, 1).to(p0.device)
    share = torch.diagonal(est.P.to(torch.float64), dim1=1, dim2=2) / p0              # (B, n_eta)
    stuck = (share > PRIOR_SHARE) & (lam >= 1.0)
    if not bool(stuck.any()):
        return []
    members = stuck.any(1).nonzero().flatten().tolist()
    names = getattr(est, "theta_names", None) or [f"theta[{i}]" for i in range(share.shape[1])]
    which = sorted({names[i] for i in stuck.any(0).nonzero().flatten().tolist() if i < len(names)})
    info = (p0 / share.clamp_min(1e-300) - p0).clamp_min(0) / p0.square()             # sum psi_i^2
    suggest = float((1e3 / info[stuck].clamp_min(1e-300)).median())
    where = f"member {members[0]}" if len(members) == 1 else f"{len(members)} members"
    steps = int(est.k)
    return [f"p0 = {float(p0[members[0], 0]):.3g} is small for the regressors of {steps} steps ({where}): the data "
            f"moved P by less than half from p0 I for {', '.join(which)}, so theta stays near its initial value; "
            f"try p0 of about {suggest:.2g}, or a longer run (the data's weight grows with the steps)"]


def _fit_pairs(met: Mapping[str, torch.Tensor]):
    """For each fit the run computed: what it is over, the refined and the initial model's fits (B,) and where
    the refined one is more than ``FIT_WORSE`` points below."""
    for what, refined, initial in _FITS:
        if refined in met and initial in met:
            r, i = (met[key].detach().to(torch.float64).cpu().reshape(-1) for key in (refined, initial))
            yield what, r, i, r < i - FIT_WORSE


def fits_worse(met: Mapping[str, torch.Tensor]) -> torch.Tensor | None:
    """(B,) bool: the members whose refined model fits the data worse than the initial (known) model did, on the
    run's last window (``fit_percent`` against ``fit_percent_initial``) or on held-out data
    (``validation_fit_percent``), by more than ``FIT_WORSE`` points; None where no fit was computed. A
    refinement exists to explain the data better; one that explains it worse went astray (an unstable
    adaptation, a Markov window much shorter than the known model's response), whatever its estimates'
    intervals say, so such a member is not ``converged``."""
    out = None
    for _, _, _, worse in _fit_pairs(met):
        out = worse if out is None else out | worse
    return out


def fit_warnings(met: Mapping[str, torch.Tensor]) -> list[str]:
    """The warnings for ``fits_worse``: for each fit, the members below the initial model's and both fits."""
    out = []
    for what, r, i, worse in _fit_pairs(met):
        if not bool(worse.any()):
            continue
        members = worse.nonzero().flatten().tolist()
        where = f"member {members[0]}" if len(members) == 1 else f"{len(members)} of {len(r)} members"
        out.append(f"the refined model fits the data worse than the initial model {what} in {where} (fit "
                   f"{_span(r[worse])} % against {_span(i[worse])} %): the refinement went astray there; a longer "
                   f"Markov window (nu), forgetting nearer 1 or a smaller p0 may help")
    return out


def _span(t: torch.Tensor) -> str:
    """A value, or the range of several, in percent with one decimal."""
    return f"{float(t.min()):.1f}" if len(t) == 1 else f"{float(t.min()):.1f}..{float(t.max()):.1f}"


def residual_metrics(res: ci.Residuals) -> dict[str, torch.Tensor]:
    """The residual checks as per-member metrics: the fit in percent of the refined and the initial model, the
    largest |autocorrelation| of z over lags 1..L and |cross-correlation| of z with w over lags 0..L (to be read
    against ``residual_bound``, 1.96 / sqrt(N)), and the Ljung-Box p-value that z is white."""
    B = res.fit.shape[0]
    out = {"fit_percent": res.fit, "fit_percent_initial": res.fit_initial,
           "z_autocorr_max": res.autocorr[:, 1:].abs().flatten(1).amax(1) if res.autocorr.shape[1] > 1 else
           torch.full((B,), math.nan, dtype=torch.float64),
           "z_whiteness_p": res.whiteness_p}
    if res.xcorr is not None:
        out["z_w_xcorr_max"] = res.xcorr.abs().flatten(1).amax(1)
    out["residual_bound"] = torch.full((B,), res.bound, dtype=torch.float64)
    return out
