"""Member health: every member of a run ends ``converged``, ``not_converged``, ``diverged``, ``undetermined`` or
``biased`` (``decide``).

**Diverged** members are frozen (theta and P held, u = 0) from a step on, for a ``Reason``:

* ``non_finite``: z, the regressor or theta's update is not finite (the estimator's step freezes the member);
* ``not_positive_definite``: P lost definiteness (the estimator's step finds the innovation covariance S not
  positive, or a check finds no Cholesky factor of P);
* ``theta_runaway``: theta would drive u far beyond the data's scale,
  ``max_i sum_j |theta_ij| phi_j,rms > runaway * u_scale``;
* ``u_runaway``: ``|u(k)| > runaway * u_scale``;
* ``covariance_windup``: ``trace(P) > windup * n_theta * p0`` (with lambda = 1, P never exceeds p0 I; with
  lambda < 1 and too little excitation it grows without bound). A P that overflowed is reported as windup.

The data's scale of u is ``u_scale = rms(y) / |beta|``: rms(y) is the rms of the measured output so far and
``|beta|`` the Frobenius norm of the Markov parameters of u -> z that the estimator uses, so a u of size
``u_scale`` moves z by about the rms of the data within nu steps. ``phi_j,rms`` is the rms of regressor entry
j sampled at the checks. The three bounds are checked at the check steps (``Health.is_check``): every
``check_every(steps)`` steps (2% of the run) from the convergence window's start on, every second of these
before it, about 30 checks a run; the same steps for any batch size, so a sweep member is frozen at the same
step as its separate run. Each check stops the engine (a pass over the batch's state): the window keeps every
check for its statistics, the checks before it only watch the bounds.

**Converged** or **not_converged** (members that were never frozen) is decided over the last ``window``
fraction of the steps (the window starts at a check step):

* ``theta_change``, theta's relative change over the window measured on the data: the rms of
  ``(theta_end - theta_start) phi(k)`` over the window's regressors phi(k), divided by the larger rms of
  ``theta_end phi(k)`` and ``theta_start phi(k)`` (or by ``1e-3 u_scale`` when both are smaller, so that an
  identified subsystem that is zero is judged against the data's scale); at most ``theta_tol``: the identified
  subsystem has settled. The regressors are those the estimator keeps (its last d + nu) of the steps since
  the previous check, each once: every step of the window when the checks are closer than d + nu steps, a
  sample of d + nu steps before each check when they are further apart. A drift of theta along directions
  the data does not see (a pole and a zero moving together, say) does not count, since it does not change
  the subsystem's output;
* ``z_ratio = rms(z) / rms(y)`` over the window, at most ``z_tol``: the refined model explains the data (a
  member whose measured output is zero over the window has learned nothing: its z_ratio is NaN and it is
  not converged).

The estimator's own step may freeze members and record why: an estimator with a ``diverged_reason`` buffer
((B,) int64, ``Reason`` codes, 0 while alive, next to ``alive`` and ``diverged_at``) is read as is; without
it, the reason of a member the step froze is inferred from its state (P not finite: windup; P not positive
definite: not_positive_definite; else an intermediate value was not finite: non_finite).
"""

from __future__ import annotations

import enum
import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch

from ..engine import kernels
from ..errors import ConfigError

STATUSES = ("converged", "not_converged", "diverged", "undetermined", "biased")
REASON_STATE = "diverged_reason"   # the estimator buffer that carries Reason codes


class Reason(enum.IntEnum):
    """Why a member was frozen (0 while it is alive)."""

    NONE = 0
    NON_FINITE = 1
    NOT_POSITIVE_DEFINITE = 2
    THETA_RUNAWAY = 3
    U_RUNAWAY = 4
    COVARIANCE_WINDUP = 5

    @property
    def label(self) -> str:
        return self.name.lower()


# Per-member words of summary.json, indexed by the status and Reason codes (object arrays: a batch's list in
# one numpy indexing instead of a Python loop over its members).
_STATUS_WORDS = np.array(STATUSES, dtype=object)
_REASON_LABELS = np.array([None] + [r.label for r in Reason if r], dtype=object)

# The bounds' reasons in the order of precedence of Health._bounds_exceeded (the compiled kernel's order).
_BOUND_REASONS = (int(Reason.NOT_POSITIVE_DEFINITE), int(Reason.COVARIANCE_WINDUP), int(Reason.U_RUNAWAY),
                  int(Reason.THETA_RUNAWAY))


