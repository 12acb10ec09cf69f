"""The package pins OpenBLAS's kernels (blas_kernels): the lockstep goldens depend on them."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from sph_tissue_sim import blas_kernels

X86_64 = os.uname().machine in ('x86_64', 'amd64')
HOST_CAN = X86_64 and all(
    f in blas_kernels._cpu_flags() for f in blas_kernels._NEEDS)


def _kernels_in_fresh_process(code: str, **env) -> str:
    environ = {k: v for k, v in os.environ.items() if k != 'OPENBLAS_CORETYPE'}
    environ.update(env)
    out = subprocess.run([sys.executable, '-c', code + '\nfrom sph_tissue_sim import blas_kernels\n'
                          'print(sorted({a for _, a in blas_kernels.loaded()}))'],
                         env=environ, capture_output=True, text=True, timeout=120, check=True)
    return out.stdout.strip().splitlines()[-1]


@pytest.mark.skipif(not HOST_CAN, reason='needs an x86-64 host with AVX2 and FMA')
def test_importing_the_package_first_gives_numpy_and_scipy_the_pinned_kernels():
    got = _kernels_in_fresh_process('import sph_tissue_sim, numpy, scipy.sparse.linalg')
    assert got == repr([blas_kernels.CORETYPE])


@pytest.mark.skipif(not X86_64, reason='an x86-64 kernel set')
def test_a_users_own_coretype_is_kept():
    got = _kernels_in_fresh_process('import sph_tissue_sim, numpy', OPENBLAS_CORETYPE='Nehalem')
    assert got == repr(['Nehalem'])


def test_pinning_after_numpy_has_loaded_changes_nothing(monkeypatch):
    import numpy  # noqa: F401  (OpenBLAS loads with it)

    monkeypatch.delenv('OPENBLAS_CORETYPE', raising=False)
    assert blas_kernels.pin() is None
    assert 'OPENBLAS_CORETYPE' not in os.environ
