"""Kernel (paper eqs. 9-10) and cell-grid neighbour search checked against independent answers."""

import math

import numpy as np
import pytest

from sph_tissue_sim.core.kernel import kernel_dwdr, kernel_w, kernel_w_array
from sph_tissue_sim.core.neighbours import CellGrid, find_neighbours

_dwdr = np.vectorize(kernel_dwdr)   # dW/dr over an array of distances


@pytest.mark.parametrize('h', [0.3, 0.01, 1.7])
def test_kernel_integrates_to_one(h):
    # radial quadrature of W over its support: int_0^2h 4 pi r^2 W(r) dr
    r = np.linspace(0.0, 2.0 * h, 200001)
    w = kernel_w_array(r, h)
    integral = np.trapezoid(4.0 * math.pi * r * r * w, r)
    assert integral == pytest.approx(1.0, abs=1e-6)


def test_kernel_is_zero_outside_support_and_continuous_at_r_equal_h():
    h = 0.5
    assert kernel_w(2.0 * h, h) == 0.0
    assert kernel_w(3.0 * h, h) == 0.0
    assert kernel_w(h * (1 - 1e-12), h) == pytest.approx(kernel_w(h * (1 + 1e-12), h), rel=1e-9)
    assert kernel_dwdr(h * (1 - 1e-12), h) == pytest.approx(kernel_dwdr(h * (1 + 1e-12), h), rel=1e-9)


@pytest.mark.parametrize('h', [0.3, 0.02])
def test_kernel_gradient_matches_finite_differences(h):
    # central differences of W; this fails with the paper's 1.25 coefficient in eq. 10
    r = np.linspace(0.01 * h, 1.99 * h, 397)
    eps = 1e-7 * h
    fd = (kernel_w_array(r + eps, h) - kernel_w_array(r - eps, h)) / (2.0 * eps)
    analytic = _dwdr(r, h)
    scale = np.abs(analytic).max()
    assert np.max(np.abs(fd - analytic)) < 1e-6 * scale


def test_neighbour_lists_match_brute_force():
    rng = np.random.default_rng(3)
    pts = rng.uniform(0.0, 0.1, size=(400, 3))
    radius = 0.021
    offsets, indices = find_neighbours(pts, radius)
    d = np.linalg.norm(pts[:, None, :] - pts[None, :, :], axis=2)
    for i in range(len(pts)):
        expected = set(np.flatnonzero((d[i] < radius) & (np.arange(len(pts)) != i)))
        got = set(indices[offsets[i]:offsets[i + 1]].tolist())
        assert got == expected


def test_cell_grid_ball_query_matches_brute_force():
    rng = np.random.default_rng(4)
    pts = rng.uniform(-0.05, 0.05, size=(500, 3))
    grid = CellGrid(pts, 0.02)
    for centre, radius in [((0.0, 0.0, 0.0), 0.03), ((0.04, -0.04, 0.01), 0.011), ((1.0, 1.0, 1.0), 0.1)]:
        got = set(grid.query(np.array(centre), radius, pts).tolist())
        expected = set(np.flatnonzero(np.linalg.norm(pts - np.array(centre), axis=1) <= radius))
        assert got == expected


def _portable_host() -> bool:
    import os
    import platform

    from llvmlite import binding as ll

    import sph_tissue_sim.core as core
    features = ll.get_host_cpu_features()
    return (not os.environ.get('NUMBA_CPU_NAME') and platform.machine().lower() in ('x86_64', 'amd64')
            and all(features.get(name) for name in core.PORTABLE_FEATURES))


#: run in a fresh interpreter: what the code generator of numba's CPU target was made with (its
#: cache key's CPU name is read from the config at each call, so it would not tell)
_PROBE = """
import {first}
from sph_tissue_sim.core.kernel import kernel_w
kernel_w(0.1, 1.0)
codegen = kernel_w.targetctx.codegen()
print(codegen._get_host_cpu_name(), repr(codegen._tm_features))
"""


def _codegen_in_fresh_process(first: str) -> tuple[str, list[str]]:
    import subprocess
    import sys
    out = subprocess.run([sys.executable, '-c', _PROBE.format(first=first)], capture_output=True,
                         text=True, timeout=300, check=True)
    cpu, features = out.stdout.split()
    return cpu, features, out.stderr


@pytest.mark.parametrize('first', ['sph_tissue_sim.core.kernel', 'sph_tissue_sim.sim_node',
                                   'sph_tissue_sim.cloud'])
def test_kernels_are_compiled_for_the_portable_cpu_level_whatever_module_a_process_imports_first(first):
    """The lockstep goldens are bit-identical across hosts only if every process compiles the same
    code: the core picks x86-64-v3 instead of the host's own CPU (sph_tissue_sim/core/__init__.py),
    also in sim_node, whose first @njit decoration (cloud.py) came before the core's import."""
    import sph_tissue_sim.core as core
    if not _portable_host():
        pytest.skip('this host compiles for itself (no x86-64-v3, or NUMBA_CPU_NAME set)')
    cpu, features, err = _codegen_in_fresh_process(first)
    assert (cpu, features) == (core.PORTABLE_CPU, "''"), err
    assert 'RuntimeWarning' not in err


def test_a_process_that_made_numbas_cpu_target_before_the_core_is_warned_its_kernels_are_the_hosts():
    if not _portable_host():
        pytest.skip('this host compiles for itself (no x86-64-v3, or NUMBA_CPU_NAME set)')
    cpu, features, err = _codegen_in_fresh_process('numba\n@numba.njit\ndef f(x):\n    return x\n'
                                                   'import sph_tissue_sim')
    assert 'numba made its CPU target before sph_tissue_sim.core was imported' in err
    assert features != "''"
