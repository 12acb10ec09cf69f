"""Contact with samples on the material's surface (``contact_samples``, :mod:`.core.surface_contact`)."""

import numpy as np
import pytest
from press import organ_too_large, press

from sph_tissue_sim.core.errors import ConfigError
from sph_tissue_sim.core.factory import make_model
from sph_tissue_sim.core.material import Material, liver_default
from sph_tissue_sim.core.models import make_block
from sph_tissue_sim.core import contact_kinds
from sph_tissue_sim.core.solver import BALL_CONTACT, Solver, SolverConfig
from sph_tissue_sim.core.surface_contact import nearest_sample_gap, samples_in_reach
from sph_tissue_sim.validation.cases import gives_way, press_and_hold, press_curve

LIVER = Material.from_shear(1800.0, 0.45, 3.0)
LIVER_DEFAULT = liver_default()
SPACING = 0.0075
#: the samples as the surface (with the fixture samples_alone)
SURFACE = {'contact_samples': 3}


@pytest.fixture(autouse=True)
def half_space(monkeypatch):
    """These tests were measured with the half-space far field (the organ's, the default up to
    ORGAN_MAX_FREE free particles, is test_core_compliance.py's)."""
    organ_too_large(monkeypatch)
@pytest.fixture
def samples_alone(monkeypatch):
    """The particles' balls shrunk to a point, so the tool meets the surface samples alone."""
    monkeypatch.setattr(contact_kinds, 'BALL_RADIUS', 1e-3)


def _sample_positions(solver: Solver, x: np.ndarray) -> np.ndarray:
    """Where the samples are for particle positions ``x`` (the kernel's interpolation, in numpy)."""
    s = solver.samples
    rows = np.repeat(np.arange(len(s.w_start) - 1), np.diff(s.w_start))
    return s.offset + np.stack([np.bincount(rows, weights=s.w_val * x[s.w_idx, a], minlength=len(s.offset))
                                for a in range(3)], axis=1)


def _centre(model) -> tuple[float, float]:
    """The middle of the block's top, between four surface particles (press_curve nudges the tool
    1 mm off it)."""
    X = model.positions
    return float(X[:, 0].mean()), float(X[:, 1].mean())


def _block_solver(mode: str = 'global', **config) -> Solver:
    model = make_block(8, 8, 5, spacing=SPACING, fix='bottom')
    return Solver(model, LIVER, SolverConfig(mode=mode, **{**SURFACE, **config}))


@pytest.mark.usefixtures('samples_alone')
def test_samples_sit_half_a_spacing_outside_a_flat_face_and_interpolate_with_a_partition_of_unity():
    solver = _block_solver()
    X = solver.X
    s = solver.samples
    owned = np.diff(s.start)
    top = np.isclose(X[:, 2], X[:, 2].max())
    centre = top & (np.abs(X[:, 0] - X[:, 0].mean()) < 1.6 * SPACING) & (np.abs(X[:, 1] - X[:, 1].mean()) < 1.6 * SPACING)
    inner = np.all(np.abs(X - X.mean(axis=0)) < [2.6 * SPACING, 2.6 * SPACING, 0.6 * SPACING], axis=1)
    assert np.all(owned[centre] == 9)                  # 3 x 3 on each surface particle's patch
    assert np.all(owned[inner] == 0)                   # none in the bulk
    rows = np.repeat(np.arange(len(s.w_start) - 1), np.diff(s.w_start))
    assert np.bincount(rows, weights=s.w_val) == pytest.approx(1.0, abs=1e-12)
    assert s.w_val.min() >= 0.0
    Y = _sample_positions(solver, X)
    mine = np.concatenate([np.arange(s.start[i], s.start[i + 1]) for i in np.flatnonzero(centre)])
    assert Y[mine, 2] == pytest.approx(X[:, 2].max() + 0.5 * SPACING, abs=1e-12)
    # the samples of a face tile it on a grid of spacing / 3
    xs = np.unique(np.round(Y[mine, 0] / (SPACING / 3.0), 6))
    assert np.diff(xs) == pytest.approx(1.0)


@pytest.mark.usefixtures('samples_alone')
def test_the_samples_move_with_a_translated_body():
    solver = _block_solver()
    shift = np.array([0.003, -0.002, 0.001])
    moved = _sample_positions(solver, solver.X + shift)
    assert moved - _sample_positions(solver, solver.X) == pytest.approx(np.broadcast_to(shift, moved.shape))


