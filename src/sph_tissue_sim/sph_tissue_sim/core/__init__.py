"""Numerical core of the simulator: numpy + numba only, never rclpy.

Main entry points: :class:`~.solver.Solver`, :class:`~.solver.SolverConfig`,
:class:`~.material.Material`, :func:`~.factory.make_model`, :func:`~.solver.warmup`.
"""

from __future__ import annotations

import hashlib
import os
import platform
import warnings
from pathlib import Path

#: the x86-64 level the kernels are compiled for on hosts that have it (AVX2 + FMA)
PORTABLE_CPU = 'x86-64-v3'
#: what that level needs of the host, as LLVM names the CPU features
PORTABLE_FEATURES = ('avx', 'avx2', 'fma', 'bmi', 'bmi2', 'lzcnt', 'movbe', 'f16c', 'popcnt',
                     'sse4.2')


def _use_portable_codegen() -> None:
    """Compile the kernels for :data:`PORTABLE_CPU` instead of this host's exact CPU.

    numba compiles for the host by default, and with fast-math LLVM vectorises and reassociates
    sums differently on, say, an AVX-512 host than on an AVX2 one: the forces then differ in their
    last bits (~5e-15 N) from host to host, and the lockstep goldens (bit-identical by design) hold
    only on the CPU model that made them. One fixed target makes the code, and so the forces, the
    same on every x86-64 host with the level's features (AVX2, FMA, BMI, ...; measured on an
    AVX-512 host: no slower). Hosts without them, other architectures, and an explicit
    ``NUMBA_CPU_NAME`` keep numba's choice.
    Must run before numba makes its CPU target, which the first ``@njit`` decoration in the
    process does (not the first compile): the package's ``__init__`` imports this module first.
    """
    if os.environ.get('NUMBA_CPU_NAME') or platform.machine().lower() not in ('x86_64', 'amd64'):
        return
    from llvmlite import binding as ll
    from numba.core import config
    from numba.core.registry import cpu_target

    try:
        features = ll.get_host_cpu_features()
    except RuntimeError:  # no feature list on this host: keep numba's default
        return
    if all(features.get(name) for name in PORTABLE_FEATURES):
        if '_toplevel_target_context' in vars(cpu_target):
            # its code generator already holds the host's CPU and features, whatever the config
            # says now (numba's own cache key would still read x86-64-v3)
            warnings.warn('numba made its CPU target before sph_tissue_sim.core was imported: the '
                          'kernels compile for this host, and lockstep forces may differ from the '
                          'goldens in their last bits (import sph_tissue_sim before any @njit code)',
                          RuntimeWarning, stacklevel=2)
            return
        config.CPU_NAME = PORTABLE_CPU
        config.CPU_FEATURES = ''   # the level's own feature set, not the host's


def _invalidate_stale_numba_cache() -> None:
    """Drop numba's on-disk cache of this package when any core source file changed.

    numba keys a cached function on its own file only, so a kernel inlined from another module
    (e.g. tlsph.py into frame.py) would otherwise keep running its old code after an edit.
    """
    here = Path(__file__).resolve().parent
    cache = here / '__pycache__'
    try:
        h = hashlib.sha1()
        for src in sorted(here.glob('*.py')):
            st = src.stat()
            h.update(f'{src.name}:{st.st_mtime_ns}:{st.st_size};'.encode())
        digest = h.hexdigest()
        stamp = cache / 'numba_sources.stamp'
        if stamp.is_file() and stamp.read_text() == digest:
            return
        for f in list(cache.glob('*.nbi')) + list(cache.glob('*.nbc')):
            f.unlink(missing_ok=True)
        cache.mkdir(exist_ok=True)
        stamp.write_text(digest)
    except OSError:
        pass  # read-only install: numba then cannot write its cache either


_use_portable_codegen()
_invalidate_stale_numba_cache()
