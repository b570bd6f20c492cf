"""Analysis of an identified subsystem against a reference: frequency responses and their error."""

from __future__ import annotations

import numpy as np
import torch

from .rco import RCOEstimator


def white_noise_rms(system, std: float = 1.0) -> np.ndarray:
    """Steady-state rms of each output of a stable discrete python-control system driven by white noise of
    std ``std`` on every input (the discrete Lyapunov equation A X A^T - X + B B^T = 0): (outputs,)."""
    import scipy.linalg

    A, B, C, D = (np.atleast_2d(np.asarray(m, dtype=float)) for m in (system.A, system.B, system.C, system.D))
    if A.size:
        X = scipy.linalg.solve_discrete_lyapunov(A, B @ B.T)
        var = np.diag(C @ X @ C.T) + np.diag(D @ D.T)
    else:
        var = np.diag(D @ D.T)
    return std * np.sqrt(var)


def log_grid(dt: float, low: float = 1e-2, n: int = 400) -> np.ndarray:
    """Log-spaced frequencies from ``low`` rad/s to the Nyquist frequency pi/dt."""
    return np.logspace(np.log10(low), np.log10(np.pi / dt), n)


def reference_response(reference, omega, dt: float) -> np.ndarray:
    """Frequency response of a python-control system (discrete at z = exp(j w dt), or continuous at s = j w)
    as an array (F,) for SISO or (F, outputs, inputs)."""
    import control
    if isinstance(reference, (control.StateSpace, control.TransferFunction)):
        x = np.exp(1j * omega * dt) if reference.isdtime(strict=True) else 1j * omega
        resp = np.asarray(reference(x))
        return resp if resp.ndim == 1 else np.moveaxis(resp, -1, 0)
    raise TypeError(f"reference must be a python-control system, got {type(reference).__name__}")


def frequency_error(identified: RCOEstimator, reference, omega) -> torch.Tensor:
    """max over omega of |G_identified - G_ref| / |G_ref| for each member, (B,); SISO paths (n_u = n_sig = 1)
    or the full matrix with the spectral-norm ratio of the difference to the reference."""
    dt = identified.sample_time
    ident = identified.frequency_response(omega).cpu()                      # (B, F, n_u, n_sig)
    ref = torch.as_tensor(reference_response(reference, omega, dt))
    ref = ref.reshape(1, len(omega), *ident.shape[2:]).to(ident.dtype)
    diff = torch.linalg.matrix_norm(ident - ref, ord=2)
    return (diff / torch.linalg.matrix_norm(ref, ord=2)).amax(dim=1)
