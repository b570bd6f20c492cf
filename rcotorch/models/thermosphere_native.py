"""The thermosphere column for the native engine: ``Column``'s step and observations, and their tangents, written
with NumPy and compiled by numba.

One copy of the physics per language: the torch ``Column`` (``rcotorch.models.thermosphere``) is the reference
(any device, autograd, float32 or float64); this module is the CPU engine's copy, in float64. Each function names
the ``Column`` method it mirrors and computes the same expressions in the same order, for one member, level by
level (loops, which numba compiles to code that runs without temporary arrays). Two things differ in method,
not in the equations: the conduction step's tridiagonal system is solved by elimination without pivoting (the
torch column calls ``torch.linalg.solve``; the matrix is diagonally dominant), and the linearization is the
tangent of the step written out (the torch column differentiates with autograd). The two agree to rounding
(``tests/test_thermosphere_native.py``).

A column's constants and sizes are data, not code: ``pack`` lays a ``Column``'s grid, band tables, profiles and
switches out in one float64 vector, which the functions take (``unpack``). So the code is compiled once per
machine for every column, whatever its grid or settings, and numba keeps it on disk (``cache=True``), so only
the first use on a machine waits for the compilation. The engine calls it through C entry points (``entry``),
each reading the vector from its first input slots, followed by the state and inputs, for each member of its
chunk:

* ``step``: ``[params | x | w | u] -> x(k+1)`` (``Column.step``);
* ``observe``: ``[params | reads | x] -> observations`` (``Column.at`` of the temperature, mass density or NO
  cooling profile; ``reads``, see ``READ_FIELDS``, is what a ``thermosphere.Observation`` asks for);
* ``storm``: ``[dt, start, rise | step count, F10.7, peak] -> w`` (``SpaceWeather.output``);
* ``features``: ``[layout | T | T_ref | memory] -> [features | next memory]`` (``TemperatureFeatures``).

``NativeColumn`` calls the same code from Python: steps, trajectories and the Markov parameters (``markov``,
``Nonlinear.markov`` along the trajectory with ``tangent_step`` and ``tangent_observe``, or by differences).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch

from .thermosphere_constants import (
    DIURNAL_AMPLITUDE,
    K_B,
    KAPPA_A,
    KAPPA_S,
    MU_PATH,
    NO_A10,
    NO_HNU,
    NO_K_O,
    NO_THETA,
    NO_UNIT,
    NO_YIELD,
    PEAK_LOCAL_TIME,
    STORM_PARTICLE_SHARE,
    W_ION,
)

#: Compiled as the engine's own code: IEEE division (inf and nan, as in torch, not Python's ZeroDivisionError),
#: kept on disk.
jit = numba.njit(cache=True, error_model="numpy")

#: Profiles an observation reads (one row of ``reads`` per observed value): the temperature [K], the mass density
#: [kg/m^3] and the Kockarts NO cooling [nW/m^3].
TEMPERATURE, MASS_DENSITY, NO_COOLING = 0, 1, 2
#: How a read takes its value from the profile: the level itself, linear or log-linear interpolation.
LEVEL, LINEAR, LOG = 0, 1, 2
#: Columns of a read: profile, level i, weight a of level i + 1, mode, scale (the value times ``scale``).
READ_FIELDS = ("profile", "level", "weight", "mode", "scale")
TINY = np.finfo(np.float64).tiny
#: The scalars at the head of a packed column: its length, sizes, grid, boundary, sun, time step and switches.
HEADER = ("size", "n", "bands", "nodes", "dz", "T_bottom", "insolation_mean", "local_time0", "dt", "substeps",
          "no_cooling", "strength")
HEAD = len(HEADER)


def pack(column) -> np.ndarray:
    """A float64 ``Column``'s constants as one vector (``HEADER``, then g, mass, c_p, log n_bottom, sigma,
    efficiency, band flux, per sfu, storm profile, 1/tau_NO, cooling basis, node levels and weights)."""
    def a(t):
        return t.detach().to("cpu", torch.float64).reshape(-1).numpy()
    brackets = [column.bracket(float(z)) for z in column.nodes]
    arrays = [a(column.g), a(column.mass), a(column.cp), a(column.log_n_bottom), a(column.sigma),
              a(column.efficiency), a(column.band_flux), a(column.band_per_sfu), a(column.storm_profile),
              a(column.no_loss), a(column.cooling_basis), np.array([float(i) for i, _ in brackets]),
              np.array([w for _, w in brackets], dtype=np.float64)]
    head = [0.0, column.n, len(column.bands), column.n_nodes, column.dz, column.T_bottom, column.insolation_mean,
            column.local_time0, column.dt, column.substeps, float(column.no_cooling),
            float(column.interpolate == "strength")]
    out = np.concatenate([np.array(head, dtype=np.float64)] + arrays)
    out[0] = out.size
    return out


@jit
def unpack(p):
    """The column of a packed vector p (``pack``) as the tuple ``step`` takes: its arrays are views of p."""
    n, nb, nodes = int(p[1]), int(p[2]), int(p[3])
    o = HEAD
    g = p[o:o + n]
    mass, cp, log_n_bottom = p[o + n:o + n + 3], p[o + n + 3:o + n + 6], p[o + n + 6:o + n + 9]
    o += n + 9
    sigma = p[o:o + 3 * nb].reshape(nb, 3)
    efficiency, band_flux, band_per_sfu = p[o + 3 * nb:o + 4 * nb], p[o + 4 * nb:o + 5 * nb], p[o + 5 * nb:o + 6 * nb]
    o += 6 * nb
    storm_profile, no_loss = p[o:o + n], p[o + n:o + 2 * n]
    o += 2 * n
    basis = p[o:o + nodes * n].reshape(nodes, n)
    o += nodes * n
    node_level, node_weight = p[o:o + nodes], p[o + nodes:o + 2 * nodes]
    return (g, mass, cp, log_n_bottom, sigma, efficiency, band_flux, band_per_sfu, storm_profile, no_loss, basis,
            node_level, node_weight, p[4], p[5], p[6], p[7], p[8], int(p[9]), p[10] != 0.0, p[11] != 0.0, n)


# --- the column: mirrors of Column's methods, for one member --------------------------------------------------
@jit
def densities(T, g, dz, log_n_bottom, mass):
    """``Column.densities``: O, O2, N2 number densities (3, n) [m^-3] in diffusive equilibrium at T (n,)."""
    n = T.shape[0]
    out = np.empty((3, n))
    integral = 0.0                                   # int g / T dz from the bottom, by the trapezoid rule
    for j in range(n):
        if j > 0:
            integral = integral + 0.5 * dz * (g[j] / T[j] + g[j - 1] / T[j - 1])
        for i in range(3):
            out[i, j] = math.exp(log_n_bottom[i] + math.log(T[0] / T[j]) - mass[i] / K_B * integral)
    return out


@jit
def mass_density(dens, mass, j):
    """``Column.mass_density`` at level j of the densities (3, n) [kg/m^3]."""
    return mass[0] * dens[0, j] + mass[1] * dens[1, j] + mass[2] * dens[2, j]


@jit
def column_above(dens, T, g, dz, mass):
    """``Column.column_above``: N_i(z) = int_z^inf n_i dz' (3, n) [m^-2], above the top n_i times its scale
    height."""
    n = T.shape[0]
    out = np.empty((3, n))
    for i in range(3):
        top = dens[i, n - 1] * K_B * T[n - 1] / (mass[i] * g[n - 1])
        out[i, n - 1] = top
        above = 0.0
        for j in range(n - 2, -1, -1):
            above = above + 0.5 * dz * (dens[i, j + 1] + dens[i, j])
            out[i, j] = above + top
    return out


@jit
def insolation(t_hours, mean, local_time0):
    """``Column.insolation``: the share I(t) of the overhead-sun flux at time t [h]."""
    return mean * (1.0 + DIURNAL_AMPLITUDE * math.cos((local_time0 + t_hours - PEAK_LOCAL_TIME) * (math.pi / 12.0)))


@jit
def solar(dens, N, t_hours, f107, sigma, efficiency, band_flux, band_per_sfu, mean, local_time0):
    """``Column.solar`` with the column densities N = ``column_above(dens, T)``: neutral heating (n,) [W/m^3] and
    the ion pairs made in N2 (n,) [1/(m^3 s)] by the sun."""
    n = dens.shape[1]
    heating, ions = np.zeros(n), np.zeros(n)
    sun = insolation(t_hours, mean, local_time0)
    for k in range(sigma.shape[0]):
        flux0 = max(band_flux[k] * (1.0 + band_per_sfu[k] * (f107 - 150.0)), 0.0) * sun
        for j in range(n):
            tau = sigma[k, 0] * N[0, j] + sigma[k, 1] * N[1, j] + sigma[k, 2] * N[2, j]
            flux = flux0 * math.exp(-tau / MU_PATH)
            absorbed = sigma[k, 0] * dens[0, j] + sigma[k, 1] * dens[1, j] + sigma[k, 2] * dens[2, j]
            heating[j] = heating[j] + efficiency[k] * flux * absorbed
            ions[j] = ions[j] + flux * (sigma[k, 2] * dens[2, j])
    return heating, ions / W_ION


@jit
def no_cooling_rate(T, n_O, n_NO):
    """``Column.no_cooling_rate`` at one level: Kockarts (1980) NO 5.3 um cooling [W/m^3]."""
    collisions = NO_K_O * n_O
    return NO_HNU * NO_A10 * n_NO * collisions * math.exp(-NO_THETA / T) / (collisions + NO_A10)


@jit
def at_node(profile, node_level, node_weight, j):
    """``Column.at_nodes``: a profile (n,) at cooling node j by linear interpolation."""
    i, a = int(node_level[j]), node_weight[j]
    return (1 - a) * profile[i] + a * profile[i + 1]


@jit
def identified_cooling(u, rate, basis, node_level, node_weight, strength):
    """``Column.identified_cooling``: the cooling profile (n,) [W/m^3] of node values u (nodes,) [nW/m^3],
    interpolated linearly, or with ``strength`` in proportion to the Kockarts rate (n,)."""
    nodes, n = basis.shape
    coefficient = np.empty(nodes)                    # 1e-9 u_j, or the strength u_j / rate(z_j)
    for j in range(nodes):
        coefficient[j] = u[j] / max(at_node(rate, node_level, node_weight, j), TINY) if strength else 1e-9 * u[j]
    out = np.zeros(n)
    for z in range(n):
        acc = 0.0
        for j in range(nodes):
            acc = acc + coefficient[j] * basis[j, z]
        out[z] = 1e-9 * rate[z] * acc if strength else acc
    return out


@jit
def conduct(T, C, Q, dt, dz, T_bottom):
    """``Column.conduct``: one backward-Euler step of C dT/dt = d/dz(kappa(T) dT/dz) + Q, kappa and C lagged,
    T = T_bottom at the bottom and a mirror level at the top: the new T (n,). Returns (T, below, above, pivots),
    the couplings and the elimination's pivots (``tangent_conduct`` solves with them again)."""
    n = T.shape[0]
    below, above = np.zeros(n), np.zeros(n)          # coupling of level i to i - 1 and to i + 1
    for f in range(n - 1):                           # the face between levels f and f + 1
        k = KAPPA_A * (0.5 * (T[f + 1] + T[f])) ** KAPPA_S * (dt / dz ** 2)
        below[f + 1] = k if f + 1 < n - 1 else 2.0 * k          # the top level's mirror doubles it
        if f > 0:
            above[f] = k
    # Row 0 is T_0 = T_bottom; row i: -below_i T_(i-1) + (C_i + below_i + above_i) T_i - above_i T_(i+1) = rhs_i.
    out, pivots = np.empty(n), np.empty(n)
    pivots[0], out[0] = 1.0, T_bottom
    for i in range(1, n):
        pivots[i] = C[i] + below[i] + above[i] - below[i] * above[i - 1] / pivots[i - 1]
        out[i] = C[i] * T[i] + dt * Q[i] + below[i] * out[i - 1] / pivots[i - 1]
    out[n - 1] = out[n - 1] / pivots[n - 1]
    for i in range(n - 2, 0, -1):
        out[i] = (out[i] + above[i] * out[i + 1]) / pivots[i]
    return out, below, above, pivots


