"""The organ's stiffness factored and solved in a process of its own (:mod:`.compliance`).

Building the organ's stiffness and factoring it takes seconds (3671 liver: about 4 s and 11 s);
the build is scipy code that holds the interpreter lock, so done beside the live loop it cost the
loop poses (docs/decisions/deferred-factor.md). Here a child interpreter
(``python -m sph_tissue_sim.core.organ_factor``, the lowest priority) builds and factors it when
the first response not on disk is asked for, then solves the responses it is asked for, one at a
time, stores each in the organ's :class:`~.response_store.ResponseStore` and sends it back. The
child does exactly what the parent would have done, so its responses are bit-identical to an
in-process solve. It ends when its parent closes the pipe, exits or dies.

The pipes carry :class:`multiprocessing.connection.Connection` messages: the parent sends the organ (:func:`organ_arrays`) once, then particle
indices; the child answers ``('factored', seconds, nnz)`` once, then ``('response', c, u)`` for
each index, or ``('error', text)`` before it exits.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from multiprocessing.connection import Connection

import numpy as np

from .errors import OrganFactorError

#: the child's Linux nice value (19, the lowest priority): the live loop comes first
CHILD_NICE = 19
#: [s] how often a wait for the child looks at the caller's interrupt flag
POLL = 0.05


def organ_arrays(X, fixed, state, free_dofs, folder) -> dict:
    """What the child needs to build and factor the stiffness, and where it stores responses.

    Copies, taken now: the child is sent them at the first response not on disk, maybe long after,
    and a blade's cut changes the scheme's ``g``, ``gsum`` and ``w0`` in place (:mod:`.bonds`), so
    the arrays themselves would factor the cut organ under the intact one's key (its disk store,
    and a later solver on the intact organ that reuses this process)."""
    return dict(X=np.array(X), fixed=np.array(fixed, dtype=bool), offsets=np.array(state.offsets),
                indices=np.array(state.indices), g=np.array(state.g), gsum=np.array(state.gsum),
                w0=np.array(state.w0), volume=float(state.volume), G=float(state.G),
                K=float(state.K), hg_k=float(state.hg_k), free_dofs=np.array(free_dofs),
                folder=None if folder is None else str(folder))


class FactorProcess:
    """The parent's end of one child: :meth:`solve` asks for a particle's response and waits.

    Args:
        key: the organ's stiffness digest (:func:`~.compliance.stiffness_key`).
        organ: :func:`organ_arrays`, sent when the child starts (at the first :meth:`solve`).
    """

    def __init__(self, key: bytes, organ: dict) -> None:
        self.key = key
        self._organ = organ
        self._proc: subprocess.Popen | None = None
        self._tx: Connection | None = None
        self._rx: Connection | None = None
        self._lock = threading.Lock()   # one request on the pipe at a time
        self._early: dict[int, np.ndarray] = {}   # replies to requests whose caller gave up
        self._asked: set[int] = set()
        #: [s] the child's stiffness build and factorisation, and the factor's non-zeros (0: not yet)
        self.factor_seconds = 0.0
        self.factor_nnz = 0
        self._closed = False

    @property
    def started(self) -> bool:
        return self._proc is not None

    def start_soon(self) -> None:
        """Start the child (and its factor) now, on a thread of its own, without asking for a
        response: an organ with nothing on disk will need the factor at its first touch."""
        def start():
            with self._lock:
                try:
                    self._start()
                except Exception:   # noqa: BLE001  (closed meanwhile, or no process: the first
                    self._stop()    # solve tries again and raises what it finds)

        threading.Thread(target=start, name='organ-factor-start', daemon=True).start()

    def _start(self) -> None:
        if self._closed:
            raise OrganFactorError('the factoring process was closed')
        if self._proc is not None:
            return
        self._early.clear()
        self._asked.clear()
        # one BLAS thread, as in sim_node (one_blas_thread): the solve's bits depend on the count
        proc = subprocess.Popen([sys.executable, '-m', __name__], stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, close_fds=True,
                                env=dict(os.environ, OPENBLAS_NUM_THREADS='1'))
        self._tx, self._rx = Connection(os.dup(proc.stdin.fileno())), Connection(os.dup(proc.stdout.fileno()))
        proc.stdin.close()
        proc.stdout.close()
        self._proc = proc
        self._tx.send(self._organ)

    def _read(self, abort: np.ndarray | None):
        """The child's next message; None if ``abort`` was set first."""
        while abort is not None and not self._rx.poll(POLL):
            if abort[0] != 0:
                return None
        try:
            return self._rx.recv()
        except (EOFError, OSError) as exc:
            code = self._proc.wait()
            raise OrganFactorError(f'the organ factoring process ended (exit code {code}) before '
                                   f'it answered') from exc

    def solve(self, c: int, abort: np.ndarray | None = None) -> np.ndarray | None:
        """Particle ``c``'s response, (N, 3, 3) float32 [m/N] (zero rows for the held particles);
        None if ``abort[0]`` was set while waiting (the answer is kept for the next ask).

        Raises:
            OrganFactorError: the child failed (the next call starts a new one).
        """
        while not self._lock.acquire(timeout=POLL):   # another caller, or the start, holds the pipe
            if abort is not None and abort[0] != 0:
                return None
        try:
            if c in self._early:
                return self._early.pop(c)
            try:
                self._start()
                if c not in self._asked:
                    self._tx.send(int(c))
                    self._asked.add(c)
                while True:
                    message = self._read(abort)
                    if message is None:
                        return None
                    if message[0] == 'factored':
                        self.factor_seconds, self.factor_nnz = message[1:]
                    elif message[0] == 'error':
                        raise OrganFactorError(f'the organ factoring process failed: {message[1]}')
                    else:
                        _, k, u = message
                        self._asked.discard(k)
                        if k == c:
                            return u
                        self._early[k] = u
            except (OSError, OrganFactorError) as exc:
                self._stop()
                if isinstance(exc, OrganFactorError):
                    raise
                raise OrganFactorError(f'the organ factoring process cannot be reached: {exc}') from exc
        finally:
            self._lock.release()

    def _stop(self) -> None:
        proc, self._proc = self._proc, None
        for end in (self._tx, self._rx):
            if end is not None:
                end.close()
        self._tx = self._rx = None
        if proc is not None:
            if proc.poll() is None:
                proc.kill()
            proc.wait()

    def close(self) -> None:
        """End the child (it holds the factor's memory); a :meth:`solve` then raises."""
        self._closed = True
        self._stop()


