"""The force-series measures against hand-counted series."""

import numpy as np
import pytest

from tissue_common.feel import TICK, energy_in, feel, misses, one_frame_reversals

Z = np.array([0.0, 0.0, 1.0])


def test_a_drop_that_comes_straight_back_is_one_reversal_and_a_ramp_is_none():
    f = np.outer(np.full(10, 0.16), Z)
    f[4] = 0.11 * Z                           # 0.16 -> 0.11 -> 0.16: one click
    assert one_frame_reversals(f) == 1
    ramp = np.outer(np.linspace(0.0, 1.0, 10), Z)   # 0.11 N a frame, always the same way
    assert one_frame_reversals(ramp) == 0
    f[4] = 0.155 * Z                          # 5 mN and back: below the threshold
    assert one_frame_reversals(f) == 0


def test_a_click_across_a_missing_reply_is_not_counted():
    f = np.outer(np.full(6, 0.16), Z)
    f[3] = 0.11 * Z
    t = np.array([0.0, 1e-3, 2e-3, 3e-3, 20e-3, 21e-3])    # no reply between 3 and 20 ms
    assert one_frame_reversals(f) == 1
    assert feel(np.zeros((6, 3)), f, t)['reversals'] == 0


def test_energy_in_charges_each_held_force_with_the_next_displacement():
    x = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -0.001], [0.0, 0.0, 0.0]])
    f = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 2.0], [0.0, 0.0, 0.0]])
    np.testing.assert_allclose(energy_in(x, f), [0.0, 0.001, 0.001 - 0.002])


def test_steady_contact_starts_after_twenty_frames_and_misses_name_each_target():
    n = 200
    z = -TICK * np.arange(n)                  # one tick a frame into a 80 N/m wall
    f = np.outer(80.0 * -z, Z)
    q = feel(np.stack([0 * z, 0 * z, z], axis=1), f)
    assert q['steady_frames'] == n - 1 - 21   # force on from frame 1, steady after 20 more
    assert q['dF_p99_mN'] == pytest.approx(80.0 * TICK * 1e3)
    assert q['reversals'] == 0 and q['E_in_min_uJ'] == 0.0 and q['E_in_final_uJ'] > 0.0
    assert misses(q) == []
    bad = dict(q, dF_p99_mN=7.0, reversals=2, E_in_min_uJ=-3.0)
    assert len(misses(bad)) == 3