@jit
def step(x, w, u, col):
    """``Column.step`` (with ``Column.tendencies``) of one member: x(k) -> x(k+1) (2n + 1,), ``substeps``
    backward-Euler substeps with w (2,) and u (nodes,) held."""
    (g, mass, cp, log_n_bottom, sigma, efficiency, band_flux, band_per_sfu, storm_profile, no_loss, basis,
     node_level, node_weight, dz, T_bottom, mean, local_time0, dt, substeps, no_cooling, strength, n) = col
    h = dt / substeps
    out = x.copy()
    C, Q, no, production = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    for _ in range(substeps):
        T = out[:n].copy()
        dens = densities(T, g, dz, log_n_bottom, mass)
        heating, ions = solar(dens, column_above(dens, T, g, dz, mass), out[2 * n], w[0], sigma, efficiency,
                              band_flux, band_per_sfu, mean, local_time0)
        for j in range(n):
            no[j] = no_cooling_rate(T[j], dens[0, j], out[n + j] * NO_UNIT)
        identified = identified_cooling(u, no, basis, node_level, node_weight, strength)
        for j in range(n):
            storm = 1e-3 * w[1] * storm_profile[j]                              # [W/m^3]
            cooling = no[j] if no_cooling else 0.0
            if basis.shape[0]:
                cooling = cooling + identified[j]
            C[j] = cp[0] * dens[0, j] + cp[1] * dens[1, j] + cp[2] * dens[2, j]   # rho c_p
            Q[j] = heating[j] + storm - cooling
            production[j] = NO_YIELD * (ions[j] + STORM_PARTICLE_SHARE * storm / W_ION)
        out[:n] = conduct(T, C, Q, h, dz, T_bottom)[0]
        for j in range(n):
            equilibrium = production[j] / no_loss[j]
            out[n + j] = (equilibrium + (out[n + j] * NO_UNIT - equilibrium) * math.exp(-h * no_loss[j])) / NO_UNIT
        out[2 * n] = out[2 * n] + h / 3600.0
    return out


