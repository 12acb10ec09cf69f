"""The needle: a dent up to the puncture force, the drop as it enters, then a force that grows with
the inserted depth (Okamura's three phases); its shaft's stick-slip hold against the analytic
spring and caps; out again above its entry point, the tissue back at rest."""

import math
from dataclasses import replace

import numpy as np
import pytest

from sph_tissue_sim.core.errors import ConfigError
from sph_tissue_sim.core.material import Material, liver_default
from sph_tissue_sim.core.models import make_block
from sph_tissue_sim.core.needle import (INSERTED, OUTSIDE, TOUCHING, cut_force, no_shaft, puncture_force,
                                        shaft_hold)
from sph_tissue_sim.core.solver import Solver, SolverConfig
from sph_tissue_sim.core.state import Body, Motion, Shaft

RADIUS, LENGTH = 0.0005, 0.06
SPACING = 0.005
DT = 1e-3
SPEED = 0.01          # [m/s] insertion and withdrawal


def needle_solver(mode='local', material=None, n=(8, 8, 8)):
    model = make_block(*n, spacing=SPACING)
    cfg = SolverConfig(mode=mode, tool_shape='needle', tool_radius=RADIUS, tool_length=LENGTH)
    return Solver(model, material or liver_default(), cfg), model


def insert(solver, xy, travel=0.02, hold=200, back=True, speed=SPEED):
    """Down from 3 mm above the top by ``travel`` [m] below it at ``speed`` [m/s], held ``hold``
    frames, drawn back out; per frame (tip height above the top [m], axial force [N], state, depth [m])."""
    top = solver.X[:, 2].max()
    z = [top + 0.003 - speed * DT * k for k in range(int(round((travel + 0.003) / (speed * DT))) + 1)]
    z += [z[-1]] * hold
    if back:
        z += [z[-1] + speed * DT * k for k in range(1, len(z) - hold)]
    out = []
    for zz in z:
        r = solver.step(np.array([xy[0], xy[1], zz]), DT, np.eye(3))
        out.append((zz - top, float(r.force_raw[2]), solver.needle_state(), solver.needle_depth()))
    return np.array(out)


def test_puncture_and_cutting_forces_follow_the_toughness_and_the_diameter():
    assert puncture_force(200.0, 0.001) == pytest.approx(math.pi * 0.2)
    assert cut_force(200.0, 0.001) == pytest.approx(0.2)
    assert puncture_force(100.0, 0.002) == pytest.approx(puncture_force(200.0, 0.001))


@pytest.mark.parametrize('mode, xy', [('local', (0.02, 0.02)), ('global', (0.0225, 0.0225))],
                         ids=['local-between-columns', 'global-on-a-column'])
def test_insertion_rises_to_the_puncture_force_drops_then_grows_with_depth(mode, xy):
    """On a particle's column or between four, the tip dents the surface until the tissue pushes
    back with pi d G_c; then it enters, the force drops, and grows with the depth as the shaft's
    hold (4 N/m sliding) adds to the tip's cut (G_c d)."""
    solver, _ = needle_solver(mode)
    mat = solver.material
    f_p, f_c = puncture_force(mat.toughness, 2 * RADIUS), cut_force(mat.toughness, 2 * RADIUS)
    run = insert(solver, xy, back=False)
    height, force, state, depth = run.T
    k = int(np.argmax(state == INSERTED))
    assert k > 0 and np.all(state[k:] == INSERTED)
    assert force[k - 1] < f_p <= force[k]                        # punctured at the threshold
    assert np.all(state[:k][height[:k] < 0.0] == TOUCHING)       # dented, not slipped in
    dent = height[k]
    assert -0.012 < dent < -0.003                                # a dent of a few mm
    assert np.all(np.diff(force[:k][height[:k] < -0.001]) > -0.01)   # the dent's force rises
    assert force[k + 5] < 0.5 * f_p                              # the drop
    # inserted: the tip's cut and the shaft's hold, growing with depth
    later = (depth > 0.003)
    assert np.all(force[later] > 0.9 * f_c)
    slope = np.polyfit(depth[later], force[later], 1)[0]
    assert 0.5 * mat.needle_hold[1] < slope < 2.0 * mat.needle_hold[0]
    assert depth[-1] == pytest.approx(-height[-1] + dent, abs=1e-6)


def test_a_tougher_tissue_punctures_later_at_a_higher_force():
    soft, _ = needle_solver('local')
    tough, _ = needle_solver('local', replace(liver_default(), toughness=260.0))
    peaks = []
    for solver in (soft, tough):
        run = insert(solver, (0.02, 0.02), travel=0.02, hold=0, back=False)
        k = int(np.argmax(run[:, 2] == INSERTED))
        assert k > 0
        peaks.append((run[k, 1], run[k, 0]))
        assert run[k - 1, 1] < puncture_force(solver.material.toughness, 2 * RADIUS) <= run[k, 1]
    assert peaks[1][0] > 1.25 * peaks[0][0] and peaks[1][1] < peaks[0][1] - 0.002


