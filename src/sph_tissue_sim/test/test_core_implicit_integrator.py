"""The implicit integrator (``integrator: implicit``, :mod:`.core.backward_euler`): its
stiffness product against finite differences of the elastic forces, the symmetry the conjugate
gradients need, and a press on the liver at 16 ms frames against the explicit scheme at 1 ms.
The validation cases (creep, uniaxial, local against global, random poking) run it in
``test_core_validation.py``, the cantilever in ``test_core_beams.py``."""

import numpy as np
import pytest

from sph_tissue_sim.core.errors import ConfigError
from sph_tissue_sim.core.factory import make_model
from sph_tissue_sim.core.backward_euler import _apply
from sph_tissue_sim.core.material import Material
from sph_tissue_sim.core.models import make_block
from sph_tissue_sim.core.solver import Solver, SolverConfig
from sph_tissue_sim.core.tlsph import tlsph_pass
from sph_tissue_sim.validation.cases import first_touch

LIVER = Material.from_shear(1800.0, 0.45, 3.0)


def _deformed(material: Material, hourglass: float, seed: int = 0) -> Solver:
    """A 4 x 4 x 3 block (bottom fixed) with the implicit integrator, its free particles displaced
    at random by up to 0.15 spacings (strains of tens of per cent: the spring is non-linear)."""
    model = make_block(4, 4, 3, spacing=0.005, fix='bottom')
    s = Solver(model, material, SolverConfig(mode='global', integrator='implicit', hourglass=hourglass))
    free = ~model.fixed
    rng = np.random.default_rng(seed)
    s.motion.x[free] += rng.uniform(-0.15, 0.15, size=(free.sum(), 3)) * 0.005
    return s


def _forces(s: Solver, sets, x: np.ndarray) -> np.ndarray:
    """Internal forces [N] of the scheme at positions ``x`` (the scheme's F, A, H left at ``x``)."""
    s.motion.x[:] = x
    tlsph_pass(s.scheme.state(sets, None, 0), s.body, s.motion, sets)
    return s.motion.acc * s.mass


def _operator(s: Solver, sets, integ, p: np.ndarray) -> np.ndarray:
    """``-f(p)`` of the solve's operator: ``(C + dt K + (hg_c + dt hg_k) L) p`` on ``sets.sph``."""
    out = np.zeros_like(p)
    _apply(integ.op, s.motion.x, p, sets, 1.0, np.zeros_like(p), out)
    return out


def test_the_stiffness_product_is_the_derivative_of_the_elastic_forces():
    """Without dashpots and hourglass bonds, the operator at ``dt = 1`` is ``K p = -df/dx p``, the
    exact tangent of the neo-Hookean forces: against central differences at a strongly deformed
    state (relative step 1e-6), for three directions."""
    s = _deformed(Material.from_shear(1800.0, 0.45, 0.0), hourglass=0.0)
    sets = s.area.global_sets(-1)
    sph = sets.sph[:sets.n_sph]
    x0 = s.motion.x.copy()
    rng = np.random.default_rng(1)
    for _ in range(3):
        p = np.zeros_like(x0)
        p[sph] = rng.standard_normal((len(sph), 3))
        eps = 1e-6 * 0.005
        kp_fd = -(_forces(s, sets, x0 + eps * p) - _forces(s, sets, x0 - eps * p)) / (2.0 * eps)
        _forces(s, sets, x0)
        kp = _operator(s, sets, s.backward.integrator(1.0), p)
        scale = np.abs(kp_fd[sph]).max()
        assert scale > 0.0
        np.testing.assert_allclose(kp[sph], kp_fd[sph], rtol=0, atol=1e-6 * scale)