@jit
def read(p, level, weight, mode):
    """``Column.at``: a profile (n,) at one level or between two (``LINEAR``, ``LOG``)."""
    if mode == LEVEL:
        return p[level]
    if mode == LINEAR:
        return (1 - weight) * p[level] + weight * p[level + 1]
    return math.exp((1 - weight) * math.log(p[level]) + weight * math.log(p[level + 1]))


@jit
def observe(x, col, reads):
    """Observations of one member's state x, one per row of ``reads`` (``READ_FIELDS``): (len(reads),)."""
    g, mass, log_n_bottom, dz, n = col[0], col[1], col[3], col[13], col[21]
    T = x[:n].copy()
    dens = densities(T, g, dz, log_n_bottom, mass)
    p = np.empty((3, n))                             # temperature, mass density, NO cooling [nW/m^3]
    for j in range(n):
        p[TEMPERATURE, j] = T[j]
        p[MASS_DENSITY, j] = mass_density(dens, mass, j)
        p[NO_COOLING, j] = 1e9 * no_cooling_rate(T[j], dens[0, j], x[n + j] * NO_UNIT)
    out = np.empty(reads.shape[0])
    for r in range(reads.shape[0]):
        out[r] = reads[r, 4] * read(p[int(reads[r, 0])], int(reads[r, 1]), reads[r, 2], int(reads[r, 3]))
    return out


