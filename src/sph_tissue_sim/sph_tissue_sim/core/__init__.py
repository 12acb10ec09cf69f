"""Numerical core of the simulator: numpy + numba only, never rclpy.

Main entry points: :class:`~.solver.Solver`, :class:`~.solver.SolverConfig`,
:class:`~.material.Material`, :func:`~.models.make_model`, :func:`~.solver.warmup`.
"""

from __future__ import annotations

import hashlib
from pathlib import Path


def _invalidate_stale_numba_cache() -> None:
    """Drop numba's on-disk cache of this package when any core source file changed.

    numba keys a cached function on its own file only, so a kernel inlined from another module
    (e.g. tlsph.py into integrate.py) would otherwise keep running its old code after an edit.
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


_invalidate_stale_numba_cache()
