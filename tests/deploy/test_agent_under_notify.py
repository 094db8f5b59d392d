"""The real agent process (``skycap agent`` on the built-in simulator) under systemd's notify protocol, with the
test in systemd's place: it binds the ``NOTIFY_SOCKET`` datagram socket, sets ``WATCHDOG_USEC`` and reads what the
agent says, with the sender's pid (``SO_PASSCRED``: ``NotifyAccess=main`` accepts only the main process).

One flight: STATUS lines, then READY=1 only once the recording file is open and the autopilot connected;
WATCHDOG=1 at least every half ``WATCHDOG_USEC``; a crash in the air (SIGKILL, as a watchdog abort) and the restart
systemd would make: a new sortie file beside the intact old one, and the restarted agent lands the vehicle it
found airborne (``safety.on_restart_airborne = "land"``, the default); SIGTERM -> STOPPING=1 and a clean exit."""

from __future__ import annotations

import hashlib
import os
import signal
import socket
import struct
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from flightdata.folder import FlightFolder

pytestmark = pytest.mark.slow

WATCHDOG_USEC = 2_000_000  # 2 s: the agent pings every 0.5 s, systemd needs one at least every 1 s


@dataclass
class Note:
    t_s: float  #: monotonic receive time
    pid: int  #: the sender (SCM_CREDENTIALS)
    fields: dict[str, str]
    sortie_files: list[str]  #: the recording folder's files when it arrived
    log: str  #: the agent's log when it arrived


@dataclass
class FakeSystemd:
    """The notify socket's receiving end (what systemd does for a Type=notify service)."""

    record_dir: Path
    log_path: Path
    notes: list[Note] = field(default_factory=list)

    def __post_init__(self):
        self.dir = tempfile.mkdtemp(prefix="sdn")  # short: AF_UNIX paths are <= 107 bytes
        self.path = os.path.join(self.dir, "notify")
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_PASSCRED, 1)
        self.sock.bind(self.path)
        self.sock.settimeout(0.2)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        creds = socket.CMSG_SPACE(struct.calcsize("3i"))
        while not self._stop.is_set():
            try:
                data, anc, _, _ = self.sock.recvmsg(4096, creds)
            except socket.timeout:
                continue
            pid = next((struct.unpack("3i", d[:12])[0] for lvl, typ, d in anc
                        if lvl == socket.SOL_SOCKET and typ == socket.SCM_CREDENTIALS), -1)
            fields = dict(line.split("=", 1) for line in data.decode().splitlines() if "=" in line)
            files = sorted(p.name for p in self.record_dir.glob("*.mcap"))
            log = self.log_path.read_text() if self.log_path.exists() else ""
            self.notes.append(Note(time.monotonic(), pid, fields, files, log))

    def of(self, pid: int, key: str) -> list[Note]:
        return [n for n in list(self.notes) if n.pid == pid and key in n.fields]

    def wait(self, pid: int, key: str, timeout_s: float) -> Note | None:
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            got = self.of(pid, key)
            if got:
                return got[0]
            time.sleep(0.05)
        return None

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        self.sock.close()
        os.unlink(self.path)
        os.rmdir(self.dir)


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _check_pings(sd: FakeSystemd, pid: int, t_from_s: float, t_to_s: float) -> None:
    pings = [n.t_s for n in sd.of(pid, "WATCHDOG") if n.fields["WATCHDOG"] == "1" and t_from_s <= n.t_s <= t_to_s]
    gaps = [b - a for a, b in zip([t_from_s, *pings], [*pings, t_to_s])]
    assert len(pings) >= 3 and max(gaps) < WATCHDOG_USEC * 1e-6 / 2, gaps


def test_agent_under_the_notify_protocol_restarts_into_a_new_sortie_and_lands(flight, monkeypatch):
    fl = flight(1)
    sd = FakeSystemd(fl.tmp, fl.tmp / "drone_1.log")
    try:
        monkeypatch.setenv("NOTIFY_SOCKET", sd.path)  # inherited by the agent processes only: the test never notifies
        monkeypatch.setenv("WATCHDOG_USEC", str(WATCHDOG_USEC))
        proc = fl.start_agent(0)
        ready = sd.wait(proc.pid, "READY", 40)
        assert ready is not None and ready.fields["READY"] == "1", fl.log("drone_1")
        # what it waited for, before READY
        before = [n.fields["STATUS"] for n in sd.of(proc.pid, "STATUS") if n.t_s < ready.t_s]
        assert any("opening the recording" in s for s in before) and any("connecting to the autopilot" in s
                                                                        for s in before), before
        # READY only with the recording open and the autopilot link up
        assert ready.sortie_files == ["drone_1.s001.mcap"]
        assert "connected to autopilot sysid" in ready.log and "recording " in ready.log
        assert "ready" in ready.fields.get("STATUS", "")
        assert all(n.pid == proc.pid for n in sd.notes), {n.pid for n in sd.notes}  # NotifyAccess=main holds

        # take off (the watchdog pings go on meanwhile), then crash in the air (SIGKILL: a crash, or the
        # watchdog's abort) and start again as systemd's Restart=on-failure would
        assert fl.fleet.wait_until(lambda f: "drone_1" in f.states and f.states["drone_1"].health_ok, 30, "healthy")
        acks = fl.fleet.command("takeoff", wait_s=30, expect=["drone_1"], results=("completed", "failed", "refused"))
        assert acks["drone_1"].result == "completed", fl.log("drone_1")
        assert fl.wait_state("drone_1", "hover", 30), fl.log("drone_1")
        _check_pings(sd, proc.pid, ready.t_s, time.monotonic())
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(5)
        folder = FlightFolder(fl.tmp)
        [first] = folder.sorties("drone_1")
        kept = _digest(first.path)

        t_restart_s = time.monotonic()
        proc = fl.start_agent(0)
        ready = sd.wait(proc.pid, "READY", 40)
        assert ready is not None, fl.log("drone_1")
        assert ready.sortie_files == ["drone_1.s001.mcap", "drone_1.s002.mcap"]  # a new file, the old one left
        assert _digest(first.path) == kept
        # the restarted agent found the vehicle in the air and lands it (the default policy)
        assert "started with the vehicle airborne" in ready.log.split("drone_1.s002.mcap")[-1], fl.log("drone_1")
        assert fl.wait_state("drone_1", "landed", 40), fl.log("drone_1")
        _check_pings(sd, proc.pid, ready.t_s, time.monotonic())

        # systemctl stop: STOPPING=1, then a clean exit; both recordings are there, the first untouched
        proc.send_signal(signal.SIGTERM)
        assert sd.wait(proc.pid, "STOPPING", 10) is not None, fl.log("drone_1")
        assert proc.wait(30) == 0, fl.log("drone_1")
        assert [s.number for s in folder.sorties("drone_1")] == [1, 2] and _digest(first.path) == kept
        assert time.monotonic() - t_restart_s < 60
    finally:
        sd.close()