# --- the tangent: step and observe, and their derivatives in D directions (dx, dw, du), rows of (D, ...) ---------
@jit
def tangent_densities(T, dT, dens, g, dz, mass):
    """The tangent of ``densities`` at T (n,) in the directions dT (D, n), given its value ``dens``: (D, 3, n)."""
    D, n = dT.shape
    out = np.empty((D, 3, n))
    for d in range(D):
        dintegral = 0.0
        for j in range(n):
            if j > 0:
                dintegral = dintegral - 0.5 * dz * (g[j] * dT[d, j] / (T[j] * T[j]) +
                                                    g[j - 1] * dT[d, j - 1] / (T[j - 1] * T[j - 1]))
            dlog_ratio = dT[d, 0] / T[0] - dT[d, j] / T[j]
            for i in range(3):
                out[d, i, j] = dens[i, j] * (dlog_ratio - mass[i] / K_B * dintegral)
    return out


@jit
def tangent_column_above(dens, ddens, T, dT, g, dz, mass):
    """The tangent of ``column_above`` at (dens, T) in the directions (ddens, dT): (D, 3, n)."""
    D, n = dT.shape
    out = np.empty((D, 3, n))
    for d in range(D):
        for i in range(3):
            top = (ddens[d, i, n - 1] * T[n - 1] + dens[i, n - 1] * dT[d, n - 1]) * K_B / (mass[i] * g[n - 1])
            out[d, i, n - 1] = top
            above = 0.0
            for j in range(n - 2, -1, -1):
                above = above + 0.5 * dz * (ddens[d, i, j + 1] + ddens[d, i, j])
                out[d, i, j] = above + top
    return out


@jit
def tangent_solar(dens, ddens, N, dN, t_hours, dt_hours, f107, df107, sigma, efficiency, band_flux, band_per_sfu,
                  mean, local_time0):
    """``solar`` and its tangent in the directions (ddens, dN, dt (D,), dF10.7 (D,)): heating, ions (n,) and
    their tangents (D, n)."""
    D, n = dN.shape[0], dens.shape[1]
    heating, ions = np.zeros(n), np.zeros(n)
    dheating, dions = np.zeros((D, n)), np.zeros((D, n))
    phase = (local_time0 + t_hours - PEAK_LOCAL_TIME) * (math.pi / 12.0)
    sun = insolation(t_hours, mean, local_time0)
    for k in range(sigma.shape[0]):
        raw = band_flux[k] * (1.0 + band_per_sfu[k] * (f107 - 150.0))
        flux0 = max(raw, 0.0) * sun
        for j in range(n):
            tau = sigma[k, 0] * N[0, j] + sigma[k, 1] * N[1, j] + sigma[k, 2] * N[2, j]
            attenuation = math.exp(-tau / MU_PATH)
            flux = flux0 * attenuation
            absorbed = sigma[k, 0] * dens[0, j] + sigma[k, 1] * dens[1, j] + sigma[k, 2] * dens[2, j]
            heating[j] = heating[j] + efficiency[k] * flux * absorbed
            ions[j] = ions[j] + flux * (sigma[k, 2] * dens[2, j])
            for d in range(D):
                dflux0 = (band_flux[k] * band_per_sfu[k] * df107[d] if raw >= 0.0 else 0.0) * sun - \
                    max(raw, 0.0) * mean * DIURNAL_AMPLITUDE * math.sin(phase) * (math.pi / 12.0) * dt_hours[d]
                dtau = sigma[k, 0] * dN[d, 0, j] + sigma[k, 1] * dN[d, 1, j] + sigma[k, 2] * dN[d, 2, j]
                dflux = dflux0 * attenuation - flux * dtau / MU_PATH
                dabsorbed = sigma[k, 0] * ddens[d, 0, j] + sigma[k, 1] * ddens[d, 1, j] + \
                    sigma[k, 2] * ddens[d, 2, j]
                dheating[d, j] = dheating[d, j] + efficiency[k] * (dflux * absorbed + flux * dabsorbed)
                dions[d, j] = dions[d, j] + sigma[k, 2] * (dflux * dens[2, j] + flux * ddens[d, 2, j])
    return heating, ions / W_ION, dheating, dions / W_ION


