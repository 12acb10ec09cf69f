"""Viscoelastic material: Kelvin-Voigt (paper eqs. 1-3, generalised to E, nu), optionally with
stress relaxation (a Prony series).

Deviatoric and volumetric parts each have a spring and a dashpot in parallel:

    S_ab    = 2 G e_ab + 2 eta_shear de_ab/dt            (deviatoric stress)
    sigma_kk = 3 K eps_kk + 3 eta_bulk deps_kk/dt         (trace of the stress)

The paper writes ``S = E e + eta de/dt`` and ``sigma_kk = E eps_kk + eta deps_kk/dt``, which is the
special case ``2G = 3K = E`` (nu = 0), ``2 eta_shear = 3 eta_bulk = eta``: :meth:`Material.paper_preset`.

With ``prony`` terms ``(g_k, tau_k)`` the spring relaxes (quasi-linear viscoelasticity, Fung): its
stress is the elastic stress of the instantaneous moduli ``G, K`` convolved with the reduced
relaxation function

    g(t) = g_inf + sum_k g_k exp(-t / tau_k),    g_inf = 1 - sum_k g_k > 0,

so a held strain's stress falls from ``G`` to ``g_inf G`` (:meth:`Material.relaxation`).

With ``stiffening`` ``b > 0`` the spring stiffens with the isochoric first invariant
``I1b = J^(-2/3) tr(F^T F)`` (an exponential law, Demiray's form added to the neo-Hookean spring):

    psi = psi_neo-Hookean + G / (2 b) (exp(b (I1b - 3)) - 1 - b (I1b - 3)),

whose extra term is of third order in the strain: the small-strain moduli stay ``G, K``, and the
shear stiffness grows as ``exp(b (I1b - 3))`` (uniaxial stretch 1 + e: ``I1b - 3 ~ 3 e^2``) up to
``tlsph.STIFFENING_CAP`` times ``G``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

from .errors import ConfigError


#: the largest strain-stiffening exponent b (at b = 50 a 10 % uniaxial stretch is 4 times stiffer)
MAX_STIFFENING = 50.0
#: [J/m^2] the largest fracture toughness accepted
MAX_TOUGHNESS = 1e5
#: [N/m] the largest hold of a needle's shaft accepted
MAX_NEEDLE_HOLD = 1e4


@dataclass(frozen=True)
class Material:
    """Isotropic Kelvin-Voigt solid, its spring optionally relaxing.

    Attributes:
        E: Young's modulus [Pa] (> 0); with ``prony`` the instantaneous one.
        nu: Poisson's ratio [-], 0 <= nu < 0.5 (explicit time steps shrink as nu -> 0.5).
        eta_shear: shear viscosity [Pa s] (>= 0), the dashpot of the deviatoric part.
        eta_bulk: volumetric viscosity [Pa s] (>= 0), the dashpot of the trace part.
        rho: density [kg/m^3] (> 0).
        name: label for logs.
        prony: ``((g_1, tau_1), ...)``: the spring's relaxation, weights ``g_k > 0`` of the
            instantaneous moduli (summing below 1) and time constants ``tau_k > 0`` [s]; empty: none.
        stiffening: the exponent ``b`` [-] of the strain-stiffening term, 0 <= b <= 50 (0: none).
        toughness: the fracture toughness ``G_c`` [J/m^2] (> 0): the work a blade pays per unit area
            of the crack it opens (porcine liver about 190-225 for a blade).
        needle_hold: ``(static, dynamic)`` [N/m]: the most a metre of a needle's inserted shaft
            holds the tissue with along its axis, sticking and sliding, ``0 <= dynamic <= static``
            (:mod:`.needle`).
    """

    E: float
    nu: float
    eta_shear: float
    eta_bulk: float
    rho: float
    name: str = 'custom'
    prony: tuple = ()
    stiffening: float = 0.0
    toughness: float = 200.0
    needle_hold: tuple = (6.0, 4.0)

    def __post_init__(self) -> None:
        for key in ('E', 'nu', 'eta_shear', 'eta_bulk', 'rho'):
            value = getattr(self, key)
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ConfigError(f'material {self.name}: {key} must be a finite number, got {value!r}')
        if self.E <= 0.0:
            raise ConfigError(f'material {self.name}: E must be > 0 Pa, got {self.E}')
        if self.rho <= 0.0:
            raise ConfigError(f'material {self.name}: rho must be > 0 kg/m^3, got {self.rho}')
        if not 0.0 <= self.nu < 0.4999:
            raise ConfigError(f'material {self.name}: nu must be in [0, 0.4999), got {self.nu}')
        if self.eta_shear < 0.0 or self.eta_bulk < 0.0:
            raise ConfigError(f'material {self.name}: viscosities must be >= 0 Pa s, got '
                              f'eta_shear={self.eta_shear}, eta_bulk={self.eta_bulk}')
        terms = []
        for term in self.prony:
            try:
                g, tau = (float(v) for v in term)
            except (TypeError, ValueError):
                raise ConfigError(f'material {self.name}: a prony term is a pair (g, tau), got {term!r}') from None
            if not (math.isfinite(g) and g > 0.0):
                raise ConfigError(f'material {self.name}: a prony weight g must be > 0, got {g}')
            if not (math.isfinite(tau) and tau > 0.0):
                raise ConfigError(f'material {self.name}: a prony time constant tau must be > 0 s, got {tau}')
            terms.append((g, tau))
        if sum(g for g, _ in terms) >= 1.0:
            raise ConfigError(f'material {self.name}: the prony weights must sum below 1 (the spring '
                              f'keeps g_inf = 1 - sum g > 0 of its stiffness), got {sum(g for g, _ in terms):g}')
        object.__setattr__(self, 'prony', tuple(terms))
        b = self.stiffening
        if not (isinstance(b, (int, float)) and math.isfinite(b) and 0.0 <= b <= MAX_STIFFENING):
            raise ConfigError(f'material {self.name}: stiffening must be in [0, {MAX_STIFFENING:g}] (below 0 the '
                              f'spring would soften with strain), got {b!r}')
        object.__setattr__(self, 'stiffening', float(b))
        g_c = self.toughness
        if not (isinstance(g_c, (int, float)) and math.isfinite(g_c) and 0.0 < g_c <= MAX_TOUGHNESS):
            raise ConfigError(f'material {self.name}: toughness must be in (0, {MAX_TOUGHNESS:g}] J/m^2, got {g_c!r}')
        object.__setattr__(self, 'toughness', float(g_c))
        try:
            hold_s, hold_d = (float(v) for v in self.needle_hold)
        except (TypeError, ValueError):
            raise ConfigError(f'material {self.name}: needle_hold is a pair (static, dynamic) [N/m], '
                              f'got {self.needle_hold!r}') from None
        if not (math.isfinite(hold_s) and math.isfinite(hold_d) and 0.0 <= hold_d <= hold_s <= MAX_NEEDLE_HOLD):
            raise ConfigError(f'material {self.name}: needle_hold must be 0 <= dynamic <= static <= '
                              f'{MAX_NEEDLE_HOLD:g} N/m, got ({hold_s}, {hold_d})')
        object.__setattr__(self, 'needle_hold', (hold_s, hold_d))

    @property
    def beyond_kelvin_voigt(self) -> bool:
        """Whether the spring relaxes or stiffens (only the tlsph scheme's explicit solver models it)."""
        return bool(self.prony) or self.stiffening > 0.0

    @property
    def G(self) -> float:
        """Shear modulus [Pa]: E / (2 (1 + nu))."""
        return self.E / (2.0 * (1.0 + self.nu))

    @property
    def K(self) -> float:
        """Bulk modulus [Pa]: E / (3 (1 - 2 nu))."""
        return self.E / (3.0 * (1.0 - 2.0 * self.nu))

    @property
    def lame_lambda(self) -> float:
        """First Lame parameter [Pa]: K - 2G/3."""
        return self.K - 2.0 * self.G / 3.0

    @property
    def wave_speed(self) -> float:
        """P-wave speed [m/s]: sqrt((K + 4G/3) / rho), the CFL speed."""
        return math.sqrt((self.K + 4.0 * self.G / 3.0) / self.rho)

    @property
    def eta_longitudinal(self) -> float:
        """Viscosity of a 1D longitudinal motion [Pa s]: eta_bulk + 4/3 eta_shear (viscous dt bound)."""
        return self.eta_bulk + 4.0 * self.eta_shear / 3.0

    @property
    def g_inf(self) -> float:
        """[-] the fraction of the instantaneous stiffness a held strain keeps: 1 - sum g_k."""
        return 1.0 - sum(g for g, _ in self.prony)

    def relaxation(self, t: float) -> float:
        """[-] the reduced relaxation function g(t): a strain applied at 0 and held has g(t) of
        its instantaneous elastic stress at t >= 0."""
        return self.g_inf + sum(g * math.exp(-t / tau) for g, tau in self.prony)

    @property
    def retardation_time(self) -> float:
        """Shear retardation time eta_shear / G [s] (creep time constant)."""
        return self.eta_shear / self.G

    @classmethod
    def paper_preset(cls, E: float, eta: float, rho: float = 1060.0) -> 'Material':
        """The paper's eq. 3: both moduli E and one viscosity eta, i.e. nu = 0 (2G = 3K = E)."""
        return cls(E=float(E), nu=0.0, eta_shear=float(eta) / 2.0, eta_bulk=float(eta) / 3.0,
                   rho=float(rho), name='paper')

    @classmethod
    def from_shear(cls, G: float, nu: float, eta_shear: float, eta_bulk: float | None = None,
                   rho: float = 1060.0, name: str = 'custom') -> 'Material':
        """Build from the shear modulus; ``eta_bulk`` defaults to the same retardation time (K tau)."""
        if not (math.isfinite(G) and G > 0.0):
            raise ConfigError(f'material {name}: G must be > 0 Pa, got {G}')
        if not 0.0 <= nu < 0.4999:
            raise ConfigError(f'material {name}: nu must be in [0, 0.4999), got {nu}')
        E = 2.0 * G * (1.0 + nu)
        if eta_bulk is None:
            K = E / (3.0 * (1.0 - 2.0 * nu))
            eta_bulk = K * eta_shear / G
        return cls(E=E, nu=float(nu), eta_shear=float(eta_shear), eta_bulk=float(eta_bulk),
                   rho=float(rho), name=name)

    def with_viscosity_scale(self, factor: float) -> 'Material':
        """A copy with both viscosities multiplied by ``factor``."""
        return replace(self, eta_shear=self.eta_shear * factor, eta_bulk=self.eta_bulk * factor)


DEFAULT_MATERIALS_YAML = Path(__file__).resolve().parents[2] / 'config' / 'materials.yaml'


def load_material(yaml_path: str | Path | None = None, name: str = 'liver') -> Material:
    """Load material ``name`` from a YAML file (default: the package's ``config/materials.yaml``).

    Each entry gives ``rho`` and either (``E``, ``nu``) or (``G``, ``nu``), plus ``eta_shear`` and
    optionally ``eta_bulk`` [Pa s] (default: same retardation time as the shear part), ``prony``
    (a list of ``[g, tau]``, the spring's relaxation), ``stiffening`` (its exponent ``b``) and
    ``toughness`` [J/m^2] and ``needle_hold`` ``[static, dynamic]`` [N/m]; or ``preset: paper`` with ``E``, ``eta``, ``rho``.

    Raises:
        ConfigError: missing file, unknown name or invalid values.
    """
    import yaml

    path = Path(yaml_path) if yaml_path is not None else DEFAULT_MATERIALS_YAML
    if not path.is_file():
        # installed layout: share/sph_tissue_sim/config/materials.yaml
        raise ConfigError(f'material file not found: {path}')
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f'{path}: invalid YAML: {exc}') from exc
    mats = data.get('materials', data)
    if name not in mats:
        raise ConfigError(f'{path}: no material {name!r}; available: {sorted(mats)}')
    entry = dict(mats[name])
    try:
        return replace(_material_entry(entry, name),
                       needle_hold=tuple(entry.get('needle_hold', Material.needle_hold)))
    except (KeyError, TypeError, ValueError) as exc:
        if isinstance(exc, ConfigError):
            raise
        raise ConfigError(f'{path}: material {name!r} is incomplete or invalid: {exc!r}') from exc


