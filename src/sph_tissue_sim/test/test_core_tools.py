"""Tools: the sphere and the capsule, their geometry against analytic answers, and a tilted shaft
pressed into the liver."""

import math

import numpy as np
import pytest

from sph_tissue_sim.core.errors import ConfigError
from sph_tissue_sim.core.factory import make_model
from sph_tissue_sim.core.material import liver_default
from sph_tissue_sim.core.models import make_block
from sph_tissue_sim.core.solver import InvalidInput, Solver, SolverConfig
from sph_tissue_sim.core.tools import NO_ROTATION, TOOLS, Blade, Capsule, Needle, Sphere, make_tool

from press import rotation_y, tilted_shaft_press


def test_tools_are_made_by_name_with_their_dimensions():
    assert set(TOOLS) == {'sphere', 'capsule', 'blade', 'needle'}
    assert isinstance(make_tool('sphere', 0.004), Sphere)
    capsule = make_tool('capsule', 0.004, 0.06)
    assert isinstance(capsule, Capsule) and capsule.length == 0.06 and not capsule.cuts
    blade = make_tool('blade', 0.0005, 0.02)
    assert isinstance(blade, Blade) and blade.cuts and blade.length == 0.02 and not blade.pierces
    needle = make_tool('needle', 0.0005, 0.06)
    assert isinstance(needle, Needle) and needle.pierces and not needle.cuts and needle.length == 0.06
    assert capsule.bounding_radius() == pytest.approx(0.064)
    for bad in (lambda: make_tool('cone', 0.004), lambda: make_tool('sphere', 0.0),
                lambda: make_tool('capsule', 0.004, -0.01)):
        with pytest.raises(ConfigError):
            bad()


def test_capsule_signed_distance_and_normal_match_the_geometry():
    """A capsule of radius 2 mm and shaft 30 mm, tip at p, shaft along the rotated +z axis."""
    cap = Capsule(0.002, 0.03)
    p = np.array([0.01, -0.02, 0.05])
    rot = rotation_y(math.radians(90.0))              # shaft along +x
    points = np.array([
        p + [0.015, 0.0, 0.005],    # beside the middle of the shaft: 5 mm from the axis
        p + [-0.004, 0.0, 0.0],     # beyond the tip, on the axis: 4 mm from the tip's centre
        p + [0.033, 0.0, 0.004],    # beyond the far end: 5 mm from its centre, off axis
        p + [0.010, 0.001, 0.0],    # inside the shaft: 1 mm from the axis
    ])
    d, n = cap.signed_distance(points, p, rot)
    assert d == pytest.approx([0.003, 0.002, 0.003, -0.001], abs=1e-12)
    assert n[0] == pytest.approx([0.0, 0.0, 1.0])
    assert n[1] == pytest.approx([-1.0, 0.0, 0.0])
    assert n[2] == pytest.approx([0.6, 0.0, 0.8])
    assert n[3] == pytest.approx([0.0, 1.0, 0.0])
    # a sphere is a capsule without a shaft, whatever the orientation
    ds, ns = Sphere(0.002).signed_distance(points, p, rot)
    dc, nc = Capsule(0.002, 0.0).signed_distance(points, p, NO_ROTATION)
    assert np.array_equal(ds, dc) and np.array_equal(ns, nc)
    assert ds[1] == pytest.approx(0.002)


@pytest.mark.parametrize('mode', ['local', 'global'])
def test_a_capsule_without_a_shaft_presses_exactly_like_the_sphere(mode):
    model = make_block(8, 8, 5, spacing=0.0075, fix='bottom')
    X = model.positions
    forces = {}
    for shape in ('sphere', 'capsule'):
        solver = Solver(model, liver_default(), SolverConfig(mode=mode, tool_shape=shape, tool_length=0.0))
        start = np.array([X[:, 0].mean() + 1e-3, X[:, 1].mean(), X[:, 2].max() + solver.contact_reach])
        rot = rotation_y(0.3)
        forces[shape] = [solver.step(start - [0.0, 0.0, 0.004 * min(1.0, k / 150)], 1e-3, rot).force
                         for k in range(200)]
    assert np.linalg.norm(forces['sphere'][-1]) > 0.05
    assert np.array_equal(np.array(forces['sphere']), np.array(forces['capsule']))


def test_a_bad_tool_rotation_is_invalid_input_and_changes_nothing():
    model = make_block(6, 6, 4, spacing=0.0075, fix='bottom')
    solver = Solver(model, liver_default(), SolverConfig(tool_shape='capsule', tool_length=0.05))
    x0 = solver.positions.copy()
    for bad in (np.full((3, 3), math.nan), np.eye(2), 'up', 2.0 * np.eye(3), np.diag([1.0, 1.0, -1.0])):
        with pytest.raises(InvalidInput):
            solver.step(model.positions.mean(axis=0), 1e-3, bad)
    assert np.array_equal(solver.positions, x0)


