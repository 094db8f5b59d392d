"""``SimWorld``: runs N simulated PX4 multirotors in real time and lets other parts of the simulator watch
the ground truth.

One asyncio event loop (one thread) drives everything: a fixed-rate physics tick (``cfg.physics_hz``,
default 100 Hz) steps the wind and every vehicle, then each vehicle's MAVLink endpoints send what is
due, then the tick hooks run. Why one loop and not one thread per vehicle: the per-vehicle work is
small (~0.2 ms per step) and Python threads would only contend for the GIL; a single loop keeps the
vehicles on one common clock, makes truth snapshots consistent across vehicles, and costs one
wake-up per tick instead of N.

Hook API (for the scene/person/camera part, a truth publisher, a recorder)::

    world = SimWorld(cfg)
    world.add_tick_hook(lambda t_ns, truths: ..., rate_hz=30)   # truths: list[VehicleSnapshot], world NED
    await world.run(stop_event)          # or: world.start_in_thread(); ...; world.stop()

``t_ns`` is wall-clock time (``time.time_ns()``) of the tick, the same clock as the MAVLink
``time_usec`` fields. Hooks run inside the simulation loop: keep them short (copy what you need and
hand heavy work to another thread/process), an exception in a hook is logged and the hook removed.
"""

from __future__ import annotations

import asyncio
import logging
import math
import threading
import time
from dataclasses import dataclass
from typing import Callable

from simulator.config import SimConfig
from simulator.vehicle.autopilot import SimVehicle, VehicleSnapshot
from simulator.vehicle.environment import WindModel
from simulator.vehicle.mavlink_endpoint import GCS_RATES, MavlinkEndpoint
from skycap.errors import SkycapError

log = logging.getLogger(__name__)

TickHook = Callable[[int, list[VehicleSnapshot]], None]


class SimPortError(SkycapError):
    """A simulator UDP port cannot be bound."""


@dataclass
class _Hook:
    fn: TickHook
    period_s: float
    next_s: float = 0.0


