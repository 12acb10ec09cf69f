"""Tissue models: the liver-shaped body, surface-mesh loading, spacing search, solver on a liver."""

import re

import numpy as np
import pytest
import trimesh

from sph_tissue_sim.core.errors import ModelError
from sph_tissue_sim.core.liver import liver_field, make_liver
from sph_tissue_sim.core.material import Material
from sph_tissue_sim.core.mesh import load_mesh_model
from sph_tissue_sim.core.factory import make_model
from sph_tissue_sim.core.models import fit_spacing
from sph_tissue_sim.core.solver import Solver, SolverConfig

PAPER_COUNTS = [289, 572, 743, 1289, 3670, 20000]


def _monte_carlo_volume(field, lo, hi, n=400_000, seed=7):
    """Volume of {field < 0} inside the box [lo, hi] and its standard error (uniform samples)."""
    rng = np.random.default_rng(seed)
    p = rng.uniform(lo, hi, size=(n, 3))
    frac = np.mean(field(p) < 0.0)
    box = float(np.prod(np.asarray(hi) - np.asarray(lo)))
    return box * frac, box * np.sqrt(frac * (1.0 - frac) / n)


def _lattice_components(pos, spacing):
    """Number of 6-connected components of lattice points (union-find on integer indices)."""
    ijk = np.rint((pos - pos.min(axis=0)) / spacing).astype(np.int64)
    index = {tuple(k): n for n, k in enumerate(ijk)}
    parent = list(range(len(pos)))

    def find(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for n, k in enumerate(ijk):
        for d in ((1, 0, 0), (0, 1, 0), (0, 0, 1)):
            m = index.get((k[0] + d[0], k[1] + d[1], k[2] + d[2]))
            if m is not None:
                parent[find(n)] = find(m)
    return len({find(n) for n in range(len(pos))})


# ----------------------------------------------------------------------------- spacing search
def test_fit_spacing_finds_the_spacing_of_an_analytic_count():
    volume = 2.0e-3

    def count(s):
        return int(volume / s ** 3)

    s, n = fit_spacing(count, 5000, volume, tol=0.02)
    assert abs(n - 5000) <= 0.005 * 5000
    assert s == pytest.approx((volume / 5000) ** (1 / 3), rel=0.01)


def test_fit_spacing_rejects_non_positive_targets_and_volumes():
    with pytest.raises(ModelError):
        fit_spacing(lambda s: 1, 0, 1.0)
    with pytest.raises(ModelError):
        fit_spacing(lambda s: 1, 10, -1.0)


# ----------------------------------------------------------------------------- liver
@pytest.mark.parametrize('n', PAPER_COUNTS + [100_000])
def test_liver_particle_count_is_within_two_percent_of_the_request(n):
    model = make_liver(n)
    assert abs(model.n_particles - n) <= 0.02 * n
    assert model.info['n_target'] == n
    assert model.info['spacing'] == model.spacing


@pytest.mark.parametrize('n', [289, 3670, 20000])
def test_liver_particle_volumes_add_up_to_the_implicit_body_volume(n):
    model = make_liver(n)
    vol, err = _monte_carlo_volume(liver_field, (-0.11, -0.085, -0.005), (0.11, 0.085, 0.09))
    assert err < 0.005 * vol
    assert model.n_particles * model.spacing ** 3 == pytest.approx(vol, rel=0.03)


def test_liver_has_adult_size_and_volume():
    vol, _ = _monte_carlo_volume(liver_field, (-0.11, -0.085, -0.005), (0.11, 0.085, 0.09))
    assert 1.0e-3 < vol < 1.8e-3                      # adult livers: 1.2-1.8 litres
    model = make_liver(20000)
    s = model.spacing
    extent = np.ptp(model.positions, axis=0) + s      # particle cells span the body
    assert extent == pytest.approx([0.20, 0.15, 0.08], abs=1.5 * s)


def test_liver_frame_is_centred_in_x_y_with_its_flat_bottom_at_z_zero():
    model = make_liver(3670)
    pos, s = model.positions, model.spacing
    assert pos[:, 2].min() == pytest.approx(0.5 * s, abs=1e-12)
    centre = 0.5 * (pos.min(axis=0) + pos.max(axis=0))
    assert abs(centre[0]) < s and abs(centre[1]) < s
    lo, hi = model.info['bbox']
    assert lo[2] == 0.0 and hi[2] == pytest.approx(0.08)


def test_liver_is_thick_on_the_right_and_thins_to_the_left():
    model = make_liver(20000)
    pos = model.positions
    right = pos[pos[:, 0] < -0.05, 2].max()
    left = pos[pos[:, 0] > 0.06, 2]
    assert right > 0.07
    assert np.ptp(left) < 0.5 * right                 # wedge-like left lobe


@pytest.mark.parametrize('n', [289, 3670])
def test_liver_is_one_connected_body(n):
    model = make_liver(n)
    assert _lattice_components(model.positions, model.spacing) == 1


@pytest.mark.parametrize('n', [289, 743, 3670, 50_000])
def test_liver_fixed_region_is_a_bottom_layer_and_neither_empty_nor_everything(n):
    model = make_liver(n)
    fixed, pos, s = model.fixed, model.positions, model.spacing
    assert 0 < fixed.sum() < len(fixed)
    assert 0.03 < fixed.mean() < 0.35
    # whole bottom layers: every fixed particle lies below every free one, at least one spacing thick
    assert pos[fixed, 2].max() < pos[~fixed, 2].min()
    assert np.all(fixed[pos[:, 2] < pos[:, 2].min() + 0.5 * s])
    assert model.info['n_fixed'] == fixed.sum()


def test_liver_bottom_fix_takes_the_requested_number_of_layers_and_none_fixes_nothing():
    s = make_liver(3670).spacing
    two = make_liver(3670, fix='bottom', fixed_layers=2)
    assert np.all(two.positions[two.fixed, 2] < 2 * s)
    assert np.any(two.positions[two.fixed, 2] > s)
    assert not make_liver(3670, fix='none').fixed.any()


def test_liver_at_a_given_spacing_holds_its_volume_over_the_cell_volume():
    vol, _ = _monte_carlo_volume(liver_field, (-0.11, -0.085, -0.005), (0.11, 0.085, 0.09))
    model = make_liver(spacing=0.005)
    assert model.spacing == 0.005 and model.info['n_target'] is None
    assert model.n_particles == pytest.approx(vol / 0.005 ** 3, rel=0.03)


def test_liver_scales_with_its_length():
    small = make_liver(3670, length=0.1)
    assert abs(small.n_particles - 3670) <= 0.02 * 3670
    assert small.spacing == pytest.approx(0.5 * make_liver(3670).spacing, rel=0.05)
    assert np.ptp(small.positions[:, 0]) + small.spacing == pytest.approx(0.1, abs=1.5 * small.spacing)


@pytest.mark.parametrize('kwargs', [dict(n_particles=0), dict(n_particles=2.5), dict(length=-0.2),
                                    dict(fix='sideways'), dict(fixed_fraction=1.0),
                                    dict(spacing=float('nan')), dict(fixed_layers=0)])
def test_liver_rejects_bad_arguments(kwargs):
    with pytest.raises(ModelError):
        make_liver(**kwargs)


def test_make_model_builds_a_liver_by_name():
    model = make_model('liver', n_particles=743)
    assert model.name == 'liver'
    assert abs(model.n_particles - 743) <= 15


def test_solver_pressing_the_top_of_a_liver_gets_a_finite_upward_force():
    model = make_liver(743)
    solver = Solver(model, Material.from_shear(1800.0, 0.45, 3.0), SolverConfig(scheme='tlsph', mode='local'))
    pos = model.positions
    top = pos[np.argmax(pos[:, 2])]
    start = top + np.array([0.0, 0.0, solver.contact_reach])
    res = None
    for k in range(120):
        depth = 0.006 * min(1.0, (k + 1) / 80)
        res = solver.step(start - np.array([0.0, 0.0, depth]), 1e-3)
    assert res.contact_index >= 0
    assert np.all(np.isfinite(res.force)) and np.all(np.isfinite(solver.positions))
    assert res.force[2] > 0.02
    assert res.force[2] > np.hypot(res.force[0], res.force[1])
    assert np.array_equal(solver.positions[model.fixed], pos[model.fixed])


# ----------------------------------------------------------------------------- meshes
def _export(mesh, path):
    mesh.export(str(path))
    return path


def test_mesh_sphere_holds_its_volume_over_the_particle_volume(tmp_path):
    R, s = 0.03, 0.003
    path = _export(trimesh.creation.icosphere(subdivisions=4, radius=R), tmp_path / 'sphere.obj')
    model = load_mesh_model(path, spacing=s)
    assert model.n_particles == pytest.approx(4.0 / 3.0 * np.pi * R ** 3 / s ** 3, rel=0.03)
    assert model.info['odd_columns'] == 0


def test_mesh_sphere_inside_agrees_with_the_ball_away_from_its_facets(tmp_path):
    R, s = 0.03, 0.0025
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=R)
    model = load_mesh_model(_export(sphere, tmp_path / 'sphere.stl'), spacing=s, fix='none')
    centre = np.array([0.0, 0.0, R])                  # moved so that its lowest point is at z = 0
    r = np.linalg.norm(model.positions - centre, axis=1)
    assert r.max() < R
    # every lattice point well inside the ball (facets lie within 0.5 % of R) was sampled
    offset = np.mod(model.positions[0], s)
    n = int(np.ceil(R / s)) + 2
    g = (np.arange(-n, n + 1) * s)
    grid = np.stack(np.meshgrid(g, g, g, indexing='ij'), axis=-1).reshape(-1, 3)
    grid += offset + np.floor(centre / s) * s
    inner = grid[np.linalg.norm(grid - centre, axis=1) < 0.99 * R]
    assert len(inner) > 0.9 * model.n_particles
    sampled = {tuple(k) for k in np.rint(model.positions / s * 4).astype(np.int64)}
    assert all(tuple(k) in sampled for k in np.rint(inner / s * 4).astype(np.int64))


