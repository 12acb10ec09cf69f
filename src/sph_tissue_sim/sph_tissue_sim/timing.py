"""Frame time step from pose stamps (pure Python, no rclpy).

Simulated time follows the stamps of the poses that drive it. The time step of a frame is the
difference to the previous processed stamp, with these rules (so a bad stream never stalls or
explodes the simulation, and the same stream always gives the same steps):

- first pose (or first after a reset): ``nominal_dt``;
- equal stamp (a resent pose): no step (``dt = 0``), the previous force is answered again;
- stamp going backwards (a restarted source, a looping bag): ``nominal_dt``, the clock restarts
  from this stamp;
- stamp jumping forward more than ``max_dt`` (a pause, a dropped stretch): ``max_dt``.
"""

from __future__ import annotations

from dataclasses import dataclass

FIRST, OK, REPEAT, BACKWARDS, JUMP = 'first', 'ok', 'repeat', 'backwards', 'jump'


@dataclass
class StampClock:
    """Turns pose stamps [ns] into frame time steps [s].

    Attributes:
        nominal_dt: step of a first or backwards pose [s].
        max_dt: largest step [s]; longer gaps are clamped.
    """

    nominal_dt: float = 1e-3
    max_dt: float = 0.02

    def __post_init__(self) -> None:
        self.last_ns: int | None = None

    def reset(self) -> None:
        """Forget the previous stamp (the next pose is a first pose)."""
        self.last_ns = None

    def advance(self, stamp_ns: int) -> tuple[float, str]:
        """Time step for a pose stamped ``stamp_ns``; returns (dt [s], kind)."""
        last = self.last_ns
        if last is None:
            self.last_ns = stamp_ns
            return self.nominal_dt, FIRST
        diff = stamp_ns - last
        if diff == 0:
            return 0.0, REPEAT
        self.last_ns = stamp_ns
        if diff < 0:
            return self.nominal_dt, BACKWARDS
        dt = diff * 1e-9
        if dt > self.max_dt:
            return self.max_dt, JUMP
        return dt, OK
