"""The organ's own far field: its linear compliance, factored once in the reference configuration.

Local mode solves a few hundred particles round the tool and moves the still particles the solved
ones read (the stress shell) with the rest of the organ. The elastic half-space (Boussinesq) is
the cheap guess of that motion, but an organ is not a half-space: a lobe bonded to the fixed base
is stiffer, a sloping dome softer, and with a load spread over a particle's patch (the surface
samples) no one gain suited both (about 0.5 and 1.3 on the 3670 liver). Here the far field is the
organ's own: the internal forces of :mod:`.tlsph` linearised at the reference configuration,

    f = -K u,    K = V sum_i B_i^T D B_i + K_hg,

``B_i`` mapping the displacements to ``H_i = sum_j (u_j - u_i) (x) g_ij`` (the deformation
gradient's change), ``D`` the neo-Hookean tangent at ``F = I`` (``dP = G (H + H^T) + lambda tr(H) I``)
and ``K_hg`` the hourglass bonds' (bond error ``(H_i + H_j)/2 X' - u'`` projected on the bond,
weighted ``w0 hg_k``), the fixed particles held. ``K`` is factored once (SuperLU, scipy's); the
response to a unit force at particle ``c`` (three right-hand sides) is solved the first time ``c``
carries the tool's load and kept, in memory and on disk (:mod:`.response_store`). Building and
factoring ``K`` takes seconds (3671 liver: about 15 s), so it runs in a process of its own
(:mod:`.organ_factor`) when the first response not on disk is asked for: a restart on the same
organ needs no factor for the places touched before, and the factor never holds this process.

A response takes tens of milliseconds to solve (3670 liver: about 45 ms idle), and a first touch
needs a few. Solved where they are asked for, they stall the frame that touches new ground, so the
force starts that much later. With ``background`` they are solved by a worker thread instead, and
until a particle's response is ready (on a first touch of an organ never factored, the factor's
seconds) the load is shared by the touched particles whose responses
are (none ready: the shell stays at rest, the paper's still region, whose force is up to about
+50 % on the liver; the first response ready then comes in over ``READY_RAMP``). A touch starts with
a small load on a particle just reached, so on an idle machine that costs little (3670 liver
pressed at 20 mm/s: Fz within 13 mN of waiting); beside a busy process the worker, the lowest
priority, had not finished within a 0.5 s press. The result depends on the
thread's timing, so stepping that must repeat bit for bit (lockstep goldens, validation) waits.
"""

from __future__ import annotations

import atexit
import hashlib
import queue
import threading
import time
import weakref

import numpy as np
from numba import njit

from .organ_factor import FactorProcess, organ_arrays
from .response_store import ResponseStore

#: the elasticity tangent acts on row-major 3x3 tensors: index of H[a, b] in a 9-vector
_AB = np.arange(9).reshape(3, 3)


def _gradient_operator(n: int, offsets: np.ndarray, indices: np.ndarray, g: np.ndarray, gsum: np.ndarray):
    """(9n, 3n) sparse map of the displacements ``u`` (row-major, 3 per particle) to the rows of
    ``H_i = sum_j (u_j - u_i) (x) g_ij`` (9 per particle, row-major)."""
    import scipy.sparse as sp
    rows_i = np.repeat(np.arange(n), np.diff(offsets))
    own = np.arange(n)
    r, c, v = [], [], []
    for a in range(3):
        for b in range(3):
            r += [9 * rows_i + _AB[a, b], 9 * own + _AB[a, b]]
            c += [3 * indices + a, 3 * own + a]
            v += [g[:, b], -gsum[:, b]]
    return sp.csr_matrix((np.concatenate(v), (np.concatenate(r), np.concatenate(c))), shape=(9 * n, 3 * n))


