"""A reduced 1-D thermosphere column in torch: the stand-in for GITM in the seed paper's Section VII.

One vertical column, 100-600 km, batch-first like every rcotorch block. The state is the neutral temperature
T(z), the nitric-oxide density n_NO(z) and a clock; everything else follows from them:

* **Composition and mass density** (diagnostic): O, O2 and N2 in diffusive equilibrium above a fixed lower
  boundary, each with its own scale height, integrated hydrostatically from T(z) (trapezoid rule):

      n_i(z) = n_i(z0) T(z0)/T(z) exp(-int_z0^z m_i g(z') / (k T(z')) dz'),   g(z) = g0 (R/(R+z))^2,
      rho(z) = sum_i m_i n_i(z).

* **Energy equation** on the fixed altitude grid (conservative finite volumes, T fixed at the lower boundary,
  zero heat flux at the top, backward Euler with kappa and rho c_p lagged, sources explicit; unconditionally
  stable, so the physics substep is limited by accuracy only):

      rho c_p dT/dt = d/dz(kappa(T) dT/dz) + Q_sun + Q_storm - Q_NO - Q_u,     kappa = A T^s,

  rho c_p = k (5/2 n_O + 7/2 (n_O2 + n_N2)) (ideal monatomic and diatomic gases). Q_u is the cooling an
  identified subsystem supplies: values at a few node altitudes (input ``u``, nW/m^3), linearly interpolated in
  between and tapered linearly to zero one node spacing below the lowest and above the highest node.
* **Solar heating** Q_sun: one Chapman layer per wavelength band, absorbed along a fixed effective path,
  band fluxes linear in the solar-activity index F10.7, with a diurnal cycle (see ``DIURNAL_AMPLITUDE``):

      Q_b(z, t) = eta_b F_b(F10.7) I(t) sum_i sigma_bi n_i(z) exp(-tau_b(z) / mu),
      tau_b(z) = sum_i sigma_bi N_i(z),   N_i(z) = int_z^inf n_i dz'   (above the top: n_i H_i).

* **Storm**: auroral Joule and particle heating, a column power S(t) [mW/m^2] deposited with a fixed Gaussian
  altitude profile; a share of it ionizes and makes NO.
* **Nitric oxide**, a *dynamic* minor species: dn_NO/dt = P_NO - n_NO / tau_NO(z), P_NO an effective yield
  times the ion-pair production (photons absorbed by N2 in every band, plus the storm's particles), advanced
  exactly over each substep with the sources held.
* **NO 5.3 um cooling** (Kockarts 1980): NO(v=1) excited by collisions with O, emitting at A10,

      Q_NO = h nu A10 n_NO k_O n_O exp(-h nu / k T) / (k_O n_O + A10),     h nu / k = 2699 K,

  proportional to n_NO n_O exp(-2700/T) where k_O n_O << A10 (the factor A10 / (A10 + k_O n_O) is 0.8 at 120 km,
  0.93 at 150 km).

The *truth* column has Q_NO (``no_cooling=True``); the *initial model* has not, and RCMR supplies Q_u.

Left out (and why it is fine here): vertical winds and the work of the expanding column, horizontal transport
(replaced by the damped diurnal cycle), eddy mixing (the turbopause is put at the lower boundary), thermal
diffusion, He and H (a few per cent of the mass at 400 km), CO2 and O 63 um cooling (the lower boundary is
the heat sink), NO transport.

Every constant names its source. Where a source gives a range or a spectrum and the column needs one
effective number, the value is marked *effective* and was chosen inside the published range so that the truth
column's climatology is typical: for F10.7 = 150 and no storm, T(120 km) about 430 K, exospheric temperature
900-1070 K over the day, 1.6-2.7e-12 kg/m^3 at 407 km, NO cooling about 0.15 mW/m^2 (a quarter of the
solar heating) peaking near 130 km, n_NO peaking near 120 km at about 1.4e13 m^-3 (SNOE saw up to ~1e14).
"""

from __future__ import annotations

import importlib.util
import math
import os
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from ..blocks.base import DEFAULT_DTYPE, Block
from ..blocks.nonlinear import Nonlinear
from ..engine import kernels
from ..errors import ConfigError
from .thermosphere_constants import (  # noqa: F401  (the column's constants, also read from here)
    AMU,
    BANDS,
    C_LIGHT,
    CP_PER_PARTICLE,
    DIURNAL_AMPLITUDE,
    EV,
    G0,
    H_PLANCK,
    K_B,
    KAPPA_A,
    KAPPA_S,
    MASS,
    MU_PATH,
    N_100KM,
    NO_A10,
    NO_HNU,
    NO_K_O,
    NO_LIFETIME,
    NO_LOSS_H,
    NO_LOSS_Z,
    NO_THETA,
    NO_UNIT,
    NO_WAVENUMBER,
    NO_YIELD,
    PEAK_LOCAL_TIME,
    R_EARTH,
    SPECIES,
    STORM_PARTICLE_SHARE,
    T_100KM,
    W_ION,
    Band,
)

#: How a column fills its identified cooling in between the nodes (``Column(interpolate=...)``).
INTERPOLATIONS = ("cooling", "strength")
#: Below this many state entries (batch x levels) the column runs on one intra-op thread (see ``few_threads``).
SINGLE_THREAD_BELOW = 65536


@contextmanager
def few_threads(entries: int) -> Iterator[None]:
    """Run small column workloads on one intra-op thread: with ~100 levels there is nothing to parallelize, and
    waking further threads for each small operation costs more than the operation itself, most of all on a
    shared machine. The previous thread count is restored on exit."""
    threads = torch.get_num_threads()
    if threads == 1 or entries >= SINGLE_THREAD_BELOW:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