@dataclass(frozen=True)
class Criteria:
    """Thresholds of the health checks (see the module docstring)."""

    window: float = 0.2          # the last fraction of the steps judged for convergence
    theta_tol: float = 0.02      # largest relative change of theta over the window (measured on the data)
    z_tol: float = 0.1           # largest rms(z) / rms(y) over the window
    runaway: float = 1e6         # theta and u bounds, in units of the data's scale of u
    windup: float = 1e6          # bound on trace(P) / (n_theta p0)

    def __post_init__(self):
        for key, value in asdict(self).items():
            if not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
                raise ConfigError(f"health criteria: {key} must be a finite positive number, got {value!r}")
        if self.window > 1:
            raise ConfigError(f"health criteria: window is a fraction of the steps in (0, 1], got {self.window}")
        for key in ("runaway", "windup"):
            if getattr(self, key) <= 1:
                raise ConfigError(f"health criteria: {key} must exceed 1, got {getattr(self, key)}")


def _definite(P: torch.Tensor) -> torch.Tensor:
    """(B,) True where P (B, n, n) is positive definite (and finite)."""
    return (torch.linalg.cholesky_ex(P.to(torch.float64)).info == 0) & torch.isfinite(P).flatten(1).all(1)


def finite_list(t: torch.Tensor) -> list:
    """The values of ``t`` as a list of floats, None where a value is not finite."""
    values = t.reshape(-1).to(torch.float64).tolist()
    if bool(torch.isfinite(t).all()):
        return values
    return [x if math.isfinite(x) else None for x in values]


CHECK_MAX = 50_000      # steps between checks at most: runs up to 2.5M steps are checked 10 times in the window


