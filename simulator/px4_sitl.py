"""Real PX4 SITL (PX4's own SIH quadrotor simulator) as a fleet of vehicles: start, stop, ports, and SIH's truth.

The PX4 build lives outside the project (``../shared/px4-sitl`` beside the checkout, or any folder with
``bin/px4``, ``modules.txt`` and ``etc/``: PX4-Autopilot's ``px4_sitl_default`` build). :class:`Px4Sitl`
starts N instances of it the way that folder's ``start.sh`` does, but with a free choice of the *first
instance number*, so that two fleets (two test sessions, a helper and a demo) can run side by side on one
machine: PX4 keeps a lock and a socket per instance number in the system's temporary folder, and every UDP
port is derived from it.

Instance ``i`` (PX4's ``-i i``; ``MAV_SYS_ID = i + 1``):

* offboard/API link: PX4 sends from UDP ``14580 + i`` to ``14540 + i`` -> the agent connects with
  ``udpin://0.0.0.0:<14540 + i>`` (:meth:`Px4Sitl.connection_url`); instances above 9 all send to 14549,
  so at most instances 0..9 are usable;
* GCS link: UDP ``18570 + i`` -> 14550;
* SIH display link: PX4 sends ``HIL_STATE_QUATERNION`` (SIH's *true* vehicle state: geodetic position,
  attitude, velocity) at 25 Hz from UDP ``19450 + i`` to ``19410 + i`` (:meth:`Px4Sitl.truth_port`), read by
  :class:`SihTruthReader`.

Home (SIH's initial position) per instance from ``homes_geodetic`` (``PX4_HOME_LAT`` / ``PX4_HOME_LON``); the
ground is at SIH_LOC_H0 (PX4's default 489.4 m AMSL) unless ``home_alt_m`` is given. Each instance writes its
parameters, logs and console (``out.log``) into ``workdir/instance_<i>/`` (made fresh).
"""

from __future__ import annotations

import logging
import math
import os
import shutil
import signal
import socket
import subprocess
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from skycap.errors import SkycapError
from skycap.frames import R_from_quat_wxyz, geodetic_to_ned

log = logging.getLogger(__name__)

__all__ = ["Px4SitlError", "Px4Sitl", "SihTruth", "SihTruthReader", "default_px4_folder", "find_px4_folder",
           "PX4_SIH_AIRFRAME"]

#: PX4's SIH quadrotor airframe (``sihsim_quadx``)
PX4_SIH_AIRFRAME = 10040
_READY_TEXT = "Startup script returned successfully"


class Px4SitlError(SkycapError):
    """PX4 SITL is missing, or an instance did not start."""


def default_px4_folder() -> Path:
    """``../shared/px4-sitl`` beside the checkout (or ``$SKYCAP_PX4_SITL``)."""
    env = os.environ.get("SKYCAP_PX4_SITL")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[2] / "shared" / "px4-sitl"


def find_px4_folder(folder: str | Path | None = None) -> Path:
    """The PX4 SITL folder to use (``folder``, else :func:`default_px4_folder`); raises :class:`Px4SitlError`
    naming what is missing and how to fix it."""
    p = Path(folder) if folder else default_px4_folder()
    missing = [n for n in ("bin/px4", "modules.txt", "etc/init.d-posix/rcS") if not (p / n).exists()]
    if missing:
        raise Px4SitlError(
            f"no PX4 SITL build at {p} (missing {', '.join(missing)}): pass the folder of a PX4 px4_sitl_default "
            f"build with SIH (bin/px4, modules.txt, etc/) with --px4-dir, or set SKYCAP_PX4_SITL; the project "
            f"expects it at ../shared/px4-sitl beside the checkout")
    return p