@jit
def tangent_no_cooling_rate(T, dT, n_O, dn_O, n_NO, dn_NO):
    """The derivative of ``no_cooling_rate`` at one level in the direction (dT, dn_O, dn_NO)."""
    collisions = NO_K_O * n_O
    boltzmann = math.exp(-NO_THETA / T)
    quench = collisions + NO_A10
    rate = NO_HNU * NO_A10 * n_NO * collisions * boltzmann / quench
    return NO_HNU * NO_A10 * boltzmann * (dn_NO * collisions / quench + n_NO * NO_K_O * dn_O * NO_A10 /
                                          (quench * quench)) + rate * NO_THETA * dT / (T * T)


@jit
def tangent_identified_cooling(u, du, rate, drate, basis, node_level, node_weight, strength):
    """The tangent of ``identified_cooling`` in the directions (du (D, nodes), drate (D, n)): (D, n)."""
    nodes, n = basis.shape
    D = du.shape[0]
    out = np.zeros((D, n))
    for d in range(D):
        dcoefficient = np.empty(nodes)
        for j in range(nodes):
            if strength:
                raw = at_node(rate, node_level, node_weight, j)
                r = max(raw, TINY)
                dr = at_node(drate[d], node_level, node_weight, j) if raw >= TINY else 0.0   # the clamp's mask
                dcoefficient[j] = du[d, j] / r - u[j] * dr / (r * r)
            else:
                dcoefficient[j] = 1e-9 * du[d, j]
        for z in range(n):
            dacc = 0.0
            for j in range(nodes):
                dacc = dacc + dcoefficient[j] * basis[j, z]
            if strength:
                acc = 0.0
                for j in range(nodes):
                    acc = acc + u[j] / max(at_node(rate, node_level, node_weight, j), TINY) * basis[j, z]
                out[d, z] = 1e-9 * (drate[d, z] * acc + rate[z] * dacc)
            else:
                out[d, z] = dacc
    return out


@jit
def tangent_conduct(T, dT, C, dC, dQ, T_new, below, above, pivots, dt, dz):
    """The tangent of ``conduct`` in the directions (dT, dC, dQ), each (D, n), given its solution T_new and
    system (``conduct``'s couplings and pivots): A dT_new = d(rhs) - dA T_new, solved by the same elimination."""
    D, n = dT.shape
    out = np.empty((D, n))
    dbelow, dabove = np.zeros(n), np.zeros(n)
    for d in range(D):
        for f in range(n - 1):
            dk = KAPPA_A * KAPPA_S * (0.5 * (T[f + 1] + T[f])) ** (KAPPA_S - 1.0) * \
                (0.5 * (dT[d, f + 1] + dT[d, f])) * (dt / dz ** 2)
            dbelow[f + 1] = dk if f + 1 < n - 1 else 2.0 * dk
            if f > 0:
                dabove[f] = dk
        out[d, 0] = 0.0
        for i in range(1, n):
            r = dC[d, i] * T[i] + C[i] * dT[d, i] + dt * dQ[d, i] - \
                (dC[d, i] + dbelow[i] + dabove[i]) * T_new[i] + dbelow[i] * T_new[i - 1]
            if i < n - 1:
                r = r + dabove[i] * T_new[i + 1]
            out[d, i] = r + below[i] * out[d, i - 1] / pivots[i - 1]
        out[d, n - 1] = out[d, n - 1] / pivots[n - 1]
        for i in range(n - 2, 0, -1):
            out[d, i] = (out[d, i] + above[i] * out[d, i + 1]) / pivots[i]
    return out


