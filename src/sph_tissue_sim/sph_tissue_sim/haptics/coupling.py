"""Virtual coupling: the device point joined to the simulated tool by a spring-damper.

The solver answers at its own rate; between its answers the coupling renders a **local contact
model**: the reaction ``F0`` (a vector, push only) the solver found with the tool at ``x0`` and the
tissue's stiffness ``k`` along the contact normal ``n = F0 / |F0|``::

    F(x) = F0 - k n (n . (x - x0))        while F(x) . n > 0, else 0

``k`` is the secant stiffness of the solver's own answers along the normal (tool and tissue in
series, so it is what the hand should feel, not the stiffer frozen-particle penalty), low-pass
filtered over refreshes and kept in ``[0, k_max]``.

A model that served ``m >= 4`` poses (a live solver's) is stale by then: its successor would change
the force at the proxy at once, by the tissue's motion over those poses (a click of 15-40 mN on the
bags' live schedule). The jump ``c`` (old model minus new, at the proxy) is carried in ``F0`` and
taken out in equal parts over the next ``min(m // 2, BLEND_POSES)`` poses, so the force at the proxy
is continuous and the new model holds alone well before its successor is due (blending over all
``m`` poses lagged more: a poke answered 16 poses late gave 1.8 uJ back)::

    F(x) = F0 + c - k n (n . (x - x0)),    c -> 0 over the blend

A model refreshed every pose or nearly (lockstep, ``m < 4``) is taken at once, as before.

A live solver's answer that finds no contact is not taken at once either: the model is kept for
one more answer and dropped when that one finds no contact too. A live solver 80 ms behind the
hand can lose a sideways contact for one answer (its tool where the hand was, sliding across the
surface), and taking that answer dropped the force to nothing and back (0.66 N -> 0 for 13 frames
-> 0.5 N in a demo). A hand that really left along the normal still loses the force with the
model's stiffness about its anchor (one that slid off sideways keeps it until the next answer), and
the energy bound (:mod:`.passivity`) caps what the kept model can give back. Lockstep answers
(``live`` False, any ``solver_every``) are taken as they come.

The simulated tool (the proxy ``x_t = x^ + a``) is held by a spring ``K_c`` to the filtered device
point ``x^``, pushed by the contact model, and its offset ``a`` from the device point is damped by
``B_p``. Each sample updates the offset implicitly (a 3x3 solve, Sherman-Morrison)::

    B_p (a - a') / T = -K_c a + F0 - k n n . (x^ + a - x0)

(``a'`` the offset a sample ago). At rest this is the quasi-static coupling ``K_c a = F(x_t)``: the
hand feels the tissue in series with ``K_c``, never stiffer than ``K_c``. The damper keeps the loop
through the solver stable: the solver answers at the proxy a sample (or more) later and, within one
frame, with its stiff penalty contact ``K_s``; the update is stable while ``K_s < 2 B_p / T + K_c +
2 k`` (``B_p`` 4 N s/m: about 8700 N/m at 1 kHz before ``k`` has learned anything). It also makes
the proxy slide into and out of contact instead of jumping, so the solver's contact dashpot never
sees a jump. The damper acts on the offset, not on the proxy's motion in the world: in free space
the offset decays (time constant ``B_p / K_c``, 5.7 ms) and the proxy moves with the device, so a
fast approach does not arrive with a stretched spring (a damper to the world trailed the device by
``B_p / K_c`` times its speed: with 2 N s/m, 0.7 mm at 0.24 m/s, felt as 0.5 N the moment contact
began).

The spring pulls the proxy with at most ``P`` (the force the device can render, the renderer's
``force_limit``): stretched further, it pulls with ``P`` along ``u = a / |a|``,

    B_p (a - a') / T = -P u + F0 - k n n . (x^ + a - x0),

so the proxy rests where the tissue holds ``P`` however deep the device goes (a god-object on
the surface: pressed past what the hand can feel, the simulated tool does not follow the device
through the tissue). The device then feels ``P``, as it would after its own clamp; the saturated
spring is a function of the stretch alone, so it stores and returns energy like the spring.

The device receives the spring's force ``K_c (x_t - x^)`` (at most ``P``) plus a damper
``-B_c (u . v^) u`` on the device's velocity along the spring, ``u = a / |a|``, while the spring
pushes (``. n > 0``); never a pull. At rest ``u`` is the normal ``n``; it differs where the
reaction turns, and then it turns with the offset, over about ``B_p / K_c``, where ``n`` turns with
each answer. A grasp's reaction is a bilateral pull: near its onset and where the jaw's press turns
into a lift the pull is a few tens of mN, and each lateral encoder tick drags the held particles and
tilts the solver's reaction by 20-60 degrees for one answer; a damper along ``n`` swung with it, by
7-15 mN a frame (``bags/grasp``, anchors not yet lagged: |dF| p99 7.8 mN; 4.5 mN along ``u``).

With zero-order hold, a rendered stiffness ``K`` is passive when the damping exceeds ``K T / 2``
(Colgate and Brown); the default ``K_c`` 700 N/m (what a PHANTOM Omni renders, about 0.7 N/mm) needs
``B_c > 0.35 N s/m`` at 1 kHz. The default ``B_c`` is 1.5 N s/m: the loop through the solver and
the estimator's overshoot are active too, and with 0.5 a poke session on tissue ten times stiffer
than the liver gave energy back (E_in -85 uJ; with 1.5 it stays >= 0).
"""