class SimWorld:
    """N vehicles, the wind, their MAVLink links, and the tick hooks.

    Args:
        cfg: simulator configuration (validated here).
    """

    def __init__(self, cfg: SimConfig):
        self.cfg = cfg.validate()
        self.vehicles = [SimVehicle(i, cfg) for i in range(cfg.vehicles.count)]
        self.wind = WindModel(cfg.wind, seed=cfg.estimator.seed + 7919)
        self.endpoints: list[MavlinkEndpoint] = []  # offboard links, index = vehicle index
        self.gcs_endpoints: list[MavlinkEndpoint] = []
        self.t_s = 0.0
        self.ticks = 0
        self.overruns = 0
        self._hooks: list[_Hook] = []
        self._stop: asyncio.Event | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None

    # ------------------------------------------------------------------ hooks
    def add_tick_hook(self, fn: TickHook, rate_hz: float | None = None) -> None:
        """Call ``fn(t_ns, truths)`` every physics tick, or at about ``rate_hz`` if given."""
        period = 0.0 if not rate_hz else 1.0 / rate_hz
        self._hooks.append(_Hook(fn, period, self.t_s))

    def remove_tick_hook(self, fn: TickHook) -> None:
        self._hooks = [h for h in self._hooks if h.fn is not fn]

    def truths(self, t_ns: int | None = None) -> list[VehicleSnapshot]:
        """Ground truth of every vehicle now (copies)."""
        t_ns = time.time_ns() if t_ns is None else t_ns
        return [v.truth_snapshot(t_ns) for v in self.vehicles]

    # ------------------------------------------------------------------ links
    async def _open_links(self) -> None:
        loop = asyncio.get_running_loop()
        p = self.cfg.ports
        clock = lambda: self.t_s  # noqa: E731
        for i, v in enumerate(self.vehicles):
            links = [("offboard", p.offboard_base + i, p.local_base + i if p.local_base else 0, self.cfg.rates)]
            if p.gcs_port:
                links.append(("gcs", p.gcs_port, p.gcs_local_base + i if p.gcs_local_base else 0, GCS_RATES))
            for name, remote_port, local_port, rates in links:
                ep = MavlinkEndpoint(v, (p.host, remote_port), rates, clock, name=name)
                try:
                    await loop.create_datagram_endpoint(lambda ep=ep: ep, local_addr=("0.0.0.0", local_port))
                except OSError as e:
                    raise SimPortError(
                        f"cannot bind UDP port {local_port} for vehicle {i} ({name} link): {e}. Is another simulator "
                        f"running? Stop it or choose other ports, e.g. --set ports.local_base=0 (any free port)"
                    ) from e
                (self.endpoints if name == "offboard" else self.gcs_endpoints).append(ep)
                log.info(
                    "vehicle %d (sysid %d) %s link: udp %d -> %s:%d",
                    i,
                    v.system_id,
                    name,
                    ep.local_port,
                    p.host,
                    remote_port,
                )

    def _close_links(self) -> None:
        for ep in self.endpoints + self.gcs_endpoints:
            ep.close()

    # ------------------------------------------------------------------ main loop
    def _tick(self, dt_s: float) -> None:
        self.ticks += 1
        self.t_s = self.ticks * dt_s
        wind = self.wind.step(dt_s)
        for v in self.vehicles:
            v.step(self.t_s, dt_s, wind)
        for ep in self.endpoints:
            ep.tick(self.t_s)
        for ep in self.gcs_endpoints:
            ep.tick(self.t_s)
        if self._hooks:
            due = [h for h in self._hooks if self.t_s + 1e-9 >= h.next_s]
            if due:
                t_ns = time.time_ns()
                truths = self.truths(t_ns)
                for h in due:
                    h.next_s = max(h.next_s + h.period_s, self.t_s) if h.period_s else self.t_s
                    try:
                        h.fn(t_ns, truths)
                    except Exception:
                        log.exception("tick hook %r failed; removed", h.fn)
                        self.remove_tick_hook(h.fn)

    async def run(
        self, stop: asyncio.Event | None = None, duration_s: float | None = None, status_every_s: float = 0.0
    ) -> None:
        """Run in real time until ``stop`` is set or ``duration_s`` elapsed (seconds of simulation)."""
        self._stop = stop or asyncio.Event()
        self._loop = asyncio.get_running_loop()
        await self._open_links()
        self._ready.set()
        dt = 1.0 / self.cfg.physics_hz
        t0 = time.monotonic() - self.ticks * dt
        next_status = status_every_s
        log.info("simulating %d vehicle(s) at %.0f Hz", len(self.vehicles), self.cfg.physics_hz)
        try:
            while not self._stop.is_set():
                if duration_s is not None and self.t_s >= duration_s:
                    break
                delay = t0 + (self.ticks + 1) * dt - time.monotonic()
                if delay > 0:
                    await asyncio.sleep(delay)
                else:
                    # behind real time (a loaded machine): still let the event loop read the links before each
                    # tick, as a real autopilot keeps receiving while busy; catching up without reading them
                    # advanced simulated time past COM_OF_LOSS_T while the agents' setpoints sat in the socket
                    # buffers, and every vehicle fell out of offboard at once
                    await asyncio.sleep(0)
                    if delay < -0.25:  # far behind (debugger, suspended machine): drop the backlog
                        self.overruns += 1
                        log.warning("simulation %.2f s behind real time; skipping ahead", -delay)
                        t0 = time.monotonic() - self.ticks * dt
                self._tick(dt)
                if status_every_s and self.t_s >= next_status:
                    next_status += status_every_s
                    for line in self.status_lines():
                        log.info(line)
        finally:
            self._close_links()

    def status_lines(self) -> list[str]:
        out = []
        for v in self.vehicles:
            s = v.truth
            out.append(
                f"vehicle {v.system_id}: {v.mode.name:<8} {'ARMED' if v.armed else 'disarmed':<8} "
                f"pos_ned=({s.position_ned_m[0]:.1f}, {s.position_ned_m[1]:.1f}, {s.position_ned_m[2]:.1f}) m "
                f"speed={math.hypot(*s.velocity_ned_m_s):.1f} m/s battery={v.battery.remaining_pct:.0f}%"
            )
        return out

    # ------------------------------------------------------------------ background thread (tests, embedding)
    def start_in_thread(self, timeout_s: float = 10.0) -> "SimWorld":
        """Run :meth:`run` on a daemon thread with its own event loop; returns once the ports are bound."""

        def main() -> None:
            try:
                asyncio.run(self.run())
            except BaseException as e:  # surfaced by start_in_thread/stop
                self._error = e
                self._ready.set()

        self._thread = threading.Thread(target=main, name="skycap-sim", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout_s):
            raise SkycapError("simulator did not start within %.0f s" % timeout_s)
        if self._error is not None:
            raise self._error
        return self

    def call_in_loop(self, fn: Callable[[], object]) -> None:
        """Run ``fn()`` inside the simulation loop (thread-safe way to command vehicles from outside)."""
        if self._loop is None:
            fn()
        else:
            self._loop.call_soon_threadsafe(fn)

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop a loop started by :meth:`start_in_thread` (or any running :meth:`run`)."""
        if self._loop is not None and self._stop is not None and not self._loop.is_closed():
            try:
                self._loop.call_soon_threadsafe(self._stop.set)
            except RuntimeError:
                pass
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None