class Column(nn.Module):
    """The reduced thermosphere column: grid, composition, sources and the model step (module docstring).

    The state x (B, 2n + 1) is [T (K, n levels) | n_NO / 1e12 m^-3 (n) | t (hours since the start)]; the driver
    w (B, 2) is [F10.7 (sfu), storm power S (mW/m^2)]; u (B, nodes) the identified cooling at ``cooling_nodes``
    [nW/m^3]. Constants live in non-persistent buffers, so ``.to()`` moves them and checkpoints leave them out.

    Args:
        z_bottom, z_top, dz: the altitude grid [m].
        n_bottom, T_bottom: O, O2, N2 densities [m^-3] and temperature [K] at the lower boundary.
        no_cooling: include the NO 5.3 um cooling (the truth) or not (the initial model).
        cooling_nodes: altitudes [m] of the identified cooling; empty for a column without input ``u``.
        interpolate: how the node coolings u fill the column between the nodes (``identified_cooling``):
            ``'cooling'``, linearly; ``'strength'``, in proportion to the column's own Kockarts rate, linearly in
            the strength u_j / rate(z_j) (a cooling of the Kockarts form whose strength varies with altitude).
        latitude: of the column [deg] (equinox).
        local_time0: local solar time at t = 0 [h].
        dt: sample time [s], ``substeps`` backward-Euler substeps per sample.
        storm_altitude, storm_width: centre and standard deviation [m] of the storm's energy deposition.
        radius: Earth radius of g(z) [m].
    """

    def __init__(self, z_bottom: float = 100e3, z_top: float = 600e3, dz: float = 5e3,
                 n_bottom: Sequence[float] = N_100KM, T_bottom: float = T_100KM, no_cooling: bool = True,
                 cooling_nodes: Sequence[float] = (), interpolate: str = "cooling", latitude: float = 30.0,
                 local_time0: float = 0.0,
                 dt: float = 900.0, substeps: int = 2, storm_altitude: float = 125e3, storm_width: float = 20e3,
                 radius: float = R_EARTH, bands: Sequence[Band] = BANDS, dtype=DEFAULT_DTYPE):
        super().__init__()
        n = int(round((z_top - z_bottom) / dz)) + 1
        if n < 4 or abs(z_bottom + (n - 1) * dz - z_top) > 1e-6 * dz:
            raise ConfigError(f"thermosphere column: z_top - z_bottom = {z_top - z_bottom} m must be a multiple of "
                              f"dz = {dz} m, with at least 4 levels")
        if substeps < 1 or dt <= 0:
            raise ConfigError(f"thermosphere column: need dt > 0 and substeps >= 1, got {dt}, {substeps}")
        if interpolate not in INTERPOLATIONS:
            raise ConfigError(f"thermosphere column: interpolate must be one of {INTERPOLATIONS}, got {interpolate!r}")
        self.n, self.dz, self.dt, self.substeps = n, float(dz), float(dt), int(substeps)
        self.interpolate = interpolate
        self.T_bottom, self.no_cooling = float(T_bottom), bool(no_cooling)
        self.insolation_mean = math.cos(math.radians(latitude)) / math.pi
        self.local_time0 = float(local_time0)
        self.bands = tuple(bands)
        self.n_nodes = len(cooling_nodes)
        z = z_bottom + dz * torch.arange(n, dtype=dtype)
        storm = torch.exp(-0.5 * ((z - storm_altitude) / storm_width) ** 2)
        nodes = torch.as_tensor([float(a) for a in cooling_nodes], dtype=dtype)
        constants = {
            "z": z,
            "g": G0 * (radius / (radius + z)) ** 2,
            "mass": torch.tensor(MASS, dtype=dtype).reshape(1, 3, 1),
            "cp": torch.tensor(CP_PER_PARTICLE, dtype=dtype).reshape(1, 3, 1) * K_B,
            "log_n_bottom": torch.log(torch.tensor(n_bottom, dtype=dtype)).reshape(1, 3, 1),
            "sigma": torch.tensor([b.sigma for b in self.bands], dtype=dtype).reshape(1, -1, 3, 1),
            "efficiency": torch.tensor([b.efficiency for b in self.bands], dtype=dtype).reshape(1, -1, 1),
            "band_flux": torch.tensor([b.flux for b in self.bands], dtype=dtype),
            "band_per_sfu": torch.tensor([b.per_sfu for b in self.bands], dtype=dtype),
            "storm_profile": storm / (storm.sum() * dz),        # [1/m]: integrates to 1 on the grid
            "no_loss": (1.0 + torch.exp((z - NO_LOSS_Z) / NO_LOSS_H)) / NO_LIFETIME,   # 1/tau_NO [1/s]
            "nodes": nodes,
            "cooling_basis": interpolation_basis(z, nodes) if self.n_nodes else torch.zeros(0, n, dtype=dtype),
        }
        for key, value in constants.items():
            self.register_buffer(key, value, persistent=False)

    # --- layout --------------------------------------------------------------------------------------------
    @property
    def n_states(self) -> int:
        return 2 * self.n + 1

    def split(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """T (B, n) [K], n_NO (B, n) [m^-3], t (B, 1) [h] of a state x."""
        return x[:, : self.n], x[:, self.n: 2 * self.n] * NO_UNIT, x[:, 2 * self.n:]

    # --- composition ---------------------------------------------------------------------------------------
    def densities(self, T: torch.Tensor) -> torch.Tensor:
        """O, O2, N2 number densities (B, 3, n) [m^-3] in diffusive equilibrium at temperature T (B, n)."""
        f = (self.g / T).unsqueeze(1)                                              # (B, 1, n)
        steps = 0.5 * self.dz * (f[..., 1:] + f[..., :-1])
        integral = torch.cat([torch.zeros_like(f[..., :1]), torch.cumsum(steps, -1)], -1)
        return torch.exp(self.log_n_bottom + torch.log(T[:, :1] / T).unsqueeze(1) - self.mass / K_B * integral)

    def mass_density(self, T: torch.Tensor) -> torch.Tensor:
        """Mass density (B, n) [kg/m^3]."""
        return (self.mass * self.densities(T)).sum(1)

    def column_above(self, n: torch.Tensor, T: torch.Tensor) -> torch.Tensor:
        """Column densities N_i(z) = int_z^inf n_i dz' (B, 3, n) [m^-2]; above the top, n_i times its scale height."""
        top = n[..., -1:] * K_B * T[:, None, -1:] / (self.mass * self.g[-1])
        steps = 0.5 * self.dz * (n[..., 1:] + n[..., :-1])
        above = torch.flip(torch.cumsum(torch.flip(steps, [-1]), -1), [-1])
        return torch.cat([above, torch.zeros_like(top)], -1) + top

    # --- sources -------------------------------------------------------------------------------------------
    def insolation(self, t_hours: torch.Tensor) -> torch.Tensor:
        """Share I(t) (B, 1) of the overhead-sun flux reaching the column at time t [h] (see DIURNAL_AMPLITUDE)."""
        phase = (self.local_time0 + t_hours - PEAK_LOCAL_TIME) * (math.pi / 12.0)
        return self.insolation_mean * (1.0 + DIURNAL_AMPLITUDE * torch.cos(phase))

    def solar(self, n: torch.Tensor, T: torch.Tensor, t_hours: torch.Tensor, f107: torch.Tensor
              ) -> tuple[torch.Tensor, torch.Tensor]:
        """Neutral heating (B, n) [W/m^3] and the ion pairs made in N2 (B, n) [1/(m^3 s)] by the sun."""
        tau = (self.sigma * self.column_above(n, T).unsqueeze(1)).sum(2)           # (B, bands, n)
        flux = (self.band_flux * (1.0 + self.band_per_sfu * (f107 - 150.0))).clamp(min=0.0)   # (B, bands)
        flux = (flux * self.insolation(t_hours)).unsqueeze(-1) * torch.exp(-tau / MU_PATH)   # (B, bands, n)
        absorbed = self.sigma * n.unsqueeze(1)                                     # (B, bands, 3, n) [1/m]
        heating = (self.efficiency * flux * absorbed.sum(2)).sum(1)
        return heating, (flux * absorbed[:, :, 2]).sum(1) / W_ION

    def no_cooling_rate(self, T: torch.Tensor, n_O: torch.Tensor, n_NO: torch.Tensor) -> torch.Tensor:
        """Kockarts (1980) NO 5.3 um cooling [W/m^3]."""
        collisions = NO_K_O * n_O
        return NO_HNU * NO_A10 * n_NO * collisions * torch.exp(-NO_THETA / T) / (collisions + NO_A10)

    def identified_cooling(self, u: torch.Tensor, rate: torch.Tensor | None = None) -> torch.Tensor:
        """The cooling profile (B, n) [W/m^3] of node values u (B, nodes) [nW/m^3]: interpolated linearly between
        the nodes, or with ``interpolate='strength'`` rate(z) sum_j (u_j / rate(z_j)) hat_j(z), ``rate`` (B, n) the
        column's Kockarts rate (any unit): the profile has the rate's shape and the value u_j at node j."""
        if self.interpolate == "cooling":
            return 1e-9 * u @ self.cooling_basis
        if rate is None:
            raise ConfigError("thermosphere column: interpolate='strength' needs the Kockarts rate profile")
        at_nodes = self.at_nodes(rate).clamp(min=torch.finfo(rate.dtype).tiny)
        return 1e-9 * rate * ((u / at_nodes) @ self.cooling_basis)

    def tendencies(self, x: torch.Tensor, w: torch.Tensor, u: torch.Tensor | None = None) -> dict:
        """Diagnostics of state x under driver w and identified cooling u: T, densities n (B, 3, n), n_NO, t,
        heat capacity rho c_p, heating, NO cooling (computed even where the column leaves it out), the total
        cooling applied, NO production."""
        T, n_no, t = self.split(x)
        n = self.densities(T)
        heating, ions = self.solar(n, T, t, w[:, :1])
        storm = 1e-3 * w[:, 1:2] * self.storm_profile                             # [W/m^3]
        no = self.no_cooling_rate(T, n[:, 0], n_no)
        cooling = no if self.no_cooling else torch.zeros_like(no)
        if u is not None and self.n_nodes:
            cooling = cooling + self.identified_cooling(u, no)
        return {"T": T, "n": n, "n_NO": n_no, "t": t, "heat_capacity": (self.cp * n).sum(1),
                "heating": heating + storm, "no_cooling": no, "cooling": cooling,
                "no_production": NO_YIELD * (ions + STORM_PARTICLE_SHARE * storm / W_ION)}

    # --- the step ------------------------------------------------------------------------------------------
    def conduct(self, T: torch.Tensor, C: torch.Tensor, Q: torch.Tensor, dt: float) -> torch.Tensor:
        """One backward-Euler step of C dT/dt = d/dz(kappa(T) dT/dz) + Q with kappa and C lagged, T fixed at the
        bottom and zero flux at the top (mirror level): the new T (B, n)."""
        k = KAPPA_A * (0.5 * (T[:, 1:] + T[:, :-1])) ** KAPPA_S * (dt / self.dz ** 2)   # face conductances
        zero = torch.zeros_like(T[:, :1])
        below = torch.cat([zero, k[:, :-1], 2.0 * k[:, -1:]], 1)       # coupling of level i to i-1 (mirror at top)
        above = torch.cat([zero, k[:, 1:], zero], 1)                   # to i+1; the bottom row is T_0 = T_bottom
        diag = torch.cat([torch.ones_like(zero), C[:, 1:] + below[:, 1:] + above[:, 1:]], 1)
        A = torch.diag_embed(diag) - torch.diag_embed(above[:, :-1], 1) - torch.diag_embed(below[:, 1:], -1)
        rhs = torch.cat([zero + self.T_bottom, C[:, 1:] * T[:, 1:] + dt * Q[:, 1:]], 1)
        return torch.linalg.solve(A, rhs.unsqueeze(-1)).squeeze(-1)

    def step(self, x: torch.Tensor, w: torch.Tensor, u: torch.Tensor | None = None) -> torch.Tensor:
        """x(k) -> x(k+1): ``substeps`` backward-Euler substeps with w and u held."""
        h = self.dt / self.substeps
        decay = torch.exp(-h * self.no_loss)
        for _ in range(self.substeps):
            d = self.tendencies(x, w, u)
            T = self.conduct(d["T"], d["heat_capacity"], d["heating"] - d["cooling"], h)
            equilibrium = d["no_production"] / self.no_loss
            n_no = equilibrium + (d["n_NO"] - equilibrium) * decay
            x = torch.cat([T, n_no / NO_UNIT, d["t"] + h / 3600.0], 1)
        return x

    # --- observation ---------------------------------------------------------------------------------------
    def bracket(self, altitude: float) -> tuple[int, float]:
        """The level i at or below ``altitude`` [m] (within the grid's last interval at most) and the weight a of
        level i + 1 in the linear interpolation at it."""
        i = min(max(int((altitude - float(self.z[0])) // self.dz), 0), self.n - 2)
        return i, (altitude - float(self.z[i])) / self.dz

    def at(self, profile: torch.Tensor, altitude: float, log: bool = False) -> torch.Tensor:
        """A profile (B, n) at ``altitude`` [m] by linear (``log``: log-linear) interpolation: (B, 1)."""
        i, a = self.bracket(altitude)
        p = torch.log(profile[:, i: i + 2]) if log else profile[:, i: i + 2]
        v = (1 - a) * p[:, :1] + a * p[:, 1:]
        return torch.exp(v) if log else v

    def at_nodes(self, profile: torch.Tensor) -> torch.Tensor:
        """A profile (B, n) at the cooling nodes by linear interpolation: (B, nodes)."""
        return torch.cat([self.at(profile, float(a)) for a in self.nodes], 1)

    def density_at(self, x: torch.Tensor, altitude: float) -> torch.Tensor:
        """Mass density at ``altitude`` in units of 1e-12 kg/m^3, (B, 1)."""
        return 1e12 * self.at(self.mass_density(x[:, : self.n]), altitude, log=True)

    def no_cooling_profile(self, x: torch.Tensor) -> torch.Tensor:
        """The Kockarts NO cooling (B, n) of state x [nW/m^3] (whether or not the column applies it)."""
        T, n_no, _ = self.split(x)
        return 1e9 * self.no_cooling_rate(T, self.densities(T)[:, 0], n_no)

    def no_cooling_at_nodes(self, x: torch.Tensor) -> torch.Tensor:
        """The Kockarts NO cooling of state x at the cooling nodes, (B, nodes) [nW/m^3]: the basis regressors of a
        structured identified subsystem u_j = theta_j y0_j."""
        return self.at_nodes(self.no_cooling_profile(x))

    def temperature_at_nodes(self, x: torch.Tensor) -> torch.Tensor:
        """The temperature of state x at the cooling nodes, (B, nodes) [K]: what a temperature-only identified
        subsystem sees (nothing of the composition, the NO density or the cooling law)."""
        return self.at_nodes(x[:, : self.n])

    def initial_state(self, batch: int = 1) -> torch.Tensor:
        """A start for a spin-up (batch, 2n + 1): a Bates profile (T_inf = 1000 K, shape 0.02 /km), no NO, t = 0."""
        T = bates_profile(self.z, 1000.0, self.T_bottom, 0.02e-3).unsqueeze(0).expand(batch, -1)
        return torch.cat([T, torch.zeros_like(T), torch.zeros_like(T[:, :1])], 1)

    def spin_up(self, f107, days: float = 3.0, batch: int = 1) -> torch.Tensor:
        """The state after ``days`` of quiet conditions (no storm, F10.7 = ``f107``, scalar or (batch,)) from
        ``initial_state``, with the clock set back to 0 (whole days keep the local time)."""
        f107 = torch.as_tensor(f107, dtype=self.z.dtype, device=self.z.device).reshape(-1, 1)
        batch = max(batch, f107.shape[0])
        w = torch.cat([f107.expand(batch, 1), torch.zeros(batch, 1, dtype=f107.dtype, device=f107.device)], 1)
        x = self.initial_state(batch)
        u = torch.zeros(batch, self.n_nodes, dtype=x.dtype, device=x.device)
        with torch.no_grad(), few_threads(x.numel()):
            for _ in range(int(round(days * 86400.0 / self.dt))):
                x = self.step(x, w, u)
        return torch.cat([x[:, :-1], torch.zeros_like(x[:, -1:])], 1)


def native_here(dtype: torch.dtype, device) -> bool:
    """Whether the column's native code (``thermosphere_native``) may run: float64 on the CPU, numba installed,
    the compiled engine allowed here (not inside ``kernels.disabled()``, which the PyTorch engine's steps run in)
    and not turned off for the process (``RCOTORCH_ENGINE=torch``)."""
    return dtype == torch.float64 and torch.device(device).type == "cpu" and kernels.allowed() and \
        os.environ.get("RCOTORCH_ENGINE", "auto") != "torch" and importlib.util.find_spec("numba") is not None


class Observation:
    """A quantity of a column's state for ``ColumnBlock``'s outputs and records, (B, width):

    * ``'density'``: the mass density at ``altitudes`` [1e-12 kg/m^3] (``Column.density_at``);
    * ``'temperature_at_nodes'`` [K], ``'no_cooling_at_nodes'`` [nW/m^3] and ``'no_cooling_profile'`` [nW/m^3,
      every level]: the ``Column`` methods of these names.

    Called with a state x (B, 2n + 1) it is the torch column's; ``reads`` describes it to the native engine
    (``thermosphere_native.observe``), which computes the same."""

    KINDS = ("density", "temperature_at_nodes", "no_cooling_at_nodes", "no_cooling_profile")

    def __init__(self, column: Column, kind: str, altitudes: Sequence[float] = ()):
        if kind not in self.KINDS:
            raise ConfigError(f"observation: kind must be one of {self.KINDS}, got {kind!r}")
        if (kind == "density") != bool(altitudes):
            raise ConfigError("observation: give altitudes for 'density' and only for it")
        self.column, self.kind, self.altitudes = column, kind, tuple(float(a) for a in altitudes)

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        if self.kind == "density":
            return torch.cat([self.column.density_at(x, a) for a in self.altitudes], 1)
        return getattr(self.column, self.kind)(x)

    @property
    def width(self) -> int:
        c = self.column
        return {"density": len(self.altitudes), "no_cooling_profile": c.n}.get(self.kind, c.n_nodes)

    def reads(self):
        """The rows (profile, level, weight, mode, scale) of ``thermosphere_native.READ_FIELDS``, (width, 5)."""
        from . import thermosphere_native as tn
        c = self.column
        if self.kind == "no_cooling_profile":
            rows = [(tn.NO_COOLING, j, 0.0, tn.LEVEL, 1.0) for j in range(c.n)]
        elif self.kind == "density":
            rows = [(tn.MASS_DENSITY, *c.bracket(a), tn.LOG, 1e12) for a in self.altitudes]
        else:
            profile = tn.TEMPERATURE if self.kind == "temperature_at_nodes" else tn.NO_COOLING
            rows = [(profile, *c.bracket(float(a)), tn.LINEAR, 1.0) for a in c.nodes]
        return np.array(rows, dtype=np.float64).reshape(-1, len(tn.READ_FIELDS))


class Record:
    """What a ``ColumnBlock`` appends to its ``history`` at every step: ``Observation``s of the state and input
    ports (by name), side by side, e.g. ``Record(Observation(col, 'density', [407e3]), 'u', 'w')``. Called as
    ``record(x, inputs)``, as a record function is."""

    def __init__(self, *parts: Observation | str):
        if not parts or not all(isinstance(p, (Observation, str)) for p in parts):
            raise ConfigError("record: give observations and input port names")
        self.parts = parts

    def __call__(self, x: torch.Tensor, inputs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        return torch.cat([p(x) if isinstance(p, Observation) else inputs[p] for p in self.parts], 1)


#: Steps the native engine runs between moves of a ``ColumnBlock``'s recorded rows into its history.
RECORD_RING = 32


class ColumnBlock(Nonlinear):
    """A ``Column`` as a nonlinear block: inputs ``w`` (width 2) and, with cooling nodes, ``u``; outputs given
    as functions of the state.

    ``markov`` is ``Nonlinear.markov`` (all input directions at once; 'autograd' by double-backward products,
    the fastest of torch's forward-mode products for this model of many elementwise operations (docs/engine.md),
    or 'fd' central differences) on one intra-op thread. ``record`` (a function of
    the state and the inputs, (B, m)) is appended to the buffer ``history`` (B, steps, m) at every step, so a
    checkpoint holds the traces.

    The native form (``lower``, with ``thermosphere_native``) needs the outputs given as ``Observation``s and the
    record as a ``Record``; the engine writes the rows of the last steps into ``pending`` (RECORD_RING, B, m),
    which move to ``history`` before each call of the engine and whenever ``history`` is read. Where the native
    code may run (``native_here``), ``markov`` computes the same Markov parameters with it: by the tangent of
    the step written out for 'autograd', by the same differences for 'fd'.

    Args:
        column: the physics.
        outputs: port name -> function of the state x (B, 2n + 1) returning (B, width), in port order.
        x0: the initial state (2n + 1,) or (B, 2n + 1).
    """

    def __init__(self, column: Column, outputs: Mapping[str, Callable[[torch.Tensor], torch.Tensor]], x0=None,
                 name: str = "column", record: Callable[[torch.Tensor, Mapping], torch.Tensor] | None = None,
                 dtype=DEFAULT_DTYPE):
        inputs = {"w": 2, **({"u": column.n_nodes} if column.n_nodes else {})}
        x0 = column.initial_state() if x0 is None else x0
        probe = torch.as_tensor(x0, dtype=dtype, device="cpu").reshape(-1, column.n_states)[:1]
        widths = {p: int(fn(probe).shape[1]) for p, fn in outputs.items()}
        fns = list(outputs.values())
        super().__init__(lambda x, s: column.step(x, s["w"], s.get("u")),
                         lambda x: torch.cat([fn(x) for fn in fns], 1), column.n_states, inputs, widths,
                         dt=column.dt, x0=x0, name=name, dtype=dtype)
        self.column, self.record, self.observations = column, record, dict(outputs)
        zeros = {p: probe.new_zeros(1, w) for p, w in inputs.items()}
        self.record_width = 0 if record is None else int(record(probe, zeros).shape[1])
        self.register_buffer("history", torch.zeros(0, 0, 0, dtype=dtype))
        self.register_buffer("pending", torch.zeros(0, 0, 0, dtype=dtype), persistent=False)
        self.register_buffer("k", torch.zeros((), dtype=torch.int64))

    def reset(self, batch_size: int) -> None:
        super().reset(batch_size)
        self.k = torch.zeros((), dtype=torch.int64, device=self.x.device)
        self.history = self.x.new_zeros(batch_size, 0, 0)
        self.pending = self.x.new_zeros(RECORD_RING, batch_size, self.record_width)

    def __getattr__(self, name: str):
        if name == "history":            # with the rows the native engine left in ``pending``
            self._flush()
        return super().__getattr__(name)

    def _flush(self) -> None:
        """Move the rows of the steps the native engine ran since the last move from ``pending`` to ``history``
        (the history has one row per step: k rows)."""
        history, pending, k = (self._buffers.get(key) for key in ("history", "pending", "k"))
        if history is None or pending is None or k is None or pending.device.type != "cpu":   # none pending
            return
        new = int(k) - history.shape[1]
        if new > 0 and pending.shape[2]:
            rows = pending[pending.shape[0] - new:].transpose(0, 1)
            self._buffers["history"] = rows.clone() if history.shape[1] == 0 else torch.cat([history, rows], 1)

    def _room(self) -> int:
        """Before each call of the native engine: the pending rows move to the history, and the ring takes
        RECORD_RING more steps."""
        self._flush()
        return RECORD_RING

    def _save_to_state_dict(self, destination, prefix, keep_vars):
        self._flush()
        super()._save_to_state_dict(destination, prefix, keep_vars)

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        key = prefix + "history"
        if key in state_dict:        # the trace grows with the run: take the checkpoint's length
            self.history = torch.empty_like(state_dict[key], device=self.x.device, dtype=self.x.dtype)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def output(self, port, inputs):
        with few_threads(self.x.numel()):
            return super().output(port, inputs)

    def update(self, inputs):
        with few_threads(self.x.numel()):
            if self.record is not None:
                row = self.record(self.x, inputs).detach().unsqueeze(1)
                history = self.history
                self.history = row if history.shape[1] == 0 else torch.cat([history, row], 1)
            super().update(inputs)
            self.k += 1

    def lower(self, b) -> None:
        """The native form: outputs, record and step as calls of ``thermosphere_native``'s entry points, each
        with the column's packed constants in its first input slots."""
        if not all(isinstance(o, Observation) and o.column is self.column for o in self.observations.values()):
            b.refuse("its outputs are Python functions; give thermosphere.Observation's of its column")
        if self.record is not None and not (isinstance(self.record, Record) and all(
                p.column is self.column for p in self.record.parts if isinstance(p, Observation))):
            b.refuse("its record is a Python function; give a thermosphere.Record")
        if importlib.util.find_spec("numba") is None:
            b.refuse("numba is not installed (pip install numba)")
        from . import thermosphere_native as tn
        packed = tn.pack(self.column)
        params, size, n = b.param(torch.from_numpy(packed).reshape(1, -1)), packed.size, self.n_states
        x = b.state("x")

        def observe(obs: Observation, out: int, port: str | None) -> None:
            reads = obs.reads()
            table = torch.from_numpy(reads).reshape(1, -1)
            count = table.shape[1] + 1
            block = b.scratch(size + count + n)
            b.emit("COPY", WIDTH=size, IN=params, OUT=block, port=port)
            b.emit("COPY", WIDTH=count, IN=b.param(torch.cat([table.new_full((1, 1), len(reads)), table], 1)),
                   OUT=block + size, port=port)
            b.emit("COPY", WIDTH=n, IN=x, OUT=block + size + count, port=port)
            fn = tn.entry("observe")
            b.emit("CALL", NIN=size + count + n, IN=block, NOUT=len(reads), OUT=out,
                   FUNCTION=b.function(fn.address, fn), port=port)

        for port, obs in self.observations.items():
            observe(obs, b.output(port), port)
        if self.record is not None:            # the ring moves up one row; the newest row is the last
            m = self.record_width
            ring = b.state("pending", rows=RECORD_RING)
            b.emit("COPY", WIDTH=(RECORD_RING - 1) * m, IN=ring + m, OUT=ring)
            at = ring + (RECORD_RING - 1) * m
            for part in self.record.parts:
                if isinstance(part, Observation):
                    observe(part, at, None)
                    at += part.width
                elif part in self.inputs and b.input(part) is not None:
                    b.emit("COPY", WIDTH=self.inputs[part], IN=b.input(part), OUT=at)
                    at += self.inputs[part]
                else:
                    b.refuse(f"its record reads '{part}', which is not a connected input")
            b.steps_left(self._room)
            b.unread("history")                # the pending rows move there on the Python side
        block = b.scratch(size + n + sum(self.inputs.values()))
        b.emit("COPY", WIDTH=size, IN=params, OUT=block)
        b.emit("COPY", WIDTH=n, IN=x, OUT=block + size)
        at = block + size + n
        for port, width in self.inputs.items():
            if b.input(port) is None:
                b.refuse(f"input '{port}' is not connected")
            b.emit("COPY", WIDTH=width, IN=b.input(port), OUT=at)
            at += width
        fn = tn.entry("step")
        b.emit("CALL", NIN=at - block, IN=block, NOUT=n, OUT=x, FUNCTION=b.function(fn.address, fn))
        b.counter()

    def markov(self, input: str, output: str, n: int, x: torch.Tensor | None = None,
               inputs: Mapping[str, torch.Tensor] | None = None, method: str = "auto",
               along: str = "trajectory", eps: float = 1e-6, compiled: bool = False) -> torch.Tensor:
        """``Nonlinear.markov``: by the column's own native code where it may run (``native_here``) and the output
        is an ``Observation``, else with torch on one intra-op thread for small columns (see ``few_threads``);
        ``compiled`` changes nothing (the column is not compiled from its Python functions)."""
        obs = self.observations.get(output)
        if isinstance(obs, Observation) and input in self.inputs and method in ("auto", "autograd", "fd") and \
                along in ("trajectory", "point") and native_here(self.x0.dtype, self.x0.device):
            from . import thermosphere_native as tn
            x = ((self.x if self.x.shape[0] else self.x0) if x is None else x).detach()
            B = x.shape[0]
            ins = {p: x.new_zeros(B, w) for p, w in self.inputs.items()}
            ins.update({p: v.detach().to(x).expand(B, -1) for p, v in dict(inputs or {}).items()})
            u = ins.get("u", x.new_zeros(B, 0))
            H = tn.NativeColumn(self.column).markov(obs.reads(), x, ins["w"], u, input, n, along, method, eps)
            return H.to(x)
        with few_threads(self.x.numel() * self.inputs.get("u", 1)):
            return super().markov(input, output, n, x, inputs, method, along, eps)


class SpaceWeather(Block):
    """The driver w = [F10.7 (sfu), storm power S (mW/m^2)], one row per member, a deterministic source:
    F10.7 constant, S(t) = peak s e^(1 - s) for s = (t - start) / rise >= 0 (a pulse peaking ``rise`` hours after
    ``start`` and decaying with e-folding time ``rise``), else 0. ``f107`` and ``peak`` may be per member."""

    def __init__(self, dt: float, f107=150.0, peak=4.0, start: float = 48.0, rise: float = 6.0,
                 name: str = "excitation", dtype=DEFAULT_DTYPE):
        super().__init__(name, {}, {"out": 2})
        if rise <= 0 or dt <= 0:
            raise ConfigError(f"block '{name}': dt and the storm's rise time must be positive")
        self.dt, self.start, self.rise = float(dt), float(start), float(rise)
        self.register_buffer("f107", torch.as_tensor(f107, dtype=dtype, device="cpu").reshape(-1, 1))
        self.register_buffer("peak", torch.as_tensor(peak, dtype=dtype, device="cpu").reshape(-1, 1))
        self.register_buffer("k", torch.zeros((), dtype=torch.int64))

    def reset(self, batch_size: int) -> None:
        super().reset(batch_size)
        self.check_batch(self.f107, "f107")
        self.check_batch(self.peak, "peak")
        self.k = torch.zeros((), dtype=torch.int64, device=self.f107.device)

    def feedthrough(self):
        return {"out": ()}

    def storm(self, t_hours: float) -> float:
        """S(t) / peak at time t [h]."""
        s = (t_hours - self.start) / self.rise
        return s * math.exp(1.0 - s) if s > 0 else 0.0

    def output(self, port, inputs):
        s = self.storm(int(self.k) * self.dt / 3600.0)
        B = self.batch_size
        return torch.cat([self.f107.expand(B, 1), (s * self.peak).expand(B, 1)], 1)

    def update(self, inputs):
        self.k += 1

    @property
    def count(self) -> torch.Tensor:
        """The step count k as a float per member (B, 1): the native form's state, set from k before each call
        of the engine (which advances k itself, ``Builder.counter``). One tensor while the batch stays, so the
        engine's binding of it stays too."""
        count = self.__dict__.get("_count")
        if count is None or count.shape[0] != self.batch_size:
            count = self.__dict__["_count"] = torch.zeros(self.batch_size, 1, dtype=torch.float64)
        if float(count[0, 0]) != float(self.k):
            count.fill_(float(self.k))
        return count

    def lower(self, b) -> None:
        """The native form: ``thermosphere_native``'s storm entry on [dt, start, rise, k, F10.7, peak]; k
        advances by one per step."""
        if importlib.util.find_spec("numba") is None:
            b.refuse("numba is not installed (pip install numba)")
        from . import thermosphere_native as tn
        count, block = b.state("count"), b.scratch(6)
        b.emit("COPY", WIDTH=3, IN=b.param(torch.tensor([[self.dt, self.start, self.rise]], dtype=torch.float64)),
               OUT=block, port="out")
        b.emit("COPY", WIDTH=1, IN=count, OUT=block + 3, port="out")
        b.emit("COPY", WIDTH=1, IN=b.param(self.f107), OUT=block + 4, port="out")
        b.emit("COPY", WIDTH=1, IN=b.param(self.peak), OUT=block + 5, port="out")
        fn = tn.entry("storm")
        b.emit("CALL", NIN=6, IN=block, NOUT=2, OUT=b.output("out"), FUNCTION=b.function(fn.address, fn),
               port="out")
        b.emit("SUM", WIDTH=1, OUT=count, terms=[dict(IN=count, SIGN=1),
                                                 dict(IN=b.param(torch.ones(1, 1, dtype=torch.float64)), SIGN=1)])
        b.counter()


#: Scale of the Arrhenius basis of ``TemperatureFeatures``: the NO 5.3 um quantum h nu / k, Kockarts' 2700 K. The
#: powers r^p of the basis span activation temperatures p x 2700 K.
ACTIVATION_K = 2700.0


@dataclass(frozen=True)
class Term:
    """One basis function of ``TemperatureFeatures``: r^power, or its low-pass memory with time constant
    ``memory_h`` hours (0: the present value)."""

    power: float
    memory_h: float = 0.0

    @classmethod
    def parse(cls, text: str) -> Term:
        """'r2' (r^2 now) or 'lp6:r2' (r^2 low-passed with a 6 h time constant)."""
        body, memory = text.strip(), 0.0
        try:
            if ":" in body:
                head, body = body.split(":", 1)
                if not head.startswith("lp"):
                    raise ValueError
                memory = float(head[2:])
            if not body.startswith("r"):
                raise ValueError
            power = float(body[1:])
        except ValueError:
            raise ConfigError(f"temperature feature {text!r}: write 'r<p>' (the Arrhenius factor to the power p) "
                              f"or 'lp<hours>:r<p>' (its low-pass memory), e.g. 'r1,lp3:r2,r3'") from None
        if memory < 0 or not math.isfinite(power) or not math.isfinite(memory):
            raise ConfigError(f"temperature feature {text!r}: the power must be finite and the memory >= 0 hours")
        return cls(power, memory)

    def __str__(self) -> str:
        r = f"r{self.power:g}"
        return f"lp{self.memory_h:g}:{r}" if self.memory_h else r


class TemperatureFeatures(Block):
    """Regressors of a temperature-only identified subsystem: basis functions of the known model's temperatures
    at the cooling nodes, and low-pass memories of them.

    At node j, r_j = exp(-Theta / T_j) / exp(-Theta / T_ref_j) is an Arrhenius factor that is 1 at the node's
    reference temperature T_ref_j (Theta = ``activation``). Each ``Term`` is r_j^p or its first-order low-pass
    memory m(k) = a m(k-1) + (1 - a) r_j(k)^p, a = exp(-dt / tau), which includes the present sample and starts
    from the value at ``T_init`` (the model's initial temperatures). The reference temperatures are part of the
    identified function (keep them when the function is reused); ``T_init`` only starts the memory.

    Input ``T`` (B, nodes) [K]; output ``f`` (B, nodes x terms), node-major: ``f[:, j * len(terms) + i]`` is
    term i at node j. Nothing but temperatures enters: the features carry no density, composition or cooling
    law. ``names`` lists the features.

    Args:
        terms: the basis, e.g. ``'r1,lp3:r2,r3'`` or a sequence of such strings or ``Term``s.
        T_ref: reference temperatures (nodes,) or (B, nodes) [K].
        dt: sample time [s].
        T_init: initial temperatures for the memory (default ``T_ref``).
        activation: Theta [K].
    """

    def __init__(self, terms: str | Sequence[str | Term], T_ref, dt: float, T_init=None,
                 activation: float = ACTIVATION_K, name: str = "features", dtype=DEFAULT_DTYPE):
        terms = terms.split(",") if isinstance(terms, str) else terms
        self.terms = tuple(t if isinstance(t, Term) else Term.parse(t) for t in terms)
        if not self.terms:
            raise ConfigError(f"block '{name}': no temperature features given")
        if dt <= 0 or activation <= 0:
            raise ConfigError(f"block '{name}': dt and the activation temperature must be positive")
        T_ref = torch.as_tensor(T_ref, dtype=dtype, device="cpu")
        T_ref = T_ref.reshape(1, -1) if T_ref.dim() < 2 else T_ref
        T_init = T_ref if T_init is None else \
            torch.as_tensor(T_init, dtype=dtype, device="cpu").reshape(-1, T_ref.shape[1])
        if bool((T_ref <= 0).any()) or bool((T_init <= 0).any()):
            raise ConfigError(f"block '{name}': temperatures must be positive (kelvin)")
        nodes = T_ref.shape[1]
        super().__init__(name, {"T": nodes}, {"f": nodes * len(self.terms)})
        self.activation = float(activation)
        self.memory = [i for i, t in enumerate(self.terms) if t.memory_h > 0]
        self.names = [f"{t}@{j}" for j in range(nodes) for t in self.terms]
        self.register_buffer("T_ref", T_ref)
        self.register_buffer("T_init", T_init)
        self.register_buffer("decay", torch.tensor([math.exp(-dt / (3600.0 * self.terms[i].memory_h))
                                                    for i in self.memory], dtype=dtype).reshape(1, -1, 1))
        self.register_buffer("m", torch.zeros(0, len(self.memory), nodes, dtype=dtype))

    def _powers(self, T: torch.Tensor, which: Sequence[int]) -> torch.Tensor:
        """r^p of the terms ``which`` at temperatures T (B, nodes): (B, len(which), nodes)."""
        log_r = self.activation * (1.0 / self.T_ref - 1.0 / T)
        p = torch.tensor([self.terms[i].power for i in which], dtype=T.dtype, device=T.device).reshape(1, -1, 1)
        return torch.exp(p * log_r.unsqueeze(1))

    def reset(self, batch_size: int) -> None:
        super().reset(batch_size)
        self.check_batch(self.T_ref, "T_ref")
        self.check_batch(self.T_init, "T_init")
        self.m = self._powers(self.T_init.expand(batch_size, -1), self.memory).clone()

    def feedthrough(self):
        return {"f": ("T",)}

    def _memory_now(self, T: torch.Tensor) -> torch.Tensor:
        return self.decay * self.m + (1.0 - self.decay) * self._powers(T, self.memory)

    def output(self, port, inputs):
        T = inputs["T"]
        f = self._powers(T, range(len(self.terms)))                                   # (B, terms, nodes)
        if self.memory:
            m = self._memory_now(T)
            f = torch.stack([m[:, self.memory.index(i)] if i in self.memory else f[:, i]
                             for i in range(len(self.terms))], 1)
        return f.transpose(1, 2).flatten(1)

    def update(self, inputs):
        if self.memory:
            self.set_state(m=self._memory_now(inputs["T"]))

    def lower(self, b) -> None:
        """The native form: ``thermosphere_native``'s features entry computes the features and the next memory
        together (for the output ``f``); the update keeps the memory."""
        if importlib.util.find_spec("numba") is None:
            b.refuse("numba is not installed (pip install numba)")
        from . import thermosphere_native as tn
        nodes, terms, mem = self.T_ref.shape[1], len(self.terms), len(self.memory)
        layout = [nodes, terms, mem, self.activation, *[t.power for t in self.terms],
                  *[self.memory.index(i) if i in self.memory else -1 for i in range(terms)],
                  *self.decay.reshape(-1).tolist()]
        head = len(layout)
        block, out = b.scratch(head + (2 + mem) * nodes), b.scratch((terms + mem) * nodes)
        b.emit("COPY", WIDTH=head, IN=b.param(torch.tensor([layout], dtype=torch.float64)), OUT=block, port="f")
        b.emit("COPY", WIDTH=nodes, IN=b.input("T"), OUT=block + head, port="f")
        b.emit("COPY", WIDTH=nodes, IN=b.param(self.T_ref), OUT=block + head + nodes, port="f")
        if mem:
            m = b.state("m")
            b.emit("COPY", WIDTH=mem * nodes, IN=m, OUT=block + head + 2 * nodes, port="f")
        fn = tn.entry("features")
        b.emit("CALL", NIN=head + (2 + mem) * nodes, IN=block, NOUT=(terms + mem) * nodes, OUT=out,
               FUNCTION=b.function(fn.address, fn), port="f")
        b.emit("COPY", WIDTH=terms * nodes, IN=out, OUT=b.output("f"), port="f")
        if mem:
            b.emit("COPY", WIDTH=mem * nodes, IN=out + terms * nodes, OUT=m)


def interpolation_basis(z: torch.Tensor, nodes: torch.Tensor) -> torch.Tensor:
    """Hat functions (nodes, n) on the grid z: linear interpolation between the nodes, tapered linearly to zero one
    node spacing below the lowest and above the highest node."""
    if nodes.numel() < 2 or bool((nodes[1:] <= nodes[:-1]).any()):
        raise ConfigError(f"cooling nodes must be at least two increasing altitudes, got {nodes.tolist()}")
    ext = torch.cat([2 * nodes[:1] - nodes[1:2], nodes, 2 * nodes[-1:] - nodes[-2:-1]])
    rising = (z - ext[:-2, None]) / (ext[1:-1, None] - ext[:-2, None])
    falling = (ext[2:, None] - z) / (ext[2:, None] - ext[1:-1, None])
    return torch.minimum(rising, falling).clamp(min=0.0)


def bates_profile(z: torch.Tensor, T_inf: float, T_0: float, shape: float, z0: float | None = None,
                  radius: float = R_EARTH) -> torch.Tensor:
    """Bates (1959) temperature profile T = T_inf - (T_inf - T_0) exp(-shape xi), xi = (z - z0)(R + z0)/(R + z)
    the geopotential height above z0 (the lowest z by default), shape in 1/m."""
    z0 = float(z[0]) if z0 is None else z0
    xi = (z - z0) * (radius + z0) / (radius + z)
    return T_inf - (T_inf - T_0) * torch.exp(-shape * xi)


def walker_density(z: torch.Tensor, n0: float, mass: float, T_inf: float, T_0: float, shape: float,
                   z0: float | None = None, radius: float = R_EARTH) -> torch.Tensor:
    """The closed-form diffusive-equilibrium density in a Bates profile (Walker 1965), the independent reference
    for ``Column.densities``: n/n0 = ((1 - a) / (1 - a exp(-shape xi)))^(1 + gamma) exp(-shape gamma xi),
    a = 1 - T_0/T_inf, gamma = m g(z0) / (shape k T_inf)."""
    z0 = float(z[0]) if z0 is None else z0
    xi = (z - z0) * (radius + z0) / (radius + z)
    a = 1.0 - T_0 / T_inf
    gamma = mass * G0 * (radius / (radius + z0)) ** 2 / (shape * K_B * T_inf)
    return n0 * ((1 - a) / (1 - a * torch.exp(-shape * xi))) ** (1 + gamma) * torch.exp(-shape * gamma * xi)
