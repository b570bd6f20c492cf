"""The constants of the reduced thermosphere column (``rcotorch.models.thermosphere``), each with its source,
kept apart so that the column's torch model and its native kernels (``thermosphere_native``) read the same
values."""

from __future__ import annotations

from dataclasses import dataclass

# --- physical constants (CODATA 2018; exact SI values where defined) ---------------------------------------------
K_B = 1.380649e-23            # Boltzmann constant [J/K]
AMU = 1.66053906660e-27       # atomic mass unit [kg]
H_PLANCK = 6.62607015e-34     # [J s]
C_LIGHT = 2.99792458e8        # [m/s]
EV = 1.602176634e-19          # [J]

# --- Earth (U.S. Standard Atmosphere 1976) --------------------------------------------------------------------
G0 = 9.80665                  # standard gravity [m/s^2]
R_EARTH = 6.356766e6          # effective Earth radius of g(z) = g0 (R/(R+z))^2 [m]

# --- species: O, O2, N2 (this order everywhere) ---------------------------------------------------------------
SPECIES = ("O", "O2", "N2")
MASS = (15.9994 * AMU, 31.9988 * AMU, 28.0134 * AMU)   # IUPAC standard atomic weights
CP_PER_PARTICLE = (2.5, 3.5, 3.5)                       # c_p / k per particle: monatomic 5/2, diatomic 7/2
#: Number densities [m^-3] and temperature [K] at 100 km: U.S. Standard Atmosphere 1976, Table VIII (the
#: MSIS-like mean atmosphere; Ar and He left out).
N_100KM = (4.298e17, 2.151e18, 9.210e18)
T_100KM = 195.08

# --- heat conduction ------------------------------------------------------------------------------------------
#: kappa = A T^s [W/(m K)]: GITM's A(O) = 5.6e-4 (src/ModInputs.f90, #THERMALCONDUCTION; Banks and Kockarts
#: 1973 give 5.6e-4 for N2 and 7.6e-4 for O) and s = 0.73, inside the range 0.69-0.75 quoted there
#: (Pawlowski and Ridley 2009).
KAPPA_A = 5.6e-4
KAPPA_S = 0.73

# --- NO 5.3 um cooling, Kockarts (1980, Geophys. Res. Lett. 7, 137) ---------------------------------------------
NO_WAVENUMBER = 1876.0e2      # NO(v=1 -> 0) band centre 1876 cm^-1 (5.33 um) [1/m]
NO_HNU = H_PLANCK * C_LIGHT * NO_WAVENUMBER             # photon energy, 3.73e-20 J
NO_THETA = NO_HNU / K_B                                 # h nu / k = 2699 K (Kockarts' "2700 K")
NO_A10 = 13.3                 # Einstein coefficient of NO(v=1) [1/s]
NO_K_O = 6.5e-17              # NO(v=0) + O -> NO(v=1) + O, 6.5e-11 cm^3/s [m^3/s]

# --- NO chemistry (effective) ---------------------------------------------------------------------------------
W_ION = 35.0 * EV             # mean energy per ion pair in N2, O2, O (Rees 1989, Physics and Chemistry of the
#                               Upper Atmosphere)
NO_YIELD = 1.0                # *effective* NO per ion pair made in N2 (N2 dissociation, then N(2D) + O2 -> NO + O)
NO_LIFETIME = 19.0 * 3600.0   # NO lifetime in the lower thermosphere, about 19 h (Barth et al. 1988)
NO_LOSS_Z, NO_LOSS_H = 120e3, 20e3   # *effective*: N(4S) + NO -> N2 + O speeds the loss upward as N(4S) grows:
#                               1/tau_NO = (1 + exp((z - 120 km) / 20 km)) / NO_LIFETIME: 12 h at 110 km, 1 h at 180 km
STORM_PARTICLE_SHARE = 0.1    # *effective* share of the storm energy in ionizing particles (the rest is Joule
#                               heating; Knipp et al. 2004 put particles at about a fifth of the total)
NO_UNIT = 1e12                # the state holds n_NO in units of 1e12 m^-3

# --- diurnal cycle (effective) --------------------------------------------------------------------------------
#: A single column has no horizontal winds, which in 3-D carry dayside heat to the night side: heated with the
#: local cos(chi) it swings by ~700 K between day and night instead of the observed ~30 per cent, with the
#: maximum near 14 LT (Jacchia 1970). The column is therefore heated with the daily-mean insolation at equinox,
#: cos(latitude)/pi, times 1 + A cos(2 pi (LT - 14 h) / 24 h), absorbed along the path cos(chi) = MU_PATH.
DIURNAL_AMPLITUDE = 0.4
PEAK_LOCAL_TIME = 14.0
MU_PATH = 0.5


@dataclass(frozen=True)
class Band:
    """A band of the solar spectrum absorbed as one Chapman layer.

    flux: energy flux at 1 AU for F10.7 = 150 [W/m^2]; per_sfu: its fractional change per solar flux unit of
    F10.7; efficiency: the share of the absorbed energy that heats the neutrals; sigma: absorption cross sections
    of (O, O2, N2) [m^2].
    """

    name: str
    flux: float
    per_sfu: float
    efficiency: float
    sigma: tuple[float, float, float]


#: Three *effective* bands. Fluxes: solar irradiance integrated over each band (Hinteregger et al. 1981; EUVAC,
#: Richards et al. 1994; soft X-rays after Solomon and Qian 2005), linear in F10.7 between solar minimum and
#: maximum. Cross sections: band averages of the photoabsorption cross sections (Fennelly and Torr 1992; the O2
#: Schumann-Runge continuum after Banks and Kockarts 1973). Efficiencies: neutral heating efficiencies (Torr et
#: al. 1980, Roble et al. 1987: 0.4-0.55 for EUV; about 0.3 for the O2 continuum).
BANDS = (
    Band("XUV 0.5-10 nm", 1.0e-3, 0.008, 0.45, (0.6e-22, 1.2e-22, 1.0e-22)),
    Band("EUV 10-105 nm", 5.0e-3, 0.005, 0.50, (1.2e-21, 2.2e-21, 2.0e-21)),
    Band("SRC 125-175 nm", 4.0e-3, 0.001, 0.30, (0.0, 1.0e-21, 0.0)),
)
