"""Process set-up of sim_node that needs no ROS: the BLAS threads and numba's cache statistics."""

from __future__ import annotations

import sys

from . import blas_kernels


def one_blas_thread() -> None:
    """Let the BLAS libraries (numpy's and scipy's OpenBLAS) use one thread each.

    Their extra threads spin while they wait for work: beside the organ's sparse solves (a
    response per touched particle) they took the core the other threads need (a 0.24 ms numba loop
    beside repeated solves: p99 4.3 ms, with one BLAS thread 0.29 ms), and the solves gain
    nothing from them (49 ms either way on the 3670 liver).
    """
    import scipy.sparse.linalg  # noqa: F401  (loads scipy's own OpenBLAS, so the limit reaches it)
    from threadpoolctl import threadpool_limits
    threadpool_limits(limits=1, user_api='blas')


def numba_cache_stats() -> tuple[int, int]:
    """(kernels compiled in this process, kernels loaded from numba's disk cache) of the core."""
    from numba.core.registry import CPUDispatcher

    # by id: a module that imports another's kernel holds the same dispatcher
    kernels = {id(obj): obj for name, mod in list(sys.modules.items())
               if mod is not None and name.startswith('sph_tissue_sim.core')
               for obj in vars(mod).values() if isinstance(obj, CPUDispatcher)}
    compiled = sum(sum(k.stats.cache_misses.values()) for k in kernels.values())
    loaded = sum(sum(k.stats.cache_hits.values()) for k in kernels.values())
    return compiled, loaded


def startup_report(compile_time: float, compiled: int, loaded: int, lockstep: bool) -> list[tuple[str, str]]:
    """What the node says about its start: (level, text) lines on the kernels it runs."""
    lines = [('info', f'numba warm-up (compile or cache load) and first step: {compile_time:.2f} s '
                      f'({compiled} kernels compiled, {loaded} loaded from the cache)')]
    if compiled and lockstep:
        lines.append(('warn', 'kernels compiled in this process (numba cache not writable?): forces may '
                              'differ in the last bits from a run on cached kernels'))
    kernels = sorted({arch for _, arch in blas_kernels.loaded()})
    lines.append(('info', f'OpenBLAS kernels: {", ".join(kernels)}'))
    if lockstep and kernels != [blas_kernels.CORETYPE]:
        lines.append(('warn', f'OpenBLAS kernels {", ".join(kernels)}, not {blas_kernels.CORETYPE} '
                              f'(OPENBLAS_CORETYPE set, numpy loaded before sph_tissue_sim, or a host without '
                              f'AVX2/FMA): forces may differ in the last bits from the goldens'))
    return lines
