"""Contact kinds (core/contact_kinds.py): the reach radii, samples and area growth the solver asks
of them, against their definitions."""

from __future__ import annotations

import pytest

from sph_tissue_sim.core.contact_kinds import (BALL_RADIUS, SAMPLE_AREA_GROWTH, BallContact, SampledContact,
                                               make_contact)
from sph_tissue_sim.core.kernel import SUPPORT
from sph_tissue_sim.core.models import make_block
from sph_tissue_sim.core.neighbours import find_neighbours
from sph_tissue_sim.core.surface_contact import SURFACE_OFFSET

SPACING, RADIUS, H = 0.005, 0.004, 1.3 * 0.005


def _sampled(per_side: int = 3) -> SampledContact:
    model = make_block(6, 6, 4, spacing=SPACING, fix='bottom')
    offsets, indices = find_neighbours(model.positions, SUPPORT * H)
    return make_contact(per_side, RADIUS, SPACING, model.positions, offsets, indices, H,
                        model.particle_volume)


def test_balls_reach_one_ball_radius_beyond_the_tool_everywhere():
    c = make_contact(0, RADIUS, SPACING, None, None, None, H, 0.0)
    assert type(c) is BallContact and c.n_samples == 0
    reach = RADIUS + BALL_RADIUS * SPACING
    assert c.contact_reach == c.ball_reach == c.detect_reach == c.cand_reach == c.samples_reach == reach
    assert c.area(False, False, 0.01, H) == (reach, 0.01)


def test_samples_reach_the_surface_half_a_spacing_out_and_their_readers_once_they_push():
    c = _sampled()
    assert c.n_samples > 0
    assert c.contact_reach == max(RADIUS + SURFACE_OFFSET * SPACING, c.ball_reach)
    assert c.cand_reach == c.ball_reach <= c.detect_reach <= c.samples_reach
    # before a sample pushes: the balls' area; after: the samples' readers, and with the half-space
    # far field (no organ) an area grown by SAMPLE_AREA_GROWTH h
    assert c.area(False, False, 0.01, H) == (c.ball_reach, 0.01)
    assert c.area(True, True, 0.01, H) == (c.samples_reach, 0.01)
    assert c.area(True, False, 0.01, H) == (c.samples_reach, pytest.approx(0.01 + SAMPLE_AREA_GROWTH * H))


def test_a_sample_carries_its_share_of_the_dashpot():
    c = _sampled(3)
    s = c.samples(10, RADIUS, 300.0, 0.9)
    assert s.damping == pytest.approx(0.9 / 3) and s.stiffness == 300.0