class Px4Sitl:
    """``n`` PX4 SITL instances numbered ``first_instance .. first_instance + n - 1`` (see the module doc).

    Use as a context manager, or :meth:`start` / :meth:`stop`. ``homes_geodetic``: one ``(lat_deg, lon_deg)``
    per vehicle (None: PX4's default home for all, which puts them on top of each other).
    """

    def __init__(self, workdir: str | Path, n: int, *, folder: str | Path | None = None, first_instance: int = 0,
                 homes_geodetic: list[tuple[float, float]] | None = None, home_alt_m: float | None = None,
                 params: dict[str, float] | None = None):
        if n < 1 or first_instance < 0 or first_instance + n > 10:
            raise Px4SitlError(f"PX4 SITL instances {first_instance}..{first_instance + n - 1}: use 0..9 "
                               "(PX4 maps instances above 9 onto one MAVLink port)")
        if homes_geodetic is not None and len(homes_geodetic) != n:
            raise Px4SitlError(f"{len(homes_geodetic)} homes for {n} vehicles")
        self.folder = find_px4_folder(folder)
        self.workdir = Path(workdir)
        self.n = int(n)
        self.first_instance = int(first_instance)
        self.homes_geodetic = homes_geodetic
        self.home_alt_m = home_alt_m
        #: extra PX4 parameters, set through PX4's shell (:meth:`shell`) once each instance is up
        self.params = dict(params or {})
        self.procs: list[subprocess.Popen] = []

    # --- ports ---------------------------------------------------------------------------------------
    def instance(self, k: int) -> int:
        """PX4 instance number of vehicle ``k`` (0-based in this fleet)."""
        return self.first_instance + k

    def system_id(self, k: int) -> int:
        return self.instance(k) + 1

    def offboard_port(self, k: int) -> int:
        return 14540 + self.instance(k)

    def connection_url(self, k: int) -> str:
        """What the agent of vehicle ``k`` connects to (MAVSDK)."""
        return f"udpin://0.0.0.0:{self.offboard_port(k)}"

    def truth_port(self, k: int) -> int:
        """UDP port on which SIH's HIL_STATE_QUATERNION of vehicle ``k`` arrives."""
        return 19410 + self.instance(k)

    def instance_dir(self, k: int) -> Path:
        return self.workdir / f"instance_{self.instance(k)}"

    # --- life ----------------------------------------------------------------------------------------
    def _busy(self) -> list[str]:
        busy = []
        for k in range(self.n):
            for port in (14580 + self.instance(k), 18570 + self.instance(k), 19450 + self.instance(k)):
                s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                try:
                    s.bind(("0.0.0.0", port))
                except OSError:
                    busy.append(f"instance {self.instance(k)} (UDP {port})")
                    break
                finally:
                    s.close()
        return busy

    def start(self, ready_timeout_s: float = 30.0) -> "Px4Sitl":
        """Start every instance and wait until each one's startup script finished (PX4 then still needs a few
        seconds for its estimator before it is armable: the agent waits for health)."""
        busy = self._busy()
        if busy:
            raise Px4SitlError(f"PX4 SITL ports in use: {', '.join(busy)} (another PX4 or the built-in simulator "
                               f"runs there); stop it or choose another first_instance")
        bindir = self.workdir / "bin"
        bindir.mkdir(parents=True, exist_ok=True)
        px4 = bindir / "px4"
        if px4.is_symlink() or px4.exists():
            px4.unlink()
        px4.symlink_to(self.folder / "bin" / "px4")
        for m in (self.folder / "modules.txt").read_text().split():
            link = bindir / m
            if not link.is_symlink():
                link.symlink_to("px4")
        alias = self.folder / "bin" / "px4-alias.sh"
        if alias.exists():
            (bindir / "px4-alias.sh").write_bytes(alias.read_bytes())
        for k in range(self.n):
            d = self.instance_dir(k)
            shutil.rmtree(d, ignore_errors=True)
            d.mkdir(parents=True, exist_ok=True)
            env = dict(os.environ, PX4_SYS_AUTOSTART=str(PX4_SIH_AIRFRAME), PX4_SIMULATOR="sihsim",
                       PX4_SIM_MODEL="sihsim_quadx")
            if self.homes_geodetic is not None:
                env["PX4_HOME_LAT"] = f"{self.homes_geodetic[k][0]:.9f}"
                env["PX4_HOME_LON"] = f"{self.homes_geodetic[k][1]:.9f}"
            if self.home_alt_m is not None:
                env["PX4_HOME_ALT"] = f"{self.home_alt_m:.3f}"
            out = open(d / "out.log", "wb")
            err = open(d / "err.log", "wb")
            p = subprocess.Popen([str(px4), "-i", str(self.instance(k)), "-d", str(self.folder / "etc")], cwd=d,
                                 env=env, stdout=out, stderr=err, stdin=subprocess.DEVNULL, start_new_session=True)
            out.close()
            err.close()
            self.procs.append(p)
            log.info("PX4 SITL instance %d (vehicle %d) pid %d, MAVLink %s, truth UDP %d", self.instance(k), k,
                     p.pid, self.connection_url(k), self.truth_port(k))
        t_end = time.monotonic() + ready_timeout_s
        for k, p in enumerate(self.procs):
            logf = self.instance_dir(k) / "out.log"
            while True:
                if p.poll() is not None:
                    tail = logf.read_text(errors="replace")[-1500:] if logf.exists() else ""
                    self.stop()
                    raise Px4SitlError(f"PX4 SITL instance {self.instance(k)} exited with {p.returncode} at start; "
                                       f"its console ({logf}):\n{tail}")
                if logf.exists() and _READY_TEXT in logf.read_text(errors="replace"):
                    break
                if time.monotonic() > t_end:
                    self.stop()
                    raise Px4SitlError(f"PX4 SITL instance {self.instance(k)} not up after {ready_timeout_s:.0f} s; "
                                       f"see {logf}")
                time.sleep(0.2)
        for name, value in self.params.items():
            for k in range(self.n):
                self.shell(k, f"param set {name} {value}")
        return self

    def shell(self, k: int, command: str, timeout_s: float = 10.0) -> str:
        """Run one PX4 shell command (e.g. ``param set COM_OF_LOSS_T 1``) on vehicle ``k``'s instance (PX4's
        client ``px4-<module>`` talks to the server over its per-instance socket)."""
        words = command.split()
        exe = self.workdir / "bin" / f"px4-{words[0]}"
        r = subprocess.run([str(exe), "--instance", str(self.instance(k)), *words[1:]], cwd=self.instance_dir(k),
                           capture_output=True, text=True, timeout=timeout_s)
        if r.returncode != 0:
            raise Px4SitlError(f"PX4 instance {self.instance(k)}: {command!r} failed ({r.returncode}): "
                               f"{(r.stdout + r.stderr).strip()[-500:]}")
        return r.stdout

    def alive(self) -> list[bool]:
        return [p.poll() is None for p in self.procs]

    def stop(self, timeout_s: float = 5.0) -> None:
        """SIGTERM every instance (SIGKILL after ``timeout_s``)."""
        for p in self.procs:
            if p.poll() is None:
                try:
                    os.killpg(p.pid, signal.SIGTERM)
                except ProcessLookupError:
                    pass
        t_end = time.monotonic() + timeout_s
        for p in self.procs:
            try:
                p.wait(max(0.1, t_end - time.monotonic()))
            except subprocess.TimeoutExpired:
                try:
                    os.killpg(p.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                p.wait(2.0)
        self.procs.clear()

    def __enter__(self) -> "Px4Sitl":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


@dataclass
class SihTruth:
    """SIH's true state of one vehicle at ``t_received_ns`` (HIL_STATE_QUATERNION carries no usable time).

    World NED about the configured origin; ``position_ned_m[2]`` is relative to the origin's altitude."""

    t_received_ns: int
    position_ned_m: np.ndarray  # (3,)
    velocity_ned_m_s: np.ndarray  # (3,)
    q_world_body_wxyz: tuple[float, float, float, float]
    latitude_deg: float
    longitude_deg: float
    altitude_amsl_m: float

    @property
    def R_world_body(self) -> np.ndarray:
        return R_from_quat_wxyz(self.q_world_body_wxyz)


class SihTruthReader:
    """Receives SIH's HIL_STATE_QUATERNION for each vehicle (``ports``, from :meth:`Px4Sitl.truth_port`) in a
    background thread; :meth:`latest` gives the newest :class:`SihTruth` per vehicle, converted to the world
    NED frame about ``origin`` = (lat_deg, lon_deg, alt_m). ``on_truth(k, truth)`` (optional) is called in the
    reader thread for every sample."""

    def __init__(self, ports: list[int], origin: tuple[float, float, float], on_truth=None):
        from pymavlink.dialects.v20 import common as mavlink2

        self.origin = tuple(float(x) for x in origin)
        self.on_truth = on_truth
        self._socks = []
        for port in ports:
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind(("127.0.0.1", port))
            except OSError as e:
                raise Px4SitlError(f"cannot listen for SIH truth on UDP {port}: {e}") from e
            s.settimeout(0.2)
            self._socks.append(s)
        self._parsers = [mavlink2.MAVLink(None, srcSystem=250, srcComponent=190) for _ in ports]
        for p in self._parsers:
            p.robust_parsing = True
        self._latest: list[SihTruth | None] = [None] * len(ports)
        self.counts = [0] * len(ports)
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=self._run, args=(k,), name=f"sih-truth-{k}", daemon=True)
                         for k in range(len(ports))]
        for t in self._threads:
            t.start()

    def _run(self, k: int) -> None:
        s, parser = self._socks[k], self._parsers[k]
        while not self._stop.is_set():
            try:
                data = s.recv(2048)
            except (socket.timeout, OSError):
                continue
            try:
                msgs = parser.parse_buffer(data) or []
            except Exception:
                continue
            for m in msgs:
                if m.get_type() != "HIL_STATE_QUATERNION":
                    continue
                t = self._convert(m)
                if t is None:
                    continue
                self._latest[k] = t
                self.counts[k] += 1
                if self.on_truth is not None:
                    try:
                        self.on_truth(k, t)
                    except Exception:
                        log.exception("SIH truth callback failed")

    def _convert(self, m) -> SihTruth | None:
        lat, lon, alt = m.lat * 1e-7, m.lon * 1e-7, m.alt * 1e-3
        q = tuple(float(v) for v in m.attitude_quaternion)
        if not all(math.isfinite(v) for v in (lat, lon, alt, *q)) or (lat == 0.0 and lon == 0.0):
            return None
        if q[0] < 0:  # one hemisphere (SIH sends w = -1 at rest)
            q = tuple(-v for v in q)
        p = geodetic_to_ned(lat, lon, alt, *self.origin)
        v = np.array([m.vx, m.vy, m.vz], dtype=float) * 1e-2
        return SihTruth(time.time_ns(), np.asarray(p, dtype=float), v, q, lat, lon, alt)

    def latest(self) -> list[SihTruth | None]:
        return list(self._latest)

    def wait_all(self, timeout_s: float = 10.0) -> bool:
        """True once every vehicle sent at least one sample."""
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            if all(t is not None for t in self._latest):
                return True
            time.sleep(0.05)
        return False

    def close(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(1.0)
        for s in self._socks:
            s.close()