def test_the_shaft_of_a_tilted_capsule_pressed_into_the_liver_pushes_back_normal_to_the_shaft():
    """A 150 mm shaft tilted 20 degrees down towards +x is lowered onto the liver with its tip in
    the air: it first meets the convex upper surface where that surface is parallel to the shaft,
    somewhere along the shaft. A frictionless shaft can only be pushed normal to itself, so the
    force has no component along the shaft and leans towards +x by the tilt (Fx / Fz = tan 20
    for a force in the x-z plane); a sphere at the tip, in the air, feels nothing."""
    model = make_model('liver', n_particles=2000)
    tilt = math.radians(20.0)
    cfg = dict(tool_radius=0.004, tool_length=0.15)
    capsule = Solver(model, liver_default(), SolverConfig(tool_shape='capsule', **cfg))
    sphere = Solver(model, liver_default(), SolverConfig(tool_shape='sphere', **cfg))
    tips, rot, axis = tilted_shaft_press(model.positions, capsule.tool,
                                         capsule.contact_reach - capsule.tool.radius, tilt, 0.004)
    for tip in tips:
        f_cap = capsule.step(tip, 1e-3, rot).force
        f_sph = sphere.step(tip, 1e-3, rot).force
    # where the shaft touches: strictly between its ends
    d, _ = capsule.tool.signed_distance(capsule.positions, tips[-1], rot)
    touching = np.flatnonzero(d < capsule.contact_reach - capsule.tool.radius)
    t = (capsule.positions[touching] - tips[-1]) @ axis / capsule.tool.length
    print(f'capsule force {f_cap} N, {len(touching)} particles touched at t = {t.min():.2f} .. '
          f'{t.max():.2f} of the shaft; sphere {f_sph} N')
    assert len(touching) >= 1 and t.min() > 0.05 and t.max() < 0.95
    norm = float(np.linalg.norm(f_cap))
    assert norm > 0.1 and f_cap[2] > 0.0
    assert abs(f_cap @ axis) < 0.05 * norm                    # normal to the shaft
    assert f_cap[0] / f_cap[2] == pytest.approx(math.tan(tilt), rel=0.25)
    assert not np.any(f_sph)                                  # the tip alone touches nothing


def test_the_dashpot_sees_the_velocity_of_the_shaft_point_that_touches():
    """One particle under the far end of a shaft that swings down about its tip: the contact force
    is k d - c (v_i - v_tool(c)) . n with v_tool the velocity of the touching point (the far end's
    here), not the tip's (zero)."""
    from sph_tissue_sim.core.contact import contact_forces
    from sph_tissue_sim.core.state import Body, Motion, ToolPath, no_touches
    from sph_tissue_sim.core.grasp import no_grip
    from sph_tissue_sim.core.needle import no_shaft
    from sph_tissue_sim.core.surface_contact import no_samples

    X = np.array([[0.1, 0.0, -0.004]])              # 4 mm below the far end of a 100 mm shaft
    seg = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]])
    reach, k, c, inv_mass = 0.005, 300.0, 0.5, 10.0
    for far_end_velocity, tip_velocity in ((-0.2, 0.0), (0.0, 0.0), (0.0, -0.2)):
        seg_vel = np.array([[0.0, 0.0, tip_velocity], [0.0, 0.0, far_end_velocity]])
        react = np.zeros(3)
        body = Body(X, np.zeros(1, dtype=np.bool_), 1.0 / inv_mass, inv_mass)
        motion = Motion(X.copy(), np.zeros((1, 3)), np.zeros((1, 3)))
        tool = ToolPath(seg, seg, True, reach, k, c, no_samples(1), no_touches(), 0.0, np.zeros((1, 3)),
                        np.zeros(1, dtype=np.bool_), 0, no_grip(), no_shaft())
        overlap = contact_forces(body, motion, np.zeros(1, dtype=np.int32), 1, tool, seg, seg_vel,
                                 react)
        # normal n = (0, 0, -1) at t = 1: relative normal velocity -(0 - v_far) . ... = v_far
        expected = k * 0.001 - c * (0.0 - far_end_velocity) * -1.0
        assert overlap == pytest.approx(0.001)
        assert react == pytest.approx([0.0, 0.0, expected], abs=1e-12)


def test_a_fast_twist_moves_the_far_end_of_the_shaft_at_most_max_tool_speed():
    model = make_block(6, 6, 4, spacing=0.0075, fix='bottom')
    solver = Solver(model, liver_default(), SolverConfig(tool_shape='capsule', tool_length=0.1,
                                                         max_tool_speed=1.0))
    tip = model.positions.mean(axis=0) + [0.0, 0.0, 0.1]     # well above the block
    solver.step(tip, 1e-3, rotation_y(0.0))                  # shaft straight up
    res = solver.step(tip, 1e-3, rotation_y(math.pi / 2))    # asked to swing 90 degrees at once
    seg = res.tool_segment
    assert np.linalg.norm(seg[1] - [*tip[:2], tip[2] + 0.1]) <= 1e-3 * 1.0 + 1e-12
    assert np.linalg.norm(seg[1] - seg[0]) == pytest.approx(0.1)      # the shaft keeps its length
    assert res.tool_lag > 0.1
    for _ in range(400):                                     # and gets there at that speed
        res = solver.step(tip, 1e-3, rotation_y(math.pi / 2))
    assert res.tool_segment[1] == pytest.approx(tip + [0.1, 0.0, 0.0], abs=1e-9)
    assert res.tool_lag == 0.0