def check_every(steps: int) -> int:
    """Steps between health checks in the convergence window of a run of ``steps`` steps (2% of the run, at
    most CHECK_MAX); twice as many between the checks before the window (``Health.is_check``)."""
    return min(CHECK_MAX, max(1, steps // 50))


class Health:
    """Per-member health of one run: statistics gathered at every check, runaway and windup freezing, and
    the final status. ``check`` is called at the check steps (``is_check``, ``next_check``) with the sums of
    z^2 and y^2 over the steps since the last check (per member); ``status`` classifies every member."""

    def __init__(self, graph, steps: int, criteria: Criteria | None = None):
        self.graph, self.est = graph, graph.role("estimator")
        self.criteria = criteria or Criteria()
        self.every = check_every(steps)
        B, dev, f64 = self.est.theta.shape[0], self.est.theta.device, torch.float64
        self.state: dict[str, Any] = {
            "reason": torch.zeros(B, dtype=torch.int64, device=dev),
            "theta_ref": self._theta(), "k_ref": int(graph.k),         # the window's start
            "theta_mid": self._theta(), "k_mid": int(graph.k),         # the last check at or before half the run
            "phi_win": torch.zeros(B, self.est.n_phi, self.est.n_phi, dtype=f64, device=dev), "phi_n": 0,
            "z_win": torch.zeros(B, dtype=f64, device=dev), "y_win": torch.zeros(B, dtype=f64, device=dev),
            "n_win": 0,
            "y_all": torch.zeros(B, dtype=f64, device=dev), "n_all": 0,   # the data's scale
            "phi_sq": torch.zeros(B, self.est.n_phi, dtype=f64, device=dev), "samples": 0,
        }
        self.window_start = 0
        self.set_target(steps)

    def _theta(self) -> torch.Tensor:
        return self.est.theta.detach().to(torch.float64).clone()

    def _recent_phi(self, steps: int | None = None) -> tuple[torch.Tensor, int]:
        """sum of phi phi^T over the regressors of the last ``steps`` steps, each once (at most the d + nu
        steps the estimator keeps in its window; all of those by default), (B, n_phi, n_phi), and how many
        steps that is."""
        est = self.est
        W, k = est.win.shape[0], int(est.k)          # row t mod W holds the regressor of update t
        n = min(W, k, W if steps is None else steps)
        first, last = (k - n) % W, (k - 1) % W
        rows = [est.win[first:last + 1]] if first <= last else [est.win[first:], est.win[:last + 1]]
        gram = torch.zeros(est.win.shape[1], est.n_phi, est.n_phi, dtype=torch.float64, device=est.win.device)
        for part in rows if n else []:
            part = part.detach()
            g = kernels.window_gram(part, est.n_phi)
            if g is None:
                phi = part[:, :, :est.n_phi].to(torch.float64)                  # (w, B, n_phi)
                g = torch.einsum("wbi,wbj->bij", phi, phi)
            gram += g
        return gram, n

    def set_target(self, steps: int) -> None:
        """The run ends at ``steps``: the checks come every ``check_every(steps)`` steps and the window starts at
        the check step at or after steps - window * steps, so that a run extended to ``steps`` (a resume with
        more steps) checks from here on at the steps of a run made that long at once; a window already under
        way is kept, with its checks, when its start has passed."""
        every = check_every(steps)
        self.target = steps
        W = max(every, round(self.criteria.window * steps))
        start = every * math.ceil(max(steps - W, 0) / every)
        k = int(self.graph.k)
        if start > k or k == 0:
            self.every, self.window_start = every, start

    # --- along the run ------------------------------------------------------------------------------------
    def is_check(self, k: int) -> bool:
        """Whether step k is a check step: a multiple of ``every`` from the window's start on, of ``2 * every``
        before it (where the checks only watch the bounds)."""
        return k % self.every == 0 and (k >= self.window_start or k % (2 * self.every) == 0)

    def next_check(self, k: int) -> int:
        """The first check step after step k."""
        step = (k // self.every + 1) * self.every
        return step if self.is_check(step) else step + self.every

    def check(self, z_sq: torch.Tensor, y_sq: torch.Tensor | None, n: int) -> None:
        """At a check step (``is_check(graph.k)``): gather the sums of the last ``n`` steps, note
        the members the estimator froze, and freeze members that ran away or wound up."""
        s, k = self.state, int(self.graph.k)
        if y_sq is not None:
            s["y_all"] += y_sq
            s["n_all"] += n
        if k - n >= max(s["k_ref"], self.window_start):   # inside the window (earlier sums would be reset)
            s["z_win"] += z_sq
            if y_sq is not None:
                s["y_win"] += y_sq
            s["n_win"] += n
            phi, count = self._recent_phi(n)
            s["phi_win"] += phi
            s["phi_n"] += count
        if 2 * k <= self.target and k > s["k_mid"]:
            s.update(theta_mid=self._theta(), k_mid=k)
        if k == self.window_start and k > s["k_ref"]:
            s.update(theta_ref=self._theta(), k_ref=k, n_win=0, phi_n=0)
            for key in ("z_win", "y_win", "phi_win"):
                s[key].zero_()
        s["reason"] = self.reasons()
        self._freeze(self._bounds_exceeded(), k)
        s["phi_sq"] += self.est.phi_now.detach().to(torch.float64) ** 2
        s["samples"] += 1

    def _bounds_exceeded(self) -> torch.Tensor:
        """Reason codes (0: none) of alive members beyond the runaway or windup bounds (in one pass of the
        compiled kernel on the CPU, else in PyTorch)."""
        est, s, c = self.est, self.state, self.criteria
        f64 = torch.float64
        windup = c.windup * est.n_theta * est.p0.to(f64)
        if s["n_all"] and s["samples"]:       # phi's scale from the earlier checks: a jump of phi is u's
            u_scale = self.u_scale()
            bound = torch.where(u_scale > 0, c.runaway * u_scale, math.inf)
            phi_rms = torch.sqrt(s["phi_sq"] / s["samples"])
        else:
            bound, phi_rms = torch.full_like(s["z_win"], math.inf), torch.zeros_like(s["phi_sq"])
        code = kernels.health_bounds(est.P, est.theta, est.u_now, phi_rms, bound, windup, est.alive, _BOUND_REASONS)
        if code is not None:
            return code
        P = est.P.detach().to(f64)
        code = torch.where(_definite(P), 0, int(Reason.NOT_POSITIVE_DEFINITE))
        code = torch.where(P.diagonal(dim1=1, dim2=2).sum(-1) > windup, int(Reason.COVARIANCE_WINDUP), code)
        u_pot = (est.theta.detach().to(f64).abs() * phi_rms.unsqueeze(1)).sum(-1).amax(-1)
        u_now = est.u_now.detach().to(f64).abs().amax(-1)
        code = torch.where(u_now > bound, int(Reason.U_RUNAWAY), code)
        code = torch.where(u_pot > bound, int(Reason.THETA_RUNAWAY), code)
        return torch.where(est.alive, code, 0)

    def u_scale(self, y_sq: torch.Tensor | None = None, n: int = 0) -> torch.Tensor:
        """The data's scale of u per member, rms(y) / |beta| (0 before any measured output was seen), with
        ``y_sq``, the sum of y^2 over ``n`` steps since the last check, when given."""
        s = self.state
        y_all, n_all = (s["y_all"], s["n_all"]) if y_sq is None else (s["y_all"] + y_sq, s["n_all"] + n)
        y_rms = torch.sqrt(y_all / max(n_all, 1))
        return y_rms / self.est.beta.detach().to(torch.float64).flatten(1).norm(dim=1)

    def _freeze(self, code: torch.Tensor, k: int) -> None:
        new = code > 0
        if not bool(new.any()):
            return
        est = self.est
        est.alive.masked_fill_(new, False)
        est.diverged_at.masked_fill_(new, k)
        self.state["reason"] = torch.where(new, code, self.state["reason"])
        if hasattr(est, REASON_STATE):
            getattr(est, REASON_STATE).copy_(torch.where(new, code, getattr(est, REASON_STATE)))

    def reasons(self) -> torch.Tensor:
        """Reason codes per member: the recorded ones, and for members the estimator froze since, its own
        (``diverged_reason``) or one inferred from its state."""
        est, known = self.est, self.state["reason"]
        new = ~est.alive & (known == 0)
        if not bool(new.any()):
            return known
        if hasattr(est, REASON_STATE):
            return torch.where(new, getattr(est, REASON_STATE), known)

        def finite(t: torch.Tensor) -> torch.Tensor:
            return torch.isfinite(t.detach()).flatten(1).all(1)
        P = est.P.detach()
        code = torch.where(_definite(P), int(Reason.NON_FINITE), int(Reason.NOT_POSITIVE_DEFINITE))
        code = torch.where(finite(P), code, int(Reason.COVARIANCE_WINDUP))
        return torch.where(new, code, known)

    # --- the verdict ---------------------------------------------------------------------------------------
    def status(self, z_sq: torch.Tensor, y_sq: torch.Tensor | None, n: int) -> dict[str, torch.Tensor]:
        """Every member's verdict, with ``z_sq``, ``y_sq`` the sums over the ``n`` steps since the last check
        (nothing is changed). Returns (B,) tensors: ``status`` (index into STATUSES), ``reason`` (Reason),
        ``diverged_at`` (-1 when alive), ``theta_change``, ``z_ratio`` (NaN when there is no measured output)
        and ``z_rms`` (over the window)."""
        s, c = self.state, self.criteria
        z_win, y_win, phi_win = s["z_win"], s["y_win"], s["phi_win"]
        n_win, phi_n = s["n_win"], s["phi_n"]
        if n and int(self.graph.k) - n >= s["k_ref"]:
            z_win = z_win + z_sq
            y_win = y_win + (y_sq if y_sq is not None else 0.0)
            n_win += n
            phi, count = self._recent_phi(n)
            phi_win, phi_n = phi_win + phi, phi_n + count
        floor = 1e-3 * self.u_scale(y_sq, n) if s["n_all"] or y_sq is not None else None
        change = self._theta_change(phi_win, phi_n, floor)
        if y_sq is None and not s["n_all"]:
            ratio = torch.full_like(change, math.nan)
            settled = change <= c.theta_tol
        else:
            ratio = torch.where(y_win > 0, torch.sqrt(z_win / y_win), torch.where(z_win > 0, math.inf, math.nan))
            settled = (change <= c.theta_tol) & (ratio <= c.z_tol)
        alive = self.est.alive
        code = torch.where(alive, torch.where(settled, 0, 1), 2)
        return {"status": code, "reason": self.reasons(), "diverged_at": self.est.diverged_at.clone(),
                "theta_change": change, "z_ratio": ratio, "z_rms": torch.sqrt(z_win / max(n_win, 1))}

    def _theta_change(self, phi: torch.Tensor, count: int, floor: torch.Tensor | None) -> torch.Tensor:
        """theta's relative change over the window, measured on the window's regressors (the sum of their outer
        products ``phi`` over ``count`` steps; the estimator's last regressors when the window has none yet),
        relative to at least ``floor`` (None: no floor)."""
        s = self.state
        if not count:
            phi, count = self._recent_phi()
        phi = phi / max(count, 1)

        def sq(t: torch.Tensor) -> torch.Tensor:       # mean square of t phi(k), summed over u's entries
            return torch.einsum("bui,bij,buj->b", t, phi, t)
        theta, ref = self._theta(), s["theta_ref"]
        size = torch.maximum(sq(theta), sq(ref))
        if floor is not None:
            size = torch.maximum(size, torch.nan_to_num(floor ** 2, posinf=0.0))
        return torch.where(size > 0, torch.sqrt(sq(theta - ref) / size), 0.0)

    def report(self, verdict: dict[str, torch.Tensor]) -> dict[str, Any]:
        """The verdict for ``summary.json``: per-member lists (plain values for a batch of one), counts and
        the criteria."""
        code = verdict["status"].cpu().numpy()
        B = code.size
        reason = _REASON_LABELS[verdict["reason"].cpu().numpy()]
        step = np.full(B, None, dtype=object)           # the step where diverged, None where alive
        diverged = code == STATUSES.index("diverged")
        step[diverged] = verdict["diverged_at"].cpu().numpy()[diverged].tolist()
        counts = np.bincount(code, minlength=len(STATUSES)).tolist()

        def plain(values: np.ndarray | list) -> Any:
            values = values.tolist() if isinstance(values, np.ndarray) else values
            return values[0] if B == 1 else values

        def numbers(t: torch.Tensor) -> Any:
            return plain(finite_list(t))
        return {"counts": dict(zip(STATUSES, counts)), "status": plain(_STATUS_WORDS[code]),
                "reason": plain(reason), "diverged_at": plain(step),
                "theta_change": numbers(verdict["theta_change"]), "z_ratio": numbers(verdict["z_ratio"]),
                "criteria": dict(asdict(self.criteria), check_every=self.every,
                                 window_start=self.state["k_ref"])}

    @staticmethod
    def decide(status: torch.Tensor, z_ratio: torch.Tensor, z_tol: float, explained: torch.Tensor | None = None,
               determined: torch.Tensor | None = None, biased: torch.Tensor | None = None,
               worse: torch.Tensor | None = None, drifting: torch.Tensor | None = None,
               white: torch.Tensor | None = None, theta_ok: torch.Tensor | None = None) -> torch.Tensor:
        """Every member's final status (index into STATUSES) from the checks' ``status`` and what the end of the
        run found, each (B,) bool where given:

        * a member not converged only because theta still moved over the window, where that move is what its
          own random error explains (``explained``, ``rcotorch.verdict.intervals.change_explained``) and its
          z_ratio is within ``z_tol``, is converged; so is one whose theta settled (``theta_ok``: its
          theta_change within the tolerance, or ``explained``) and whose z_ratio is above ``z_tol`` only with
          residuals that are white (``white``: the model error is what the measurement noise leaves);
        * a converged member whose estimates still drift by more than their intervals (``drifting``) is not
          converged;
        * a converged member is ``undetermined`` where the data did not determine an estimate (``determined``
          false), else ``biased`` where an estimate carries a bias beyond its interval (``biased``);
        * a converged, undetermined or biased member whose refined model fits worse than the initial one
          (``worse``) is not converged."""
        code = {s: STATUSES.index(s) for s in STATUSES}
        if explained is not None:
            z_ok = z_ratio <= z_tol
            if white is not None:
                z_ok = z_ok | (white & torch.isfinite(z_ratio))
            moved_ok = explained if theta_ok is None else explained | theta_ok
            settled = (status == code["not_converged"]) & moved_ok & z_ok
            status = torch.where(settled, code["converged"], status)
        if drifting is not None:
            status = torch.where((status == code["converged"]) & drifting, code["not_converged"], status)
        converged = status == code["converged"]
        if determined is not None:
            status = torch.where(converged & ~determined, code["undetermined"], status)
        if biased is not None:
            status = torch.where((status == code["converged"]) & biased, code["biased"], status)
        if worse is not None:
            trusted = (status == code["converged"]) | (status == code["undetermined"]) | (status == code["biased"])
            status = torch.where(worse & trusted, code["not_converged"], status)
        return status

    # --- checkpoints --------------------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        return dict(self.state, every=self.every, window_start=self.window_start, criteria=asdict(self.criteria))

    def load_state_dict(self, state: dict[str, Any]) -> None:
        dev = self.est.theta.device
        self.every, self.window_start = int(state["every"]), int(state["window_start"])
        self.criteria = Criteria(**state["criteria"])
        for key in self.state:
            v = state[key]
            self.state[key] = v.to(dev) if isinstance(v, torch.Tensor) else int(v)