def test_withdrawn_needle_is_outside_again_and_the_tissue_comes_to_rest():
    """In 20 mm, held, out: no energy gained (the hand did positive work), outside above the entry,
    the tissue at rest after."""
    solver, _ = needle_solver('global')
    run = insert(solver, (0.02, 0.02))
    height, force, state, depth = run.T
    k = int(np.argmax(state == INSERTED))
    entry = height[k]
    out = height > entry + 1e-4
    assert np.all(state[np.flatnonzero(out)[np.flatnonzero(out) > k]] != INSERTED)
    # the hand's work on the tissue: the tool moves dz, the tissue pushes it with force
    work = -np.sum(force[1:] * np.diff(height))
    assert work > 0.0
    for _ in range(800):
        solver.step(None, DT)
    assert solver.needle_state() == OUTSIDE
    assert np.abs(solver.velocities).max() < 1e-3
    assert solver.displacement().max() < 5e-4
    solver.reset()
    assert solver.needle_state() == OUTSIDE and solver.needle_depth() == 0.0


def hold_shaft(static, dynamic, grip_norm=1.0):
    n = 1
    return Shaft(True, True, np.zeros(3), np.array([0.0, 0.0, 1.0]), 0.0, 0.003, 0.0, 300.0, 0.005, grip_norm,
                 static, dynamic, np.zeros(n), np.zeros(n, dtype=np.bool_), np.zeros(n, dtype=np.bool_),
                 np.zeros(0, dtype=np.int32), np.zeros(0), np.zeros(3), 0)


def test_the_shaft_holds_a_particle_by_a_spring_until_it_slips_then_by_the_dynamic_hold():
    """One particle 1 mm off the axis (weight (1 - 1/25)^2 of the grip), the needle drawn up in
    1 mm steps: the spring k_c w x until the static cap, then the dynamic cap while it slides; a
    stop lets it stick again."""
    from sph_tissue_sim.core.grasp import no_grip
    from sph_tissue_sim.core.state import ToolPath
    from sph_tissue_sim.core.surface_contact import no_samples
    from sph_tissue_sim.core.state import no_touches

    k_c = 300.0
    w = (1.0 - (0.001 / 0.005) ** 2) ** 2
    static, dynamic = 6.0, 4.0
    sh = hold_shaft(static, dynamic)
    X = np.array([[0.001, 0.0, 0.05]])
    body = Body(X, np.zeros(1, dtype=np.bool_), 1.0, 1.0)
    forces = []
    for step in list(range(0, 40)) + [39] * 3:
        tip = 0.001 * step
        seg = np.array([[0.0, 0.0, tip], [0.0, 0.0, tip + 0.06]])
        tool = ToolPath(seg, seg, True, 0.003, k_c, 0.0, no_samples(1), no_touches(), 0.0, np.zeros((1, 3)),
                        np.zeros(1, dtype=np.bool_), 0, no_grip(), sh)
        motion = Motion(X.copy(), np.zeros((1, 3)), np.zeros((1, 3)))
        react = np.zeros(3)
        shaft_hold(body, motion, np.zeros(1, dtype=np.int32), 1, tool, seg, react)
        forces.append(motion.acc[0, 2])
        assert react[2] == pytest.approx(-motion.acc[0, 2])
    forces = np.array(forces)
    travel = 0.001 * np.arange(40)
    sticking = k_c * w * travel <= static * w
    assert np.allclose(forces[:40][sticking], k_c * w * travel[sticking])
    slip = int(np.argmin(k_c * w * travel <= static * w))      # the first step past the static cap
    assert forces[slip] == pytest.approx(static * w)              # it breaks loose at the static cap
    assert np.allclose(forces[slip + 1:40], dynamic * w)          # and slides at the dynamic one
    assert np.allclose(forces[40:], dynamic * w)        # stopped: held where it slid to, and sticks
    assert not sh.sliding[0]


def test_needle_needs_the_tlsph_scheme_and_a_valid_hold():
    model = make_block(4, 4, 4, spacing=SPACING)
    for scheme in ('paper', 'mass_spring'):
        with pytest.raises(ConfigError, match='needle'):
            Solver(model, liver_default(), SolverConfig(scheme=scheme, tool_shape='needle', tool_radius=RADIUS))
    for bad in ((4.0, 6.0), (-1.0, 0.0), (float('nan'), 1.0), (1.0,)):
        with pytest.raises(ConfigError, match='needle_hold'):
            Material(5000.0, 0.45, 3.0, 3.0, 1060.0, needle_hold=bad)
    assert no_shaft().needle is False


def test_a_needle_lifted_while_inserted_leaves_no_anchor_for_its_next_insertion():
    """Inserted, then lifted at once (no pose): outside, the shaft's anchors gone, and a second
    insertion at the same place dents and punctures again as the first did."""
    solver, _ = needle_solver('local')
    first = insert(solver, (0.02, 0.02), travel=0.015, hold=0, back=False, speed=0.03)
    assert first[-1, 2] == INSERTED and solver.needles[0].stuck.any()
    solver.step(None, DT)
    assert solver.needle_state() == OUTSIDE and not solver.needles[0].stuck.any()
    for _ in range(300):
        solver.step(None, DT)
    second = insert(solver, (0.02, 0.02), travel=0.015, hold=0, back=False, speed=0.03)
    k1, k2 = (int(np.argmax(r[:, 2] == INSERTED)) for r in (first, second))
    assert k2 > 0 and abs(k2 - k1) <= 3
    assert second[k2, 1] >= puncture_force(solver.material.toughness, 2 * RADIUS)
