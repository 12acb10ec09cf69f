"""One set of OpenBLAS kernels on every x86-64-v3 host, so lockstep forces repeat bit for bit.

OpenBLAS (numpy's and scipy's) picks its kernels for the CPU when it loads: ``SkylakeX`` on an
AVX-512 host, ``Haswell`` on an AVX2 one. The organ's far field is solved by scipy's SuperLU, in
single precision, through those kernels, and the forces a lockstep replay returns moved by up to
7.5e-9 N from one kernel set to the other (the golden ``press`` session on one host). OpenBLAS
reads ``OPENBLAS_CORETYPE`` only when it loads, so :func:`pin` must run before numpy or scipy is
imported: the package's ``__init__`` calls it, which is first in every process it starts (``ros2
run``). A user's own ``OPENBLAS_CORETYPE`` is kept, and a host without AVX2 and FMA keeps
OpenBLAS's choice (the Haswell kernels would not run there).
"""

from __future__ import annotations

import os
import platform
import sys

#: the kernel set, the level numba's code is compiled for as well (:mod:`.core`: x86-64-v3)
CORETYPE = 'Haswell'
_NEEDS = ('avx2', 'fma')


def _cpu_flags() -> set[str]:
    try:
        with open('/proc/cpuinfo', encoding='ascii', errors='replace') as f:
            for line in f:
                if line.startswith('flags'):
                    return set(line.split(':', 1)[1].split())
    except OSError:
        pass
    return set()


def pin() -> str | None:
    """Set ``OPENBLAS_CORETYPE`` to :data:`CORETYPE` where that is safe and still has an effect;
    returns the core type OpenBLAS will use when it loads (``None``: its own choice)."""
    if 'OPENBLAS_CORETYPE' in os.environ:
        return os.environ['OPENBLAS_CORETYPE']
    if platform.machine().lower() not in ('x86_64', 'amd64') or not all(f in _cpu_flags() for f in _NEEDS):
        return None
    if 'numpy' in sys.modules or 'scipy' in sys.modules:
        return None   # OpenBLAS is loaded already: too late
    os.environ['OPENBLAS_CORETYPE'] = CORETYPE
    return CORETYPE


def loaded() -> list[tuple[str, str]]:
    """(library file, kernel set) of each OpenBLAS loaded in this process."""
    from threadpoolctl import threadpool_info
    return [(os.path.basename(i['filepath']), str(i.get('architecture')))
            for i in threadpool_info() if i.get('internal_api') == 'openblas']