from __future__ import annotations

import math

import numpy as np

#: a refresh moved the proxy less than this along the normal: too little to measure a stiffness [m]
MIN_SECANT_TRAVEL = 2e-6
#: the most poses a stale model's jump is spread over (half of the 100 poses between the refreshes
#: of a solver five times slower than real time; a longer stall is a fault, not a schedule)
BLEND_POSES = 50
#: weight of a new secant in the filtered stiffness when the model served one pose (about 20 poses
#: of memory; a model that served ``m`` poses weighs its successor's secant ``1 - (1 - gain)^m``)
STIFFNESS_GAIN = 0.05


class ContactModel:
    """The last reaction the solver found, and the tissue's normal stiffness about it."""

    def __init__(self, k_max: float) -> None:
        self.k_max = k_max
        self.clear()

    def clear(self) -> None:
        """Forget everything (the tissue was reset)."""
        self.lose()
        self.stiffness = 0.0          # k [N/m]
        self.refreshes = 0
        self.kept = False             # the last answer found no contact and the model was kept

    def lose(self) -> None:
        """The contact ended: no force, but the tissue's stiffness is kept for the next touch (with
        k = 0 every touch would begin as a force a refresh late, which is active)."""
        self.force = np.zeros(3)      # F0 [N]
        self.point = np.zeros(3)      # x0 [m]
        self.normal = np.zeros(3)     # n
        self.magnitude = 0.0          # |F0| [N]
        self.carry = np.zeros(3)      # c: the jump still to take out [N]
        self._carry_step = np.zeros(3)
        self._carry_left = 0          # poses until c is gone

    def at(self, x) -> np.ndarray:
        """The model's push at ``x`` [m] (carry included): zero without contact or where it would
        pull."""
        if self.magnitude == 0.0:
            return np.zeros(3)
        depth = float(self.normal @ (np.asarray(x, float) - self.point))
        f = self.anchor_force() - (self.stiffness * depth) * self.normal
        return f if float(f @ self.normal) > 0.0 else np.zeros(3)

    def anchor_force(self) -> np.ndarray:
        """``F0 + c``: the force the model renders at ``x0``."""
        return self.force + self.carry if self._carry_left else self.force

    def advance(self) -> None:
        """One pose passed: take the next part of the carried jump out."""
        if self._carry_left:
            self._carry_left -= 1
            self.carry = self.carry - self._carry_step if self._carry_left else np.zeros(3)

    def refresh(self, point, force, served: int = 1, proxy=None, live: bool = False) -> bool:
        """The solver found reaction ``force`` [N] with the tool at ``point`` [m]; the model it
        replaces answered ``served`` poses. With ``proxy`` [m] (where the simulated tool is now)
        and ``served >= 4``, the force there stays what it was and the change comes over the next
        ``served // 2`` poses (see the module docstring). ``live``: a solver thread's answer, which
        is kept over once when it finds no contact. Returns False for an answer kept over (the
        model in use goes on serving).

        The stiffness's memory is counted in poses, not refreshes: a live solver refreshes every
        15-30 poses, and with a per-refresh memory of 20 the first touch rendered a flat force
        between refreshes (k 19 N/m after the first 3 mm poke against 57 N/m), a staircase that
        lagged on the way in and gave energy back on the way out."""
        point = np.array(point, dtype=float)
        force = np.array(force, dtype=float)
        mag = math.sqrt(float(force @ force))
        blend = min(int(served) // 2, BLEND_POSES) if proxy is not None else 0
        if mag == 0.0:
            if live and self.magnitude > 0.0 and not self.kept:
                self.kept = True
                return False
            self.kept = False
            self.lose()
            self.point = point
            return True
        self.kept = False
        before = self.at(proxy) if blend > 1 else None
        normal = force / mag
        if self.magnitude > 0.0:
            travel = float(normal @ (point - self.point))
            if abs(travel) > MIN_SECANT_TRAVEL:
                secant = -(mag - float(normal @ self.force)) / travel
                secant = min(max(secant, 0.0), self.k_max)
                gain = STIFFNESS_GAIN if served <= 1 else 1.0 - (1.0 - STIFFNESS_GAIN) ** served
                self.stiffness += gain * (secant - self.stiffness)
        self.force, self.point, self.normal, self.magnitude = force, point, normal, mag
        self.refreshes += 1
        self._carry_left = 0
        self.carry = np.zeros(3)
        if before is not None:
            self.carry = before - self.at(proxy)
            self._carry_step = self.carry / blend
            self._carry_left = blend
        return True


class VirtualCoupling:
    """The proxy (simulated tool) and the force on the device, against a :class:`ContactModel`."""

    def __init__(self, stiffness: float, damping: float, proxy_damping: float,
                 model: ContactModel, push_limit: float = math.inf) -> None:
        for name, val, low in (('coupling stiffness', stiffness, 'open'),
                               ('coupling damping', damping, 'closed'),
                               ('proxy damping', proxy_damping, 'open')):
            if not (math.isfinite(val) and (val > 0.0 if low == 'open' else val >= 0.0)):
                raise ValueError(f'{name} must be {">" if low == "open" else ">="} 0, got {val}')
        if not push_limit >= 0.0:
            raise ValueError(f'push limit must be >= 0 N, got {push_limit}')
        self.stiffness = stiffness
        self.damping = damping
        self.proxy_damping = proxy_damping
        self.push_limit = push_limit  # P [N]: the most the spring pushes the proxy into the tissue
        self.model = model
        self.proxy: np.ndarray | None = None
        self.offset = np.zeros(3)     # x_t - x^ [m]
        self.stretch = 0.0            # [m] how far the proxy sits outside the device point
        self.spring = np.zeros(3)     # [N] the spring's part of the latest force (the damper's is the rest)

    def reset(self) -> None:
        self.proxy = None
        self.offset = np.zeros(3)
        self.stretch = 0.0
        self.spring = np.zeros(3)

    def render(self, x_hat: np.ndarray, v_hat: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Proxy position and device force for the filtered device point and velocity, ``dt`` [s]
        after the previous sample (``dt <= 0``: the proxy stays where it is)."""
        m = self.model
        if self.proxy is None:
            self.offset = np.zeros(3)
        elif dt > 0.0:
            # B_p (a - a_prev) / dt = -K_c a + F0 - k n n.(x^ + a - x0) for the offset a = x_t - x^,
            # solved for a: ((b + K_c) I + k n n^T) a = r, inverted by Sherman-Morrison
            b, kc, k, n = self.proxy_damping / dt, self.stiffness, m.stiffness, m.normal
            r = b * self.offset + m.anchor_force() - (k * float(n @ (x_hat - m.point))) * n
            self.offset = (r - (k * float(n @ r) / (b + kc + k)) * n) / (b + kc)
            length = math.sqrt(float(self.offset @ self.offset))
            if m.magnitude > 0.0 and kc * length > self.push_limit:
                # saturated: the spring pulls with P along u = a / |a| (from the unsaturated
                # solution), (b I + k n n^T) a = r - P u
                q = r - (self.push_limit / length) * self.offset
                self.offset = (q - (k * float(n @ q) / (b + k)) * n) / b
        self.proxy = x_hat + self.offset
        n = m.normal
        a_n = float(self.offset @ n)
        if m.magnitude == 0.0 or a_n <= 0.0:
            self.stretch = 0.0
            self.spring = np.zeros(3)
            return self.proxy, np.zeros(3)
        self.stretch = a_n
        spring = self.stiffness * self.offset
        pull = math.sqrt(float(spring @ spring))
        if pull > self.push_limit:
            spring *= self.push_limit / pull
        self.spring = spring
        # the damper acts along the spring (its direction the offset's, which moves as smoothly as
        # the proxy), not along the model's normal, which turns with each answer: a grasp's small
        # bilateral pull turned it by 20-60 degrees at a tick and the damper with it
        u = self.offset / math.sqrt(float(self.offset @ self.offset))
        force = spring - (self.damping * float(u @ v_hat)) * u
        return self.proxy, (force if float(force @ n) > 0.0 else np.zeros(3))