def test_mesh_box_gives_the_exact_lattice_count(tmp_path):
    path = _export(trimesh.creation.box(extents=(0.04, 0.03, 0.02)), tmp_path / 'box.stl')
    model = load_mesh_model(path, spacing=0.005)
    assert model.n_particles == 8 * 6 * 4
    assert model.fixed.sum() == 8 * 6                 # one bottom layer
    assert model.positions[:, 2].min() == pytest.approx(0.0025)
    assert np.allclose(0.5 * (model.positions.min(axis=0) + model.positions.max(axis=0))[:2], 0.0)


def test_mesh_in_millimetres_is_scaled_to_metres(tmp_path):
    path = _export(trimesh.creation.box(extents=(40.0, 30.0, 20.0)), tmp_path / 'box_mm.obj')
    model = load_mesh_model(path, spacing=0.005, scale=0.001)
    assert model.n_particles == 192


def test_mesh_particle_count_target_is_met_within_two_percent(tmp_path):
    path = _export(trimesh.creation.icosphere(subdivisions=3, radius=0.05), tmp_path / 'ball.obj')
    for n in (289, 3670):
        model = load_mesh_model(path, n_particles=n)
        assert abs(model.n_particles - n) <= 0.02 * n


def test_mesh_that_is_not_watertight_is_rejected(tmp_path):
    box = trimesh.creation.box(extents=(0.04, 0.03, 0.02))
    open_box = trimesh.Trimesh(box.vertices, box.faces[:-1], process=False)
    with pytest.raises(ModelError, match='not watertight'):
        load_mesh_model(_export(open_box, tmp_path / 'open.stl'), spacing=0.005)


