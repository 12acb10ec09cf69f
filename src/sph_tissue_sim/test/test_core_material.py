"""Kelvin-Voigt material: moduli, the paper's nu = 0 preset, YAML loading and rejected values."""

import math

import pytest

from sph_tissue_sim.core.errors import ConfigError
from sph_tissue_sim.core.material import Material, load_material


def test_moduli_follow_isotropic_elasticity():
    m = Material(E=5220.0, nu=0.45, eta_shear=3.0, eta_bulk=29.0, rho=1060.0)
    assert m.G == pytest.approx(1800.0)
    assert m.K == pytest.approx(17400.0)
    assert m.wave_speed == pytest.approx(math.sqrt((17400.0 + 2400.0) / 1060.0))


def test_paper_preset_is_nu_zero_with_both_moduli_e():
    # eq. 3: S = E e + eta de/dt and sigma_kk = E eps_kk + eta deps_kk/dt  <=>  2G = 3K = E
    m = Material.paper_preset(E=3000.0, eta=12.0, rho=1000.0)
    assert m.nu == 0.0
    assert 2.0 * m.G == pytest.approx(3000.0)
    assert 3.0 * m.K == pytest.approx(3000.0)
    assert 2.0 * m.eta_shear == pytest.approx(12.0)
    assert 3.0 * m.eta_bulk == pytest.approx(12.0)


def test_liver_defaults_load_from_yaml():
    m = load_material(name='liver')
    assert m.G == pytest.approx(1800.0)
    assert 0.45 <= m.nu <= 0.49
    assert m.rho == pytest.approx(1060.0)
    assert m.eta_shear > 0.0 and m.eta_bulk > 0.0
    assert load_material(name='paper').nu == 0.0


@pytest.mark.parametrize('kwargs', [
    dict(E=0.0, nu=0.3, eta_shear=1.0, eta_bulk=1.0, rho=1000.0),
    dict(E=-5.0, nu=0.3, eta_shear=1.0, eta_bulk=1.0, rho=1000.0),
    dict(E=5.0, nu=0.5, eta_shear=1.0, eta_bulk=1.0, rho=1000.0),
    dict(E=5.0, nu=0.3, eta_shear=-1.0, eta_bulk=1.0, rho=1000.0),
    dict(E=5.0, nu=0.3, eta_shear=1.0, eta_bulk=1.0, rho=0.0),
    dict(E=float('nan'), nu=0.3, eta_shear=1.0, eta_bulk=1.0, rho=1000.0),
])
def test_material_rejects_non_physical_values(kwargs):
    with pytest.raises(ConfigError):
        Material(**kwargs)


def test_load_material_rejects_unknown_name_and_missing_file(tmp_path):
    with pytest.raises(ConfigError, match='no material'):
        load_material(name='granite')
    with pytest.raises(ConfigError, match='not found'):
        load_material(tmp_path / 'missing.yaml')
