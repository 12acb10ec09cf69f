"""The organ's solved responses on disk (:mod:`.compliance`), so that a restart on the same organ
does not factor its stiffness again to feel where it was touched before.

A response is a pure function of the organ's stiffness (:func:`~.compliance.stiffness_key`: the
reference positions, the held particles, the pairs, gradients and moduli) and of the code that
builds, factors and solves it (the sources of :mod:`.compliance` and :mod:`.organ_factor`, this
format, scipy's and numpy's versions, the machine's architecture): the store's folder is named by
a digest of both, one ``.npy`` file per particle, written by the factoring process. A file is written
whole (to a temporary name, then renamed), and one that does not load as the expected
``(N, 3, 3)`` finite float32 array is ignored and solved again, so a crashed writer, a full disk or
two processes writing the same response cost a solve, never a wrong response.

The folder is ``$SPH_TISSUE_CACHE`` (empty: no store), else ``$XDG_CACHE_HOME/sph_tissue_sim``,
else ``~/.cache/sph_tissue_sim``; each organ takes about 0.13 MB per touched particle (3670 liver).
"""

from __future__ import annotations

import hashlib
import os
import platform
import tempfile
from pathlib import Path

import numpy as np

#: the environment variable naming the store's folder (set and empty: no store)
CACHE_ENV = 'SPH_TISSUE_CACHE'
#: bump when the factorisation or the solve changes what a response's bits are
FORMAT = 'organ-response-1 float32 splu MMD_AT_PLUS_A'


def code_digest() -> bytes:
    """A digest of what makes a response's bits besides the organ: the code and the libraries."""
    import scipy

    h = hashlib.blake2b(digest_size=16)
    here = Path(__file__).parent
    for name in ('compliance.py', 'organ_factor.py'):
        h.update((here / name).read_bytes())
    h.update(f'{FORMAT} scipy {scipy.__version__} numpy {np.__version__} {platform.machine()}'.encode())
    return h.digest()


def cache_root() -> Path | None:
    """The folder the stores live in (None: no store)."""
    value = os.environ.get(CACHE_ENV)
    if value is not None:
        return Path(value) if value else None
    base = os.environ.get('XDG_CACHE_HOME') or str(Path.home() / '.cache')
    return Path(base) / 'sph_tissue_sim'


class ResponseStore:
    """The responses of one organ (``key``, its stiffness digest) with ``n`` particles, in
    ``root`` (default :func:`cache_root`; None: a store that keeps nothing)."""

    def __init__(self, key: bytes, n: int, root: Path | None = None) -> None:
        root = cache_root() if root is None else root
        h = hashlib.blake2b(key, digest_size=16)
        h.update(code_digest())
        self.folder = None if root is None else Path(root) / f'organ-{h.hexdigest()}'
        self.n = n
        #: responses loaded, and files that could not be read
        self.hits = 0
        self.errors = 0

    def __len__(self) -> int:
        """How many responses the store holds."""
        if self.folder is None or not self.folder.is_dir():
            return 0
        return sum(1 for p in self.folder.glob('*.npy'))

    def load(self, c: int) -> np.ndarray | None:
        """Particle ``c``'s response (N, 3, 3) float32, or None if it is not stored (or unreadable)."""
        if self.folder is None:
            return None
        path = self.folder / f'{c}.npy'
        try:
            u = np.load(path, allow_pickle=False)
        except FileNotFoundError:
            return None
        except (OSError, ValueError):
            self.errors += 1
            return None
        if u.dtype != np.float32 or u.shape != (self.n, 3, 3) or not np.isfinite(u).all():
            self.errors += 1
            return None
        self.hits += 1
        return u


def save_response(folder: str | Path, c: int, u: np.ndarray) -> bool:
    """Store particle ``c``'s response in ``folder``; False (and nothing stored) if it cannot be
    written. Written whole under a temporary name, then renamed: a reader never sees half a file."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=folder, suffix='.tmp')
        try:
            with os.fdopen(fd, 'wb') as f:
                np.save(f, np.ascontiguousarray(u, dtype=np.float32), allow_pickle=False)
            os.replace(tmp, folder / f'{c}.npy')
        except BaseException:
            os.unlink(tmp)
            raise
    except OSError:
        return False
    return True