@jit
def tangent_step(x, w, u, dx, dw, du, col):
    """``step`` of one member and its tangent in the directions (dx (D, 2n + 1), dw (D, 2), du (D, nodes)):
    (x(k+1), dx(k+1))."""
    (g, mass, cp, log_n_bottom, sigma, efficiency, band_flux, band_per_sfu, storm_profile, no_loss, basis,
     node_level, node_weight, dz, T_bottom, mean, local_time0, dt, substeps, no_cooling, strength, n) = col
    D = dx.shape[0]
    h = dt / substeps
    out, dout = x.copy(), dx.copy()
    C, Q, no, production = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    dC, dQ, dno, dproduction = np.empty((D, n)), np.empty((D, n)), np.empty((D, n)), np.empty((D, n))
    for _ in range(substeps):
        T, dT = out[:n].copy(), dout[:, :n].copy()
        dens = densities(T, g, dz, log_n_bottom, mass)
        ddens = tangent_densities(T, dT, dens, g, dz, mass)
        N = column_above(dens, T, g, dz, mass)
        dN = tangent_column_above(dens, ddens, T, dT, g, dz, mass)
        heating, ions, dheating, dions = tangent_solar(dens, ddens, N, dN, out[2 * n], dout[:, 2 * n], w[0],
                                                       dw[:, 0], sigma, efficiency, band_flux, band_per_sfu, mean,
                                                       local_time0)
        for j in range(n):
            no[j] = no_cooling_rate(T[j], dens[0, j], out[n + j] * NO_UNIT)
            for d in range(D):
                dno[d, j] = tangent_no_cooling_rate(T[j], dT[d, j], dens[0, j], ddens[d, 0, j],
                                                    out[n + j] * NO_UNIT, dout[d, n + j] * NO_UNIT)
        identified = identified_cooling(u, no, basis, node_level, node_weight, strength)
        didentified = tangent_identified_cooling(u, du, no, dno, basis, node_level, node_weight, strength)
        for j in range(n):
            storm = 1e-3 * w[1] * storm_profile[j]
            cooling = no[j] if no_cooling else 0.0
            if basis.shape[0]:
                cooling = cooling + identified[j]
            C[j] = cp[0] * dens[0, j] + cp[1] * dens[1, j] + cp[2] * dens[2, j]
            Q[j] = heating[j] + storm - cooling
            production[j] = NO_YIELD * (ions[j] + STORM_PARTICLE_SHARE * storm / W_ION)
            for d in range(D):
                dstorm = 1e-3 * dw[d, 1] * storm_profile[j]
                dcooling = (dno[d, j] if no_cooling else 0.0) + (didentified[d, j] if basis.shape[0] else 0.0)
                dC[d, j] = cp[0] * ddens[d, 0, j] + cp[1] * ddens[d, 1, j] + cp[2] * ddens[d, 2, j]
                dQ[d, j] = dheating[d, j] + dstorm - dcooling
                dproduction[d, j] = NO_YIELD * (dions[d, j] + STORM_PARTICLE_SHARE * dstorm / W_ION)
        T_new, below, above, pivots = conduct(T, C, Q, h, dz, T_bottom)
        dout[:, :n] = tangent_conduct(T, dT, C, dC, dQ, T_new, below, above, pivots, h, dz)
        out[:n] = T_new
        for j in range(n):
            decay = math.exp(-h * no_loss[j])
            equilibrium = production[j] / no_loss[j]
            out[n + j] = (equilibrium + (out[n + j] * NO_UNIT - equilibrium) * decay) / NO_UNIT
            for d in range(D):
                dequilibrium = dproduction[d, j] / no_loss[j]
                dout[d, n + j] = (dequilibrium + (dout[d, n + j] * NO_UNIT - dequilibrium) * decay) / NO_UNIT
        out[2 * n] = out[2 * n] + h / 3600.0
    return out, dout


@jit
def tangent_observe(x, dx, col, reads):
    """``observe`` of one member and its tangent in the directions dx (D, 2n + 1): (len(reads),) and
    (D, len(reads))."""
    g, mass, log_n_bottom, dz, n = col[0], col[1], col[3], col[13], col[21]
    D = dx.shape[0]
    T, dT = x[:n].copy(), dx[:, :n].copy()
    dens = densities(T, g, dz, log_n_bottom, mass)
    ddens = tangent_densities(T, dT, dens, g, dz, mass)
    p, dp = np.empty((3, n)), np.empty((D, 3, n))
    for j in range(n):
        p[TEMPERATURE, j] = T[j]
        p[MASS_DENSITY, j] = mass_density(dens, mass, j)
        p[NO_COOLING, j] = 1e9 * no_cooling_rate(T[j], dens[0, j], x[n + j] * NO_UNIT)
        for d in range(D):
            dp[d, TEMPERATURE, j] = dT[d, j]
            dp[d, MASS_DENSITY, j] = mass_density(ddens[d], mass, j)
            dp[d, NO_COOLING, j] = 1e9 * tangent_no_cooling_rate(T[j], dT[d, j], dens[0, j], ddens[d, 0, j],
                                                                 x[n + j] * NO_UNIT, dx[d, n + j] * NO_UNIT)
    out, dout = np.empty(reads.shape[0]), np.empty((D, reads.shape[0]))
    for r in range(reads.shape[0]):
        src, level, weight, mode, scale = int(reads[r, 0]), int(reads[r, 1]), reads[r, 2], int(reads[r, 3]), \
            reads[r, 4]
        out[r] = scale * read(p[src], level, weight, mode)
        for d in range(D):
            if mode == LOG:                          # d exp(v) = exp(v) dv, v interpolating log p
                dout[d, r] = out[r] * ((1 - weight) * dp[d, src, level] / p[src, level] +
                                       weight * dp[d, src, level + 1] / p[src, level + 1])
            else:
                dout[d, r] = scale * read(dp[d, src], level, weight, mode)
    return out, dout