def linear_stiffness(X: np.ndarray, offsets: np.ndarray, indices: np.ndarray, g: np.ndarray,
                     gsum: np.ndarray, w0: np.ndarray, volume: float, G: float, K: float, hg_k: float):
    """``K`` (3n, 3n, scipy CSR) with ``f = -K u`` the :mod:`.tlsph` internal forces (elastic and
    hourglass, no dashpot) at ``x = X + u`` to first order in ``u`` (see the module docstring)."""
    import scipy.sparse as sp
    n, nnz = len(X), len(indices)
    B = _gradient_operator(n, offsets, indices, g, gsum)
    lam = K - 2.0 * G / 3.0
    D = np.zeros((9, 9))
    for a in range(3):
        for b in range(3):
            D[_AB[a, b], _AB[a, b]] += G
            D[_AB[a, b], _AB[b, a]] += G
            D[_AB[a, a], _AB[b, b]] += lam
    k_el = volume * (B.T @ sp.kron(sp.identity(n, format='csr'), sp.csr_matrix(D), format='csr') @ B)
    # hourglass: pair k = (i, j) with unit bond n_k; s_k = n_k . ((H_i + H_j)/2 X'_k - (u_j - u_i)),
    # f_i -= w0_k hg_k s_k n_k
    rows_i = np.repeat(np.arange(n), np.diff(offsets))
    Xp = X[indices] - X[rows_i]
    nk = Xp / np.linalg.norm(Xp, axis=1)[:, None]
    pair = np.arange(nnz)
    load = sp.csr_matrix(((nk * (w0 * hg_k)[:, None]).ravel(),
                          ((3 * rows_i[:, None] + np.arange(3)).ravel(), np.repeat(pair, 3))),
                         shape=(3 * n, nnz))
    coef = 0.5 * (nk[:, :, None] * Xp[:, None, :]).reshape(nnz, 9)
    pick = sp.csr_matrix((np.concatenate([coef.ravel(), coef.ravel()]),
                          (np.tile(np.repeat(pair, 9), 2),
                           np.concatenate([(9 * rows_i[:, None] + np.arange(9)).ravel(),
                                           (9 * indices[:, None] + np.arange(9)).ravel()]))),
                         shape=(nnz, 9 * n))
    bond = sp.csr_matrix((np.concatenate([nk.ravel(), -nk.ravel()]),
                          (np.tile(np.repeat(pair, 3), 2),
                           np.concatenate([(3 * indices[:, None] + np.arange(3)).ravel(),
                                           (3 * rows_i[:, None] + np.arange(3)).ravel()]))),
                         shape=(nnz, 3 * n))
    k_hg = (load @ pick) @ B - load @ bond
    return (k_el + k_hg).tocsr()


#: compliances whose worker was started: closed at exit, for the reason in OrganCompliance.close
_working: 'weakref.WeakSet[OrganCompliance]' = weakref.WeakSet()


@atexit.register
def close_all() -> None:
    """End the factoring process and every worker (at exit; a process that leaves with
    ``os._exit`` calls it first, or its factoring process outlives it)."""
    global _last_factor
    if _last_factor is not None:
        _last_factor.close()   # a worker waiting on the child then sees the pipe closed
        _last_factor = None
    for organ in list(_working):
        organ.close(EXIT_JOIN)


#: [s] how long the process's exit waits for a worker to finish
EXIT_JOIN = 2.0

#: [s] in the background, the shell's displacement grows from rest to the organ's response over
#: this long once a touch has a response ready
READY_RAMP = 0.05

#: the last factoring process: a solver rebuilt on the same organ and material (a parameter change
#: in sim_node, every press of the validation) asks it instead of paying the factor again; one
#: kept, so at most one factor no solver uses is held
_last_factor: FactorProcess | None = None


def stiffness_key(X: np.ndarray, fixed: np.ndarray, state) -> bytes:
    """A digest of everything :func:`linear_stiffness` and the held particles depend on."""
    h = hashlib.blake2b(digest_size=20)
    for a in (X, np.asarray(fixed, dtype=bool), state.offsets, state.indices, state.g, state.gsum, state.w0):
        a = np.ascontiguousarray(a)
        h.update(f'{a.dtype.str}{a.shape}'.encode())
        h.update(a.tobytes())
    h.update(np.array([state.volume, state.G, state.K, state.hg_k], dtype=np.float64).tobytes())
    return h.digest()


