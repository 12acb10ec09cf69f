"""What the hand feels in a force series: smoothness and passivity (numpy only).

One definition of each measure, used by the lockstep replays (``benchmarks/haptic_quality.py``),
the live benchmark (the forces ``sim_node`` published), the demo's closing lines and the viz
report. Input: the device positions ``x`` (M, 3) [m] and the forces ``f`` (M, 3) [N] answered to
them, in order; optionally the poses' stamps ``t`` (M,) [s], where a live run may have poses
without a reply: a change between two rows further apart than ``MAX_FRAME_GAP`` frames is no
frame-to-frame change and is not counted (the energy still is: the device held the force meanwhile).

* **steady contact**: frames more than ``STEADY_AFTER`` frames after the force came on;
* **|dF|**: the norm of the force change from one frame to the next (p99 and max in steady contact);
* **one-frame reversal**: a change of more than ``REVERSAL`` followed at once by one of more than
  ``REVERSAL`` the other way (a drop that comes straight back: a click), anywhere, contact onset
  and loss included;
* **tick share**: on frames where the device moved by exactly one encoder tick, the force change as
  a share of the force (median); ``still``: only ticks after a frame without motion (the
  quantisation alone); ``smooth``: the same for the force's centred ``SMOOTH_WINDOW``-frame mean,
  the floor of the tick share along the same motion;
* **ripple**: |F| minus its centred ``RIPPLE_WINDOW``-frame mean, rms over steady contact;
* **E_in**: the energy the hand put in, each force held until the next pose (zero-order hold),
  ``-sum F_k . (x_{k+1} - x_k)``; a passive rendering keeps it >= 0.
"""

from __future__ import annotations

import numpy as np

TICK = 5.5e-5           # [m] the Omni's encoder resolution (the bundled bags reproduce it)
STEADY_AFTER = 20       # frames after contact onset before contact counts as steady
RIPPLE_WINDOW = 21      # frames of the centred mean the ripple is measured against
SMOOTH_WINDOW = 11      # frames of the centred mean whose tick share is the floor of ``tick %``
REVERSAL = 0.01         # [N] a one-frame change larger than this that comes straight back: a click
MAX_FRAME_GAP = 1.5     # two replies further apart than this many nominal frames are not neighbours
#: the targets a rendering must meet (the lockstep goldens' figures): |dF| p99 [mN], reversals, E_in [uJ]
TARGETS = {'dF_p99_mN': 5.0, 'reversals': 0, 'E_in_min_uJ': -1.0}


def energy_in(x: np.ndarray, f: np.ndarray) -> np.ndarray:
    """E_in [J] after each sample (zero-order hold; 0 at the first)."""
    return -np.cumsum(np.r_[0.0, np.einsum('ij,ij->i', f[:-1], np.diff(x, axis=0))])


def one_frame_reversals(f: np.ndarray, neighbours: np.ndarray | None = None,
                        threshold: float = REVERSAL) -> int:
    """How many frames change the force by more than ``threshold`` and the next frame changes it
    back by more than ``threshold`` (``neighbours[k]``: rows k and k+1 are consecutive frames)."""
    d = np.diff(f, axis=0)
    big = np.linalg.norm(d, axis=1) > threshold
    if neighbours is not None:
        big &= neighbours
    back = np.einsum('ij,ij->i', d[:-1], d[1:]) < 0.0
    return int(np.count_nonzero(big[:-1] & big[1:] & back))


def neighbour_frames(t: np.ndarray | None, m: int, nominal_dt: float = 1e-3) -> np.ndarray:
    """(m-1,) bool: rows k and k+1 are consecutive frames (all of them without stamps)."""
    if t is None:
        return np.ones(max(m - 1, 0), bool)
    return np.diff(t) <= MAX_FRAME_GAP * nominal_dt


