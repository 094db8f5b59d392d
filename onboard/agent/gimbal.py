"""The agent's view of its camera gimbal (pure logic, no I/O): the gimbal's reports as :class:`GimbalAttitude`
messages, their time base, and the check that the gimbal reaches what it was told.

* :func:`attitude_message` -- one MAVSDK gimbal ``Attitude`` (MAVLink GIMBAL_DEVICE_ATTITUDE_STATUS) as the
  :class:`shared_msgs.GimbalAttitude` the agent publishes and records on ``<drone>/gimbal``.
* :class:`BootClock` -- the gimbal reports its time since the autopilot booted; mapped to the wall clock
  (``t_measurement_ns``) with the smallest observed transport delay.
* :class:`GimbalWatch` -- after a command, the reported attitude must come within ``tolerance_deg`` of it
  within ``settle_timeout_s``, or the gimbal is reported (once per command) as not following: a Health warning.
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass

from shared_msgs import GimbalAttitude

__all__ = ["BootClock", "GimbalWatch", "attitude_message"]


class BootClock:
    """Maps a sender's boot-time stamps (us) to wall-clock ns: wall = stamp + offset, the offset being the
    smallest (arrival wall time - stamp) seen over the last ``window_s`` of arrivals (the report's fastest transport
    lately), reset when the stamps jump back (the autopilot restarted).

    The window makes it follow a sender clock that drifts from the wall clock (a simulator whose simulated time
    falls behind on a loaded machine slipped 32 s in a 40 s flight: with one offset kept from the start, a camera
    frame was given the gimbal pitch of seconds later). A real autopilot drifts by ppm, which the window follows
    too; transport jitter shorter than the window is still removed."""

    def __init__(self, window_s: float = 1.0) -> None:
        self.window_ns = int(window_s * 1e9)
        self._last_us = -1
        self._mins: collections.deque[tuple[int, int]] = collections.deque()  # (arrival_ns, offset_ns), offsets rising

    def to_wall_ns(self, stamp_us: int, arrival_ns: int) -> int:
        if stamp_us <= 0:
            return arrival_ns
        if stamp_us < self._last_us:
            self._mins.clear()
        self._last_us = stamp_us
        off = arrival_ns - stamp_us * 1000
        while self._mins and self._mins[-1][1] >= off:  # a sliding-window minimum (monotonic deque)
            self._mins.pop()
        self._mins.append((arrival_ns, off))
        while self._mins[0][0] < arrival_ns - self.window_ns:
            self._mins.popleft()
        return stamp_us * 1000 + self._mins[0][1]


def _rad(deg: float) -> float:
    return math.radians(deg) if math.isfinite(deg) else math.nan


def attitude_message(drone_id: str, att, t_measurement_ns: int, seq: int, vehicle_yaw_rad: float = math.nan) -> GimbalAttitude:
    """A MAVSDK ``gimbal.Attitude`` as :class:`GimbalAttitude` (radians). ``yaw_north_rad``: MAVSDK's own (from the
    vehicle heading it reads), else forward yaw + ``vehicle_yaw_rad``, else NaN."""
    fwd, north, w = att.euler_angle_forward, att.euler_angle_north, att.angular_velocity
    yaw = _rad(fwd.yaw_deg)
    yaw_north = _rad(north.yaw_deg)
    if not math.isfinite(yaw_north) and math.isfinite(yaw) and math.isfinite(vehicle_yaw_rad):
        yaw_north = (yaw + vehicle_yaw_rad + math.pi) % (2 * math.pi) - math.pi
    return GimbalAttitude(
        header=GimbalAttitude.make_header(drone_id, t_measurement_ns, seq),
        gimbal_id=int(att.gimbal_id), roll_rad=_rad(fwd.roll_deg), pitch_rad=_rad(fwd.pitch_deg), yaw_rad=yaw,
        yaw_north_rad=yaw_north,
        angular_velocity_rad_s=tuple(float(x) if math.isfinite(x) else 0.0
                                     for x in (w.roll_rad_s, w.pitch_rad_s, w.yaw_rad_s)),
    )  # fmt: skip


@dataclass
class GimbalWatch:
    """Does the gimbal reach its commanded angles? Feed it commands and reports; :meth:`check` returns a warning
    text once per command that was not reached (within ``tolerance_deg`` on pitch and yaw) ``settle_timeout_s``
    after it was sent, or when no report came for that long after a command."""

    tolerance_deg: float = 2.0
    settle_timeout_s: float = 3.0

    def __post_init__(self) -> None:
        self._cmd: tuple[float, float, float] | None = None  # (t_s, pitch_rad, yaw_rad)
        self._reached = False
        self._warned = False
        self._last: tuple[float, float, float] | None = None  # (t_s, pitch_rad, yaw_rad) of the latest report
        self.warnings = 0

    def command(self, t_s: float, pitch_rad: float, yaw_rad: float = 0.0) -> None:
        """A command sent at ``t_s`` (yaw relative to the heading, as the agent's yaw-follow commands are)."""
        if self._cmd is not None and not self._reached and not self._warned:
            # a new command before the last was reached (commands at 2 Hz while the camera pitch changes):
            # keep timing from the older one, so that a gimbal that never follows is still noticed
            self._cmd = (self._cmd[0], pitch_rad, yaw_rad)
        else:
            self._cmd = (t_s, pitch_rad, yaw_rad)
            self._reached = self._warned = False
        self._update()

    def report(self, t_s: float, pitch_rad: float, yaw_rad: float) -> None:
        self._last = (t_s, pitch_rad, yaw_rad)
        self._update()

    def _update(self) -> None:
        if self._cmd is None or self._last is None or self._reached:
            return
        _, p, y = self._cmd
        _, rp, ry = self._last
        tol = math.radians(self.tolerance_deg)
        dy = (ry - y + math.pi) % (2 * math.pi) - math.pi
        if abs(rp - p) <= tol and abs(dy) <= tol:
            self._reached = True

    def check(self, t_s: float) -> str | None:
        """A warning when the pending command is overdue (once per command), else None."""
        if self._cmd is None or self._reached or self._warned or t_s - self._cmd[0] < self.settle_timeout_s:
            return None
        self._warned = True
        self.warnings += 1
        t0, p, y = self._cmd
        if self._last is None or self._last[0] < t0:
            return (f"gimbal not reporting: no attitude {self.settle_timeout_s:.0f} s after commanding pitch "
                    f"{math.degrees(p):.1f} deg")
        return (f"gimbal not following: at pitch {math.degrees(self._last[1]):.1f} yaw {math.degrees(self._last[2]):.1f} "
                f"deg {t_s - t0:.1f} s after commanding pitch {math.degrees(p):.1f} yaw {math.degrees(y):.1f} deg")