def _material_entry(entry: dict, name: str) -> Material:
    """The material of one ``materials.yaml`` entry (but its needle's hold)."""
    g_c = float(entry.get('toughness', Material.toughness))
    if entry.get('preset') == 'paper':
        mat = Material.paper_preset(float(entry['E']), float(entry['eta']), float(entry.get('rho', 1060.0)))
        return Material(mat.E, mat.nu, mat.eta_shear, mat.eta_bulk, mat.rho, name,
                        tuple(tuple(term) for term in entry.get('prony') or ()),
                        float(entry.get('stiffening', 0.0)), g_c)
    nu = float(entry['nu'])
    rho = float(entry['rho'])
    eta_s = float(entry['eta_shear'])
    eta_b = entry.get('eta_bulk')
    prony = tuple(tuple(term) for term in entry.get('prony') or ())
    b = float(entry.get('stiffening', 0.0))
    if 'G' in entry:
        mat = Material.from_shear(float(entry['G']), nu, eta_s,
                                  None if eta_b is None else float(eta_b), rho, name)
        return Material(mat.E, mat.nu, mat.eta_shear, mat.eta_bulk, mat.rho, name, prony, b, g_c)
    E = float(entry['E'])
    if eta_b is None:
        G = E / (2.0 * (1.0 + nu))
        eta_b = E / (3.0 * (1.0 - 2.0 * nu)) * eta_s / G
    return Material(E, nu, eta_s, float(eta_b), rho, name, prony, b, g_c)


def liver_default() -> Material:
    """The liver defaults of ``config/materials.yaml`` (G = 1.8 kPa, nu = 0.45, 3 Pa s, 1060 kg/m^3)."""
    try:
        return load_material(None, 'liver')
    except ConfigError:
        return Material.from_shear(1800.0, 0.45, 3.0, None, 1060.0, 'liver')