def test_missing_mesh_file_is_rejected(tmp_path):
    with pytest.raises(ModelError, match='not found'):
        load_mesh_model(tmp_path / 'nothing.obj', spacing=0.005)


@pytest.mark.parametrize('name, content', [('garbage.stl', b'\x00\x01garbage' * 50),
                                           ('broken.obj', b'v 1 2\nf 1 2 3 4 5\n'),
                                           ('empty.obj', b'')])
def test_corrupt_mesh_file_is_rejected(tmp_path, name, content):
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(ModelError):
        load_mesh_model(path, spacing=0.005)


_RANDOM = np.random.default_rng(7).integers(0, 256, 3000, dtype=np.uint8).tobytes()


@pytest.mark.parametrize('name, content, says', [
    ('random.stl', _RANDOM, 'not a valid binary STL file'),
    ('random.obj', _RANDOM, 'not a text OBJ file'),
    ('random.off', _RANDOM, 'not a text OFF file'),
    ('random.ply', _RANDOM, 'not a PLY file'),
    ('tiny.stl', b'\x00' * 40, 'shorter than a binary STL header'),
    ('empty.stl', b'', 'the file is empty'),
    ('mesh.xyz', b'1 2 3\n', "unsupported mesh format '.xyz'"),
])
def test_a_file_that_is_not_the_mesh_its_name_says_is_rejected_with_a_sentence(tmp_path, name,
                                                                                 content, says):
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(ModelError, match=re.escape(says)):
        load_mesh_model(path, spacing=0.005)


def test_a_truncated_binary_stl_is_rejected_with_its_sizes(tmp_path):
    path = _export(trimesh.creation.box(extents=(0.04, 0.03, 0.02)), tmp_path / 'box.stl')
    data = path.read_bytes()
    path.write_bytes(data[:-30])
    with pytest.raises(ModelError, match=f'12 triangles \\({len(data)} bytes\\) but the file has '
                                         f'{len(data) - 30} bytes'):
        load_mesh_model(path, spacing=0.005)


@pytest.mark.parametrize('kwargs', [dict(spacing=0.005, n_particles=100), dict(spacing=-1.0),
                                    dict(spacing=0.005, scale=0.0), dict(spacing=0.005, fix='top'),
                                    dict(spacing=0.5)])
def test_mesh_rejects_bad_options(tmp_path, kwargs):
    path = _export(trimesh.creation.box(extents=(0.04, 0.03, 0.02)), tmp_path / 'box.stl')
    with pytest.raises(ModelError):
        load_mesh_model(path, **kwargs)


def test_make_model_loads_a_mesh_by_name(tmp_path):
    path = _export(trimesh.creation.box(extents=(0.04, 0.03, 0.02)), tmp_path / 'box.stl')
    model = make_model('mesh', path=path, spacing=0.005)
    assert model.name == 'mesh:box.stl'
    assert model.n_particles == 192