class OrganCompliance:
    """The still organ's displacement under a load at one of its particles (:func:`linear_stiffness`
    factored on the free particles).

    Args:
        X: (N, 3) reference positions [m]; fixed: (N,) held particles.
        state: the :class:`~.tlsph.Tlsph` state of the model's material (its pairs, gradients,
            hourglass weights and moduli).
        share: [m] a particle this near one whose response is solved uses that response.
        abort: (1,) flag another thread sets to stop :meth:`place` between two responses (a
            first touch solves a few, each tens of ms; the solver's interrupt flag).
        background: solve the responses on a worker thread; :meth:`place` never waits for one.
    """

    def __init__(self, X: np.ndarray, fixed: np.ndarray, state, share: float = 0.0,
                 abort: np.ndarray | None = None, background: bool = False) -> None:
        global _last_factor
        self.X, self.n, self.share = X, len(X), share
        self.abort = np.zeros(1, dtype=np.int8) if abort is None else abort
        self.background = background
        self.free_dofs = np.flatnonzero(np.repeat(~np.asarray(fixed, dtype=bool), 3))
        key = stiffness_key(X, fixed, state)
        #: the responses solved before, on disk
        self.disk = ResponseStore(key, self.n)
        #: the factoring process is the previous organ's (same stiffness), not started for this one
        self.reused = _last_factor is not None and _last_factor.key == key
        if not self.reused:
            if _last_factor is not None:
                _last_factor.close()   # its memory back before the new factor's peak
            _last_factor = FactorProcess(key, organ_arrays(X, fixed, state, self.free_dofs, self.disk.folder))
        #: builds, factors and solves in a process of its own at the first response not on disk
        self.factor = _last_factor
        if background and not self.factor.started and len(self.disk) == 0:
            # never touched before: its first touch will need the factor, so it starts now
            self.factor.start_soon()
        #: row of ``store`` holding particle i's response (-1: none yet); a particle within
        #: ``share`` of a solved one points at that one's row
        self.slot = np.full(self.n, -1, dtype=np.int32)
        self.store = np.zeros((0, self.n, 3, 3), dtype=np.float32)
        self.solved = np.zeros(0, dtype=np.int64)
        self.n_columns = 0
        # the worker publishes a response under this lock, and place() reads them under it
        self._publish = threading.Lock()
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._pending: set[int] = set()
        self._worker: threading.Thread | None = None
        self._closed = False
        self._closing = np.zeros(1, dtype=np.int8)   # ends the worker's wait for the factor
        #: per load (instrument): when its touch's first response was ready (monotonic s)
        self._ready_since: dict[int, float] = {}
        #: the last exception a background solve raised (None: none did)
        self.failure: Exception | None = None

    def _solve(self, c: int, abort: np.ndarray | None = None) -> np.ndarray | None:
        """``c``'s response from disk, else from the factoring process (None: ``abort`` was set)."""
        u = self.disk.load(c)
        return u if u is not None else self.factor.solve(c, abort)

    def _share(self, c: int) -> bool:
        """Point ``c`` at a solved response within ``share`` of it, if there is one."""
        if len(self.solved):
            d = np.linalg.norm(self.X[self.solved] - self.X[c], axis=1)
            k = int(np.argmin(d))
            if d[k] <= self.share:
                self.slot[c] = self.slot[self.solved[k]]
                return True
        return False

    def _keep(self, c: int, u: np.ndarray) -> None:
        if self.n_columns == len(self.store):
            grown = np.zeros((max(8, 2 * len(self.store)), self.n, 3, 3), dtype=np.float32)
            grown[:self.n_columns] = self.store[:self.n_columns]
            self.store = grown
        self.store[self.n_columns] = u
        self.slot[c] = self.n_columns
        self.solved = np.append(self.solved, c)
        self.n_columns += 1

    def column(self, c: int, abort: np.ndarray | None = None) -> np.ndarray | None:
        """(N, 3, 3) displacement [m/N] of every particle (axis 1) under a unit force along each
        axis (axis 2) on particle ``c`` (or on a particle within ``share`` of it whose response
        was solved before); zero if ``c`` is held. Waits for it if need be, in either mode, until
        ``abort[0]`` is set (then None)."""
        with self._publish:
            if self.slot[c] >= 0 or self._share(c):
                return self.store[self.slot[c]]
        u = self._solve(c, abort)
        if u is None:
            return None
        with self._publish:
            if self.slot[c] < 0:   # the worker may have solved it meanwhile
                self._keep(c, u)
            return self.store[self.slot[c]]

    def _request(self, c: int) -> None:
        """Queue ``c``'s response for the worker, started by the first request (it waits on the
        disk and the factoring process, holding the interpreter only to read a response)."""
        if c not in self._pending:
            self._pending.add(c)
            self._queue.put(c)
            if self._worker is None and not self._closed:
                self._worker = threading.Thread(target=self._work, name='organ-responses', daemon=True)
                self._worker.start()
                _working.add(self)

    def _work(self) -> None:
        while True:
            c = self._queue.get()
            if c < 0:
                return
            try:
                self.column(c, self._closing)
            except Exception as exc:   # noqa: BLE001  (the worker must outlive one failed solve)
                self.failure = exc     # the particle is asked for again at its next touch
            with self._publish:
                self._pending.discard(c)

    @property
    def pending(self) -> int:
        """How many responses the worker has still to solve."""
        with self._publish:
            return len(self._pending)

    def wait(self, timeout: float | None = None) -> bool:
        """Wait until the worker has solved every response asked for; False on ``timeout`` [s]."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while self.pending:
            if deadline is not None and time.monotonic() > deadline:
                return False
            time.sleep(0.002)
        return True

    def close(self, timeout: float = 0.0) -> bool:
        """Stop the worker (a wait for the factoring process ends within its poll), waiting up to
        ``timeout`` [s] for it; no worker starts after this. False if it is still running. The
        factoring process is kept for a solver on the same organ (closed with the next organ's,
        or by :func:`close_all` at exit)."""
        with self._publish:
            self._closed = True
            worker = self._worker
        if worker is None:
            return True
        self._closing[0] = 1
        self._queue.put(-1)
        worker.join(timeout)
        return not worker.is_alive()

    def place(self, x: np.ndarray, X: np.ndarray, idx: np.ndarray, at: np.ndarray, weights: np.ndarray,
              load: np.ndarray) -> bool:
        """Put particles ``idx`` at ``X`` plus their displacement under ``load`` [N] shared by the
        particles ``at`` in proportion to ``weights`` (:meth:`place_loads` with one load)."""
        return self.place_loads(x, X, idx, [(at, weights, load)])

    def place_loads(self, x: np.ndarray, X: np.ndarray, idx: np.ndarray, loads: list) -> bool:
        """Put particles ``idx`` at ``X`` plus their displacement under several loads (the organ is
        linear: the responses add): ``loads`` holds per load ``(at, weights, load)``, the load [N]
        shared by the particles ``at`` in proportion to ``weights``. Waiting, the responses not
        solved yet are solved here, and the call returns False, with nothing moved, once ``abort``
        is set (the responses solved so far are kept). In the background they are queued, and each
        load is shared by its particles whose responses are ready (none ready at all: ``idx`` at
        rest), the displacement growing over ``READY_RAMP`` from the first one ready."""
        if not self.background:
            loads = [(at, w, load) for at, w, load in loads if len(at)]
            for at, _, _ in loads:
                for c in at.tolist():
                    if self.abort[0] != 0 or self.column(c, self.abort) is None:
                        return False
            self._place(x, X, idx, [(at, w / float(np.sum(w)), load) for at, w, load in loads])
            return True
        with self._publish:
            shares = []
            now = time.monotonic()
            for i, (at, w, load) in enumerate(loads):
                ready = np.array([self.slot[c] >= 0 or self._share(c) for c in at.tolist()], dtype=bool)
                for c in at[~ready].tolist():
                    self._request(c)
                total = float(np.sum(w[ready]))
                if total <= 0.0:
                    self._ready_since.pop(i, None)
                    continue
                # a response that came late (a busy machine: hundreds of ms) would move the shell
                # from rest at once, a step in the force; each load comes in over READY_RAMP instead
                gain = min(1.0, (now - self._ready_since.setdefault(i, now)) / READY_RAMP)
                shares.append((at[ready], w[ready] * (gain / total), load))
            if shares:
                self._place(x, X, idx, shares)
            else:
                x[idx] = X[idx]
        return True

    def _place(self, x: np.ndarray, X: np.ndarray, idx: np.ndarray, shares: list) -> None:
        """:func:`organ_place` of ``(at, weights, load)`` shares (weights already normalised)."""
        if len(shares) == 1:
            at, w, load = shares[0]
            organ_place(x, X, idx, at, w, self.slot, self.store, np.broadcast_to(load, (len(at), 3)))
            return
        organ_place(x, X, idx, np.concatenate([at for at, _, _ in shares]),
                    np.concatenate([w for _, w, _ in shares]), self.slot, self.store,
                    np.concatenate([np.broadcast_to(load, (len(at), 3)) for at, _, load in shares]))


@njit(cache=True, nogil=True)
def organ_place(x, X, idx, at, w, slot, store, loads):
    """``x_j = X_j + sum_t w_t C(j, at_t) loads_t`` for j in ``idx`` (``C`` the responses in
    ``store``, row ``slot[at_t]``; the weights of each load's particles sum to 1)."""
    for q in range(idx.shape[0]):
        j = idx[q]
        u0 = 0.0; u1 = 0.0; u2 = 0.0
        for t in range(at.shape[0]):
            c = store[slot[at[t]], j]
            wt = w[t]
            load = loads[t]
            u0 += wt * (c[0, 0] * load[0] + c[0, 1] * load[1] + c[0, 2] * load[2])
            u1 += wt * (c[1, 0] * load[0] + c[1, 1] * load[1] + c[1, 2] * load[2])
            u2 += wt * (c[2, 0] * load[0] + c[2, 1] * load[1] + c[2, 2] * load[2])
        x[j, 0] = X[j, 0] + u0; x[j, 1] = X[j, 1] + u1; x[j, 2] = X[j, 2] + u2


@njit(cache=True, nogil=True)
def shell_and_ring(body, topo, sets, mark, ff_list, n_ff, x):
    """The still particles the organ's far field moves: the stress shell (still particles that
    solved ones read) and the shell's own neighbours, whose positions its deformation gradient
    reads (held at rest, they made the shell look stretched and the area 2-5 % too stiff).

    Particles in ``ff_list[:n_ff]`` (the previous frame's) that are neither solved nor listed now
    go back to rest. ``mark`` (n,) int8 is zero on entry and on return. Returns the new count
    (``ff_list[:count]``).
    """
    X, fixed = body.X, body.fixed
    offsets, indices = topo.offsets, topo.indices
    for t in range(sets.n_sph):
        mark[sets.sph[t]] = 1
    for t in range(sets.n_layer):
        mark[sets.layer[t]] = 1
    for t in range(n_ff):
        j = ff_list[t]
        if mark[j] == 0:
            x[j, 0] = X[j, 0]; x[j, 1] = X[j, 1]; x[j, 2] = X[j, 2]
    m = 0
    for t in range(sets.n_stress):
        j = sets.stress[t]
        if mark[j] == 0 and not fixed[j]:
            mark[j] = 2
            ff_list[m] = j
            m += 1
    n_shell = m
    for t in range(n_shell):
        i = ff_list[t]
        for k in range(offsets[i], offsets[i + 1]):
            j = indices[k]
            if mark[j] == 0 and not fixed[j]:
                mark[j] = 2
                ff_list[m] = j
                m += 1
    for t in range(m):
        mark[ff_list[t]] = 0
    for t in range(sets.n_sph):
        mark[sets.sph[t]] = 0
    for t in range(sets.n_layer):
        mark[sets.layer[t]] = 0
    return m