# --- Markov parameters and trajectories ---------------------------------------------------------------------------
@jit
def markov(p, reads, x, w, u, port, steps, trajectory, fd, eps):
    """``Nonlinear.markov`` of a packed column from input ``port`` (0: w, 1: u) to the observations ``reads``:
    H_0 .. H_(steps-1), (B, steps, len(reads), width of the port), along the trajectory from x (B, 2n + 1) (or
    at the point x) with w and u held; by the tangent (``fd`` False) or by central differences of step eps
    relative to the largest entry of the point over all members and directions, as ``Nonlinear.markov``. The
    directions of a member share its trajectory."""
    col = unpack(p)
    B, N = x.shape
    width = w.shape[1] if port == 0 else u.shape[1]
    R = reads.shape[0]
    dw, du = np.zeros((width, w.shape[1])), np.zeros((width, u.shape[1]))
    for j in range(width):
        if port == 0:
            dw[j, j] = 1.0
        else:
            du[j, j] = 1.0
    no_w, no_u = np.zeros_like(dw), np.zeros_like(du)
    H = np.zeros((B, steps, R, width))
    xi, dx = np.empty((B, N)), np.empty((B, width, N))
    s = eps * max(1.0, np.abs(w if port == 0 else u).max())
    for b in range(B):
        if fd:
            xi[b] = step(x[b], w[b], u[b], col)
            for j in range(width):
                dx[b, j] = (step(x[b], w[b] + s * dw[j], u[b] + s * du[j], col) -
                            step(x[b], w[b] - s * dw[j], u[b] - s * du[j], col)) / (2 * s)
        else:
            xb, dxb = tangent_step(x[b], w[b], u[b], np.zeros((width, N)), dw, du, col)
            xi[b], dx[b] = xb, dxb
    for i in range(1, steps):
        base = xi if trajectory else x
        s = eps * max(1.0, np.abs(base).max())
        xn = np.empty((B, N))
        for b in range(B):
            if fd:
                for j in range(width):
                    H[b, i, :, j] = (observe(base[b] + s * dx[b, j], col, reads) -
                                     observe(base[b] - s * dx[b, j], col, reads)) / (2 * s)
            else:
                dy = tangent_observe(base[b], dx[b], col, reads)[1]
                for j in range(width):
                    H[b, i, :, j] = dy[j]
            if i + 1 < steps:
                if fd:
                    xn[b] = step(base[b], w[b], u[b], col)
                    for j in range(width):
                        dx[b, j] = (step(base[b] + s * dx[b, j], w[b], u[b], col) -
                                    step(base[b] - s * dx[b, j], w[b], u[b], col)) / (2 * s)
                else:
                    xb, dxb = tangent_step(base[b], w[b], u[b], dx[b], no_w, no_u, col)
                    xn[b], dx[b] = xb, dxb
        if trajectory:
            xi = xn
    return H


@jit
def trajectory(p, reads, x, w, u):
    """The column from x (B, 2n + 1) driven by w (B, K, 2) and u (B, K, nodes): the observations ``reads`` of
    x(0) .. x(K-1) (B, K, len(reads)) and x(K)."""
    col = unpack(p)
    B, K = w.shape[0], w.shape[1]
    y = np.empty((B, K, reads.shape[0]))
    out = np.empty_like(x)
    for b in range(B):
        xb = x[b].copy()
        for k in range(K):
            y[b, k] = observe(xb, col, reads)
            xb = step(xb, w[b, k], u[b, k], col)
        out[b] = xb
    return y, out


# --- entry points of the engine's CALL: void f(const double *in, double *out, int64 lanes) -------------------------
SIGNATURE = numba.types.void(numba.types.CPointer(numba.types.float64), numba.types.CPointer(numba.types.float64),
                             numba.types.int64)


def _step_entry(inp, out, lanes):
    """[params | x | w | u] -> x(k+1), slot by slot for the chunk's lanes."""
    head = numba.carray(inp, (HEAD, lanes))
    size, n, nodes = int(head[0, 0]), int(head[1, 0]), int(head[3, 0])
    N = 2 * n + 1
    slots, o = numba.carray(inp, (size + N + 2 + nodes, lanes)), numba.carray(out, (N, lanes))
    col = unpack(np.ascontiguousarray(slots[:size, 0]))
    for lane in range(lanes):
        o[:, lane] = step(np.ascontiguousarray(slots[size:size + N, lane]),
                          np.ascontiguousarray(slots[size + N:size + N + 2, lane]),
                          np.ascontiguousarray(slots[size + N + 2:, lane]), col)


def _observe_entry(inp, out, lanes):
    """[params | number of reads | reads | x] -> the observations."""
    head = numba.carray(inp, (HEAD, lanes))
    size, n = int(head[0, 0]), int(head[1, 0])
    count = int(numba.carray(inp, (size + 1, lanes))[size, 0])
    first = size + 1 + len(READ_FIELDS) * count
    slots, o = numba.carray(inp, (first + 2 * n + 1, lanes)), numba.carray(out, (count, lanes))
    col = unpack(np.ascontiguousarray(slots[:size, 0]))
    reads = np.ascontiguousarray(slots[size + 1:first, 0]).reshape(count, len(READ_FIELDS))
    for lane in range(lanes):
        o[:, lane] = observe(np.ascontiguousarray(slots[first:, lane]), col, reads)


