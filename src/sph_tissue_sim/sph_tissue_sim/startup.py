"""Process set-up of sim_node that needs no ROS: the BLAS threads and numba's kernels."""

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


def _core_kernels() -> list:
    from numba.core.registry import CPUDispatcher

    found = {}
    for name, mod in list(sys.modules.items()):
        if mod is None or not name.startswith('sph_tissue_sim.core'):
            continue
        for obj in vars(mod).values():
            if isinstance(obj, CPUDispatcher):
                found[id(obj)] = obj
    return list(found.values())


def numba_cache_stats() -> tuple[int, int]:
    """(kernels compiled in this process, kernels loaded from numba's disk cache) of the core."""
    compiled = loaded = 0
    for kernel in _core_kernels():
        compiled += sum(kernel.stats.cache_misses.values())
        loaded += sum(kernel.stats.cache_hits.values())
    return compiled, loaded


#: (kernel, signature) pairs that run from the cache (a process may build several solvers)
_FROM_CACHE: set = set()


def reload_from_cache() -> tuple[int, int]:
    """Run the core's kernels that were compiled in this process from numba's disk cache instead.

    A kernel compiled here and the same kernel loaded from the cache can differ in the last bits
    (measured: 4e-15 N on a press); every later start loads from the cache, so a lockstep replay
    right after a change of the core would not repeat its successors bit for bit. Each such
    kernel's compiled versions are dropped and loaded again (numba compiles and saves them to the
    cache first, so a writable cache has them). Whatever the old code computed must be computed
    again by the caller. Returns (versions reloaded, versions compiled again: no cache)."""
    reloaded = again = 0
    for kernel in _core_kernels():
        signatures = [args for args in kernel.overloads if (id(kernel), args) not in _FROM_CACHE]
        if not kernel.stats.cache_misses or not signatures:
            continue
        signatures = list(kernel.overloads)
        _FROM_CACHE.update((id(kernel), args) for args in signatures)
        misses = sum(kernel.stats.cache_misses.values())
        kernel._clear()                 # the typed dispatch table of numba's C dispatcher
        kernel.overloads.clear()
        for args in signatures:
            kernel.compile(args)
        again += sum(kernel.stats.cache_misses.values()) - misses
        reloaded += len(signatures)
    return reloaded - again, again


def startup_report(compile_time: float, compiled: int, loaded: int, reloaded: int, again: int,
                   lockstep: bool) -> list[tuple[str, str]]:
    """What the node says about its start: (level, text) lines on the kernels it runs."""
    lines = [('info', f'numba warm-up (compile or cache load) and first step: {compile_time:.2f} s '
                      f'({compiled} kernels compiled, {loaded} loaded from the cache)')]
    if reloaded:
        lines.append(('info', f'{reloaded} kernels compiled in this process now run from the cache '
                              f'(bit-identical lockstep)'))
    if again:
        lines.append(('warn', f'{again} kernels compiled again (numba cache not writable?): forces may '
                              f'differ in the last bits from a run on cached kernels'))
    kernels = sorted({arch for _, arch in blas_kernels.loaded()})
    lines.append(('info', f'OpenBLAS kernels: {", ".join(kernels)}'))
    if lockstep and kernels != [blas_kernels.CORETYPE]:
        lines.append(('warn', f'OpenBLAS kernels {", ".join(kernels)}, not {blas_kernels.CORETYPE} '
                              f'(OPENBLAS_CORETYPE set, numpy loaded before sph_tissue_sim, or a host without '
                              f'AVX2/FMA): forces may differ in the last bits from the goldens'))
    return lines