def feel(x: np.ndarray, f: np.ndarray, t: np.ndarray | None = None, nominal_dt: float = 1e-3,
         skip: np.ndarray | None = None) -> dict:
    """The smoothness and passivity measures of one force series (see the module docstring);
    ``skip`` (bool per frame): frames left out of the steady ones (a blade's crack steps, where the
    force is meant to drop)."""
    x = np.asarray(x, float)
    f = np.asarray(f, float)
    mag = np.linalg.norm(f, axis=1)
    near = np.r_[False, neighbour_frames(t, mag.size, nominal_dt)]
    run = np.zeros(mag.size, int)
    for k in range(mag.size):
        run[k] = run[k - 1] + 1 if mag[k] > 0.0 and k and near[k] else int(mag[k] > 0.0)
    steady = (run > STEADY_AFTER) & near
    steady[1:] &= steady[:-1]
    if skip is not None:
        steady &= ~np.asarray(skip, dtype=bool)
    dF = np.r_[0.0, np.linalg.norm(np.diff(f, axis=0), axis=1)]
    moved = np.r_[0.0, np.linalg.norm(np.diff(x, axis=0), axis=1)]
    tick = steady & (np.abs(moved - TICK) < 1e-3 * TICK)
    # a tick after a still frame is the quantisation alone; inside a motion the change is also the
    # rendered stiffness times the speed
    still_tick = tick & np.r_[False, moved[:-1] == 0.0]
    e_in = energy_in(x, f) if mag.size else np.zeros(1)
    mean = np.convolve(mag, np.ones(RIPPLE_WINDOW) / RIPPLE_WINDOW, 'same')
    smooth = np.stack([np.convolve(c, np.ones(SMOOTH_WINDOW) / SMOOTH_WINDOW, 'same') for c in f.T], axis=1)
    smooth_dF = np.r_[0.0, np.linalg.norm(np.diff(smooth, axis=0), axis=1)]
    smooth_mag = np.linalg.norm(smooth, axis=1)
    some = steady.any()
    nan = float('nan')
    return {
        'frames': int(mag.size), 'steady_frames': int(steady.sum()),
        'dF_p99_mN': float(np.percentile(dF[steady], 99) * 1e3) if some else nan,
        'dF_max_mN': float(dF[steady].max() * 1e3) if some else nan,
        'reversals': one_frame_reversals(f, near[1:]) if mag.size > 2 else 0,
        'tick_change_pct': float(np.median(dF[tick] / mag[tick]) * 100) if tick.any() else nan,
        'ticks': int(tick.sum()),
        'smooth_tick_change_pct': (float(np.median(smooth_dF[tick] / smooth_mag[tick]) * 100)
                                   if tick.any() else nan),
        'still_tick_change_pct': (float(np.median(dF[still_tick] / mag[still_tick]) * 100)
                                  if still_tick.any() else nan),
        'ripple_mN': float(np.sqrt(np.mean((mag - mean)[steady] ** 2)) * 1e3) if some else nan,
        'E_in_min_uJ': float(e_in.min() * 1e6), 'E_in_final_uJ': float(e_in[-1] * 1e6),
        'peak_N': float(mag.max()) if mag.size else 0.0,
    }


def misses(measures: dict) -> list[str]:
    """The targets (``TARGETS``) a series misses, as short phrases (empty: all met)."""
    out = []
    if measures['dF_p99_mN'] > TARGETS['dF_p99_mN']:
        out.append(f"|dF| p99 {measures['dF_p99_mN']:.1f} mN > {TARGETS['dF_p99_mN']:g}")
    if measures['reversals'] > TARGETS['reversals']:
        out.append(f"{measures['reversals']} one-frame reversals > {REVERSAL * 1e3:g} mN")
    if measures['E_in_min_uJ'] < TARGETS['E_in_min_uJ']:
        out.append(f"E_in min {measures['E_in_min_uJ']:.1f} uJ < {TARGETS['E_in_min_uJ']:g}")
    return out