@pytest.mark.usefixtures('samples_alone')
def test_the_tool_touches_the_material_surface_half_a_spacing_above_the_particles():
    """What the point cloud shows is what the hand feels: contact starts at the surface, half a
    spacing above the particle centres (the ball model touched a whole spacing above them)."""
    X = make_block(8, 8, 5, spacing=SPACING, fix='bottom').positions
    above = np.array([X[:, 0].mean() + 1e-3, X[:, 1].mean() + 5e-4, X[:, 2].max()])
    for gap, touching in ((2e-4, False), (-5e-4, True)):
        solver = _block_solver()
        assert solver.contact_reach == pytest.approx(solver.tool.radius + 0.5 * SPACING)
        tip = above + [0.0, 0.0, solver.tool.radius + 0.5 * SPACING + gap]
        fz = solver.step(tip, 1e-3).force[2]
        assert (fz > 0.0) == touching, (gap, fz)


@pytest.mark.usefixtures('samples_alone')
def test_a_straight_press_between_surface_particles_pushes_them_straight_down():
    """A frictionless tool pressed straight down on a flat face, between four surface particles:
    the surface under it goes down with it (the particle nearest the tool stays under it) and the
    force on the tool has almost no sideways part. As balls, the particles were pushed apart."""
    model = make_block(8, 8, 5, spacing=SPACING, fix='bottom')
    curve = press_curve(model, LIVER, SolverConfig(mode='global', **SURFACE), 0.006, speed=0.02,
                        xy=_centre(model))
    side = curve['sideways'][-1] / curve['normal'][-1]
    print(f'at 6 mm: Fz {curve["normal"][-1]:.3f} N, sideways/normal {side:.3f}, '
          f'slip {curve["slip"][-1] * 1e3:.2f} mm')
    assert curve['normal'][-1] > 0.1
    assert side < 0.05
    assert curve['slip'][-1] < 1e-3