def _die_with_parent() -> None:
    """End this process when its parent is gone, even mid-factor (a killed node's child must not
    keep a core and the factor's memory); the pipe alone is read only between two requests."""
    parent = os.getppid()

    def watch():
        while os.getppid() == parent:
            time.sleep(POLL * 10)
        os._exit(0)

    threading.Thread(target=watch, name='parent-watch', daemon=True).start()


def main() -> int:
    """The child: build, factor, then answer indices until the pipe closes."""
    out, source = Connection(os.dup(1)), Connection(0)
    os.dup2(2, 1)   # a library's print must not corrupt the pipe
    # a Ctrl-C reaches the whole process group: the parent decides when this one ends
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _die_with_parent()
    try:
        os.nice(CHILD_NICE)
    except OSError:
        pass
    try:
        organ = source.recv()
    except EOFError:
        return 0
    try:
        import scipy.sparse.linalg as sla

        from .compliance import linear_stiffness
        from .response_store import save_response

        t0 = time.perf_counter()
        free = organ['free_dofs']
        k = linear_stiffness(organ['X'], organ['offsets'], organ['indices'], organ['g'], organ['gsum'],
                             organ['w0'], organ['volume'], organ['G'], organ['K'], organ['hg_k'])
        # single precision: half the factor's memory and solve time, responses within 2e-6 of double's
        lu = sla.splu(k[free][:, free].astype(np.float32).tocsc(), permc_spec='MMD_AT_PLUS_A')
        del k
        out.send(('factored', time.perf_counter() - t0, int(lu.L.nnz + lu.U.nnz)))
        n = len(organ['X'])
        while True:
            try:
                c = source.recv()
            except EOFError:
                return 0
            rhs = np.zeros((3 * n, 3), dtype=np.float32)
            rhs[3 * c:3 * c + 3] = np.eye(3)
            u = np.zeros((3 * n, 3), dtype=np.float32)
            u[free] = lu.solve(rhs[free])
            u = u.reshape(n, 3, 3)
            if organ['folder'] is not None:
                save_response(organ['folder'], c, u)
            out.send(('response', c, u))
    except BrokenPipeError:
        return 0
    except Exception as exc:   # noqa: BLE001  (reported to the parent, which raises it)
        try:
            out.send(('error', f'{type(exc).__name__}: {exc}'))
        except OSError:
            pass
        return 1


if __name__ == '__main__':
    sys.exit(main())