def test_the_solves_operator_is_symmetric_with_dashpots_and_hourglass_bonds():
    """``C + dt K + (hg_c + dt hg_k) L`` column by column on a deformed block: symmetric (to
    rounding), as the conjugate gradients need, and positive definite at this deformation."""
    s = _deformed(LIVER, hourglass=1.0, seed=2)
    sets = s.area.global_sets(-1)
    sph = sets.sph[:sets.n_sph]
    _forces(s, sets, s.motion.x.copy())
    integ = s.backward.integrator(0.016)
    n = len(sph)
    M = np.zeros((3 * n, 3 * n))
    p = np.zeros_like(s.motion.x)
    for k in range(3 * n):
        p[:] = 0.0
        p[sph[k // 3], k % 3] = 1.0
        M[:, k] = _operator(s, sets, integ, p)[sph].ravel()
    scale = np.abs(M).max()
    np.testing.assert_allclose(M, M.T, rtol=0, atol=1e-9 * scale)
    assert np.linalg.eigvalsh(0.5 * (M + M.T)).min() > 0.0


@pytest.mark.parametrize('mode', ['global', 'local'])
def test_the_liver_pressed_at_16_ms_frames_pushes_back_as_the_explicit_scheme_at_1_ms(mode):
    """The 1289-particle liver pressed 8 mm at the top of the dome over 0.8 s and held 0.4 s:
    with the implicit integrator at 16 ms frames (one sub-step each) the force at the end is the
    explicit scheme's at 1 ms frames within 1 % (quasi-static: both are the tissue's equilibrium;
    the implicit one's solve stops at 1e-3 of the velocities)."""
    model = make_model('liver', n_particles=1289)
    forces = {}
    for integrator, frame in (('explicit', 1e-3), ('implicit', 0.016)):
        s = Solver(model, LIVER, SolverConfig(mode=mode, integrator=integrator))
        start = first_touch(model, s.contact_reach, (-0.034, 0.0), (1e-3, 5e-4))
        frames = int(round(1.2 / frame))
        for k in range(frames):
            depth = 0.008 * min(1.0, (k + 1) * frame / 0.8)
            res = s.step(start - np.array([0.0, 0.0, depth]), frame)
        forces[integrator] = res.force
    assert res.substeps == 1
    print(f'{mode}: explicit {forces["explicit"]}, implicit {forces["implicit"]} N')
    assert forces['explicit'][2] > 0.1
    np.testing.assert_allclose(forces['implicit'], forces['explicit'], rtol=0,
                               atol=0.01 * forces['explicit'][2])


def test_the_implicit_integrator_needs_the_tlsph_scheme_and_a_positive_sub_step():
    with pytest.raises(ConfigError, match='integrator implicit needs scheme tlsph'):
        SolverConfig(scheme='paper', integrator='implicit').validate()
    with pytest.raises(ConfigError, match='integrator must be one of'):
        SolverConfig(integrator='backward').validate()
    with pytest.raises(ConfigError, match='implicit_max_dt'):
        SolverConfig(implicit_max_dt=0.0).validate()


def test_a_frame_takes_sub_steps_of_at_most_implicit_max_dt():
    model = make_block(4, 4, 3, spacing=0.005, fix='bottom')
    s = Solver(model, LIVER, SolverConfig(mode='global', integrator='implicit', implicit_max_dt=0.004))
    assert s.dt_bounds == {'implicit': 0.004}
    assert s.step(None, 0.016).substeps == 4
    assert s.step(None, 0.001).substeps == 1


def test_the_threaded_solve_is_bit_identical_to_the_serial_one():
    """``parallel_min_particles`` moves the solve's passes (and the scheme's) onto numba's thread
    pool; both loops are gathers in the serial order, so 30 frames of 16 ms pressing the 1289
    liver leave bit-identical positions and forces. (With one numba thread both runs are serial.)"""
    model = make_model('liver', n_particles=1289)
    runs = []
    for par in (0, 1):
        s = Solver(model, LIVER, SolverConfig(mode='global', integrator='implicit', parallel_min_particles=par))
        start = first_touch(model, s.contact_reach, (-0.034, 0.0), (1e-3, 5e-4))
        forces = [s.step(start - np.array([0.0, 0.0, 0.0003 * (k + 1)]), 0.016).force_raw.copy()
                  for k in range(30)]
        runs.append((s.positions.copy(), np.array(forces)))
    assert np.array_equal(runs[0][0], runs[1][0])
    assert np.array_equal(runs[0][1], runs[1][1])
    assert runs[0][1][-1, 2] > 0.1