@pytest.mark.usefixtures('samples_alone')
@pytest.mark.parametrize('mode', ['global', 'local'])
def test_pressing_twice_the_tool_radius_deep_the_force_keeps_rising_and_no_particle_passes_over(mode):
    """Pop-through: with particles as balls, a tool pressed about 1.5 radii between surface
    particles pushed them apart and slipped between them (the force fell to nothing). The samples
    are the material between the particles: the force rises with depth all the way."""
    model = make_block(8, 8, 5, spacing=SPACING, fix='bottom')
    curve = press_curve(model, LIVER, SolverConfig(mode=mode, **{**SURFACE, 'far_field': 1.0}), 0.010,
                        speed=0.02, xy=_centre(model))
    fz = curve['normal']
    fall = np.max(np.maximum.accumulate(fz) - fz)
    print(f'{mode}: Fz at 5 / 10 mm {fz[len(fz) // 2 - 1]:.3f} / {fz[-1]:.3f} N, largest fall {fall:.4f} N')
    assert fz[-1] > 1.5 * fz[len(fz) // 2 - 1] > 0.0
    assert fall < 0.02 * fz.max()
    assert curve['over'].max() == 0


def test_more_than_five_samples_per_side_are_refused():
    with pytest.raises(ConfigError, match='contact_samples'):
        SolverConfig(contact_samples=6).validate()


@pytest.mark.usefixtures('samples_alone')
def test_a_shaft_laid_on_the_surface_presses_it_along_its_length():
    """The samples meet any tool shape through its segment: a capsule lying flat, lowered 2 mm into
    the surface, is pushed straight up, harder than its tip alone would be."""
    from press import rotation_y

    forces = {}
    for shape in ('sphere', 'capsule'):
        solver = _block_solver(tool_shape=shape, tool_length=0.03)
        X = solver.X
        rot = rotation_y(np.pi / 2)                 # the shaft along +x
        tip = np.array([X[:, 0].mean() - 0.015, X[:, 1].mean() + 5e-4, X[:, 2].max() + solver.contact_reach])
        for k in range(300):
            res = solver.step(tip - [0.0, 0.0, 0.002 * min(1.0, (k + 1) / 200)], 1e-3, rot)
        forces[shape] = res.force
    print({k: np.round(v, 4) for k, v in forces.items()})
    f = forces['capsule']
    assert f[2] > 2.0 * forces['sphere'][2] > 0.0
    assert np.hypot(f[0], f[1]) < 0.1 * f[2]


@pytest.mark.usefixtures('samples_alone')
def test_through_the_renderer_the_tool_rests_where_the_tissue_holds_the_device_limit():
    """The device pressed 30 mm into the block through the haptic renderer (force limit 1 N):
    the simulated tool stops where the tissue's own force-depth curve (the tool pressed directly)
    reaches 1 N, however deep the device goes (within the creep of a held tissue against one
    pressed at 10 mm/s); the device feels the limit and no particle ends up over the tool."""
    from sph_tissue_sim.haptics.renderer import HapticRenderer, RendererConfig

    model = make_block(8, 8, 5, spacing=SPACING, fix='bottom')
    config = SolverConfig(mode='local', **SURFACE)
    direct = press_curve(model, LIVER, config, 0.012, speed=0.01, xy=_centre(model))
    held = float(np.interp(1.0, direct['normal'], direct['depth']))
    curve = press_curve(model, LIVER, config, 0.03, speed=0.02, xy=_centre(model),
                        renderer=HapticRenderer(RendererConfig(force_limit=1.0)))
    print(f'direct: 1 N at {held * 1e3:.2f} mm; renderer: tool at {curve["tool"][-1] * 1e3:.2f} mm, '
          f'deepest {curve["tool"].max() * 1e3:.2f} mm')
    assert 0.003 < held < 0.012
    assert abs(curve['tool'][-1] - held) < 1e-3
    assert curve['tool'].max() < held + 1.5e-3
    assert curve['device'][-1] == pytest.approx(1.0, abs=1e-3)   # the limit, nearly all along +z
    assert curve['over'].max() == 0


@pytest.mark.usefixtures('samples_alone')
@pytest.mark.slow
def test_the_far_field_does_not_ring_when_a_fine_liver_is_pressed_deep():
    """The far field places the shell at its response to the force, and the force follows the
    shell. On the 30k liver (the half-space far field) the area (k1 h = 7.7 mm) is small next to a
    13 mm press; with the samples as the surface and the previous frame's force as it was, that
    loop rang (up to 1 N from one frame to the next). With the default contact it stays smooth:
    the largest frame-to-frame change 1.2 % of the final force (0.6 % without the far field's
    3 ms low pass, ``FAR_FIELD_TAU``)."""
    model = make_model('liver', n_particles=30000)
    c = press_curve(model, LIVER_DEFAULT, SolverConfig(mode='local'), 0.013, xy=(-0.034, 0.0))
    assert c['unstable_at'] is None
    fz = c['normal']
    assert fz[-1] > 0.5
    assert float(np.abs(np.diff(fz)).max()) < 0.03 * float(fz[-1])


# ----------------------------------------------------------------------------- samples as a backstop
BACKSTOP = {'contact_samples': 3}


def test_backstop_samples_leave_a_shallow_press_to_the_balls():
    """The balls reach half a spacing farther than the samples: until the tool is that deep, the
    press is exactly the ball contact's (same sub-steps, same forces)."""
    model = make_block(8, 8, 5, spacing=SPACING, fix='bottom')
    balls = Solver(model, LIVER, SolverConfig(mode='global', **BALL_CONTACT))
    backstop = Solver(model, LIVER, SolverConfig(mode='global', **BACKSTOP))
    assert backstop.contact_reach == balls.contact_reach
    X = model.positions
    start = np.array([X[:, 0].mean() + 1e-3, X[:, 1].mean() + 5e-4, X[:, 2].max() + balls.contact_reach])
    for k in range(150):
        tip = start - [0.0, 0.0, 0.003 * min(1.0, (k + 1) / 100)]
        a, b = balls.step(tip, 1e-3), backstop.step(tip, 1e-3)
        assert a.substeps == b.substeps
        assert np.array_equal(a.force_raw, b.force_raw), k
    assert a.force[2] > 0.05


def test_backstop_samples_keep_a_deep_press_rising_where_the_balls_give_way():
    """Pressed straight into the default liver's dome (local mode, 10 mm/s): the balls are pushed
    apart and give way by 12 mm; with the samples behind them the first millimetres are the
    balls' and the force keeps rising to 25 mm with no particle over the tool (but for a dip near
    18 mm, where the first-touched particle is pushed past the tool)."""
    model = make_model('liver', n_particles=3670)
    top = (-0.034, 0.0)
    balls = press_curve(model, LIVER_DEFAULT, SolverConfig(**BALL_CONTACT), 0.025, xy=top)
    held = press_curve(model, LIVER_DEFAULT, SolverConfig(**BACKSTOP), 0.025, xy=top)
    f_b, f_h = balls['normal'], held['normal']
    at5 = np.searchsorted(held['depth'], 0.005)
    fall = np.max(np.maximum.accumulate(f_h) - f_h)
    print(f'balls: gives way at {gives_way(balls["depth"], f_b) * 1e3:.1f} mm, Fz at 25 mm {f_b[-1]:.3f} N; '
          f'backstop: Fz at 5 / 25 mm {f_h[at5]:.3f} / {f_h[-1]:.3f} N, largest fall {fall:.3f} N')
    assert gives_way(balls['depth'], f_b) < 0.012 and f_b[-1] < 0.3
    assert f_h[at5] == pytest.approx(f_b[at5], rel=0.05)
    assert f_h[-1] > 2.0 and f_h[-1] > 8.0 * f_h[at5]
    assert fall < 0.15 * f_h[-1]
    assert held['over'].max() == 0


def test_backstop_samples_hold_a_coarse_liver_as_the_balls_do():
    """The 743 liver (11.5 mm spacing, the tool's radius 0.43 of it) pressed 6 mm at its apex: the
    samples alone let the tool sink into the surface layer there; behind the balls they leave the
    press to the balls."""
    model = make_model('liver', n_particles=743)
    X = model.positions
    forces = {}
    for name, config in (('balls', SolverConfig(**BALL_CONTACT)), ('backstop', SolverConfig(**BACKSTOP))):
        solver = Solver(model, LIVER, config)
        start = X[np.argmax(X[:, 2])] + [0.0, 0.0, solver.contact_reach]
        for k in range(120):
            res = solver.step(start - [0.0, 0.0, 0.006 * min(1.0, (k + 1) / 80)], 1e-3)
        forces[name] = res.force
    print(forces)
    f = forces['backstop']
    assert f[2] > 0.2 and f[2] > 3.0 * np.hypot(f[0], f[1])
    assert f[2] == pytest.approx(forces['balls'][2], rel=0.1)


def test_backstop_samples_that_push_widen_the_local_area_so_local_stays_with_global():
    """The samples spread their load over their kernel support: once one pushes the tool the
    local area solves every particle they read and grows (sized for the balls, local mode was
    12 % softer than global at this 10 mm press); before that it is the balls' area, also with
    the samples within a millimetre of the tool."""
    model = make_model('liver', n_particles=3670)
    area = {}
    for name, config in (('balls', SolverConfig(**BALL_CONTACT)), ('backstop', SolverConfig(**BACKSTOP))):
        solver = Solver(model, LIVER_DEFAULT, config)
        res = press(solver, 0.0035, frames=150)
        area[name] = res.n_active
    everyone = np.arange(solver.n, dtype=np.int32)
    gap = nearest_sample_gap(solver.x, solver.v, everyone, solver.n, solver.seg_prev, solver.samples,
                           1e-3)
    assert 0.0 < gap < 1e-3
    assert not solver.samples_push
    assert area['backstop'] == area['balls']
    f = {mode: np.linalg.norm(press_and_hold(model, LIVER_DEFAULT, SolverConfig(mode=mode, **BACKSTOP), 0.010,
                                             xy=(0.03, 0.0)))
         for mode in ('global', 'local')}
    print(f)
    assert f['local'] == pytest.approx(f['global'], rel=0.05)


@pytest.mark.parametrize('within', [0.0, 0.002])
def test_the_owner_test_never_skips_a_sample_near_the_tool_and_skips_most_owners_the_margin_passes(within):
    """samples_in_reach's exact bound (the weights sum to one) against the samples' positions,
    through a smooth dent and a few particles thrown several spacings (torn material)."""
    solver = _block_solver()
    X = solver.X
    rng = np.random.default_rng(3)
    cx, cy = _centre(make_block(8, 8, 5, spacing=SPACING))
    top = X[:, 2].max()
    r2 = (X[:, 0] - cx) ** 2 + (X[:, 1] - cy) ** 2
    x = X.copy()
    x[:, 2] -= 0.008 * np.exp(-r2 / (2 * 0.012 ** 2)) * np.exp(-(top - X[:, 2]) / 0.02)
    x += rng.normal(scale=1e-4, size=x.shape)
    torn = rng.choice(len(x), 5, replace=False)
    x[torn] += rng.normal(scale=3 * SPACING, size=(5, 3))
    x = np.ascontiguousarray(x)
    y = _sample_positions(solver, x)
    s = solver.samples
    owner = np.repeat(np.arange(solver.n), np.diff(s.start))
    seg = np.array([[cx, cy, top + 0.003], [cx, cy, top - 0.004]])
    dist = np.linalg.norm(y - np.array([cx, cy, 0.0]) * [1, 1, 0] - [0, 0, 1] * np.clip(y[:, 2:3], seg[1, 2], seg[0, 2]),
                          axis=1) - s.radius
    near = set(owner[dist < within])
    assert near, 'the tool reaches some samples'
    passing = {i for i in set(owner) if samples_in_reach(i, x, seg, s, within)}
    assert near <= passing
    d_owner = np.linalg.norm(x - np.array([cx, cy, 0.0]) * [1, 1, 0] - [0, 0, 1] * np.clip(x[:, 2:3], seg[1, 2], seg[0, 2]),
                             axis=1)
    loose = {i for i in set(owner) if d_owner[i] < s.radius + within + s.margin}
    assert passing <= loose and len(passing) < len(loose) / 2