def _storm_entry(inp, out, lanes):
    """``SpaceWeather.output``: [dt, start, rise, step count k, F10.7, peak] -> [F10.7, S(k dt)]."""
    a, o = numba.carray(inp, (6, lanes)), numba.carray(out, (2, lanes))
    for lane in range(lanes):
        s = (a[3, lane] * a[0, lane] / 3600.0 - a[1, lane]) / a[2, lane]
        o[0, lane] = a[4, lane]
        o[1, lane] = (s * math.exp(1.0 - s) if s > 0 else 0.0) * a[5, lane]


def _features_entry(inp, out, lanes):
    """``TemperatureFeatures``: [nodes, terms, memories, activation, powers (terms), memory of each term (-1:
    none), decays (memories) | T | T_ref | memory (memories, nodes)] -> [features (nodes, terms) | next memory]."""
    head = numba.carray(inp, (4, lanes))
    nodes, terms, memories, activation = int(head[0, 0]), int(head[1, 0]), int(head[2, 0]), head[3, 0]
    first = 4 + 2 * terms + memories
    a = numba.carray(inp, (first + 2 * nodes + memories * nodes, lanes))
    o = numba.carray(out, (nodes * terms + memories * nodes, lanes))
    for lane in range(lanes):
        for j in range(nodes):
            log_r = activation * (1.0 / a[first + nodes + j, lane] - 1.0 / a[first + j, lane])
            for i in range(terms):
                value = math.exp(a[4 + i, 0] * log_r)
                mem = int(a[4 + terms + i, 0])
                if mem >= 0:
                    decay = a[4 + 2 * terms + mem, 0]
                    value = decay * a[first + 2 * nodes + mem * nodes + j, lane] + (1.0 - decay) * value
                    o[nodes * terms + mem * nodes + j, lane] = value
                o[j * terms + i, lane] = value


_ENTRIES = {"step": _step_entry, "observe": _observe_entry, "storm": _storm_entry, "features": _features_entry}
_compiled: dict = {}


def entry(name: str):
    """The C entry point ``name`` (``_ENTRIES``), compiled on first use (numba keeps it on disk)."""
    if name not in _compiled:
        _compiled[name] = numba.cfunc(SIGNATURE, nopython=True, cache=True, error_model="numpy")(_ENTRIES[name])
    return _compiled[name]


class NativeColumn:
    """A float64 ``Column``'s native code called from Python on NumPy arrays or tensors (CPU)."""

    def __init__(self, column):
        self.column, self.params = column, pack(column)

    def _arrays(self, *values):
        return [np.ascontiguousarray(torch.as_tensor(v).detach().to("cpu", torch.float64).numpy()) for v in values]

    def step(self, x, w, u=None) -> torch.Tensor:
        """``Column.step``: x(k+1) (B, 2n + 1)."""
        u = torch.zeros(x.shape[0], self.column.n_nodes) if u is None else u
        x, w, u = self._arrays(x, w, u)
        col = unpack(self.params)
        return torch.from_numpy(np.stack([step(x[b], w[b], u[b], col) for b in range(x.shape[0])]))

    def trajectory(self, x, w, u, reads: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """``trajectory``: the observations (B, K, len(reads)) on the way and the final state."""
        x, w, u, reads = self._arrays(x, w, u, reads)
        y, xk = trajectory(self.params, reads, x, w, u)
        return torch.from_numpy(y), torch.from_numpy(xk)

    def spin_up(self, f107, days: float = 3.0, batch: int = 1) -> torch.Tensor:
        """``Column.spin_up``: the state after ``days`` of quiet conditions from ``Column.initial_state``, the
        clock set back to 0."""
        column = self.column
        f107 = torch.as_tensor(f107, dtype=torch.float64).reshape(-1, 1)
        batch = max(batch, f107.shape[0])
        steps = int(round(days * 86400.0 / column.dt))
        w = torch.cat([f107.expand(batch, 1), torch.zeros(batch, 1, dtype=torch.float64)], 1)
        x = self.trajectory(column.initial_state(batch), w.unsqueeze(1).expand(-1, steps, -1),
                            torch.zeros(batch, steps, column.n_nodes, dtype=torch.float64),
                            np.zeros((0, len(READ_FIELDS))))[1]
        return torch.cat([x[:, :-1], torch.zeros_like(x[:, -1:])], 1)

    def markov(self, reads: np.ndarray, x, w, u, port: str, steps: int, along: str, method: str,
               eps: float) -> torch.Tensor:
        """``markov``: (B, steps, len(reads), width of ``port``)."""
        x, w, u, reads = self._arrays(x, w, u, reads)
        return torch.from_numpy(markov(self.params, reads, x, w, u, 0 if port == "w" else 1, int(steps),
                                       along == "trajectory", method == "fd", float(eps)))
