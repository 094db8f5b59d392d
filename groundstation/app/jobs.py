"""Background jobs of the ground station: ``skycap reconstruct FLIGHT_DIR`` in a subprocess.

    job = ReconstructJob.submit("flights/f1")
    job.progress()   # (state, stage, elapsed_s): state "running" / "done" / "failed" / "cancelled"
    job.fraction()   # 0..1 by the reconstruction's stages
    job.log()        # the process's output lines so far
    job.cancel()
    job.result()     # {"summary": {...}, "outputs": {...}} once done (None before; raises on failure)

No Qt here: the widgets poll it.
"""

from __future__ import annotations

import json
import logging
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from flightdata.folder import FlightFolder
from skycap.errors import SkycapError

log = logging.getLogger(__name__)

__all__ = ["JobError", "ReconstructJob", "list_flights"]


class JobError(SkycapError):
    """A background job that failed (its log says why)."""


#: the reconstruction's log lines that mark its stages -> (fraction done, stage shown); ``skycap reconstruct`` reports
#: no fraction on a pipe (its bars need a terminal), so progress advances by these milestones
_MILESTONES = (("read the whole flight", 0.15, "read the recordings"), ("read sortie", 0.15, "read the recordings"),
               (" reconstruction of ", 0.2, "reading observations"), ("fit (", 0.3, "fitting the body model"),
               ("fit of", 0.3, "fitting the body model"), ("wrote ", 0.95, "writing the outputs"))
_LOG_LINE = re.compile(r"^\S+ \S+ (INFO|WARNING|ERROR) (\S+): (.*)$")


class ReconstructJob:
    """``skycap reconstruct FLIGHT_DIR`` as a child process (its own process group: cancel stops it all)."""

    def __init__(self, flight_dir: Path, cmd: list[str]):
        self.flight = FlightFolder(flight_dir)
        self.cmd = cmd
        self._lines: list[str] = []
        self._lock = threading.Lock()
        self._stage = "starting"
        self._fraction = 0.0
        self._state = "running"
        self._t0 = time.monotonic()
        self._t_wall0 = time.time()
        self._t_end: float | None = None
        self._cancelled = False
        self._result: dict | None = None
        self._error = ""
        log.info("process flight: %s", " ".join(cmd))
        self._proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1,
                                      start_new_session=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
        self._reader = threading.Thread(target=self._read, name="reconstruct-job", daemon=True)
        self._reader.start()

    @classmethod
    def submit(cls, flight_dir: str | Path, extra_args: list[str] | None = None) -> "ReconstructJob":
        flight = FlightFolder(flight_dir)
        if not flight.has_recordings():
            raise JobError(f"{flight.path} holds no drone recording (<drone>.sNNN.mcap): nothing to process")
        return cls(flight.path, [sys.executable, "-m", "apps.cli", "reconstruct", str(flight.path),
                                 *(extra_args or [])])

    def _read(self) -> None:
        assert self._proc.stdout is not None
        for line in self._proc.stdout:
            line = line.rstrip("\n")
            with self._lock:
                self._lines.append(line)
                m = _LOG_LINE.match(line)
                if m:
                    for marker, frac, stage in _MILESTONES:
                        if marker in m.group(3) and frac >= self._fraction:
                            self._fraction, self._stage = frac, stage
        code = self._proc.wait()
        with self._lock:
            self._t_end = time.monotonic()
            if self._cancelled:
                self._state = "cancelled"
            elif code != 0:
                self._state, self._error = "failed", f"skycap reconstruct exited with code {code}"
            else:
                try:
                    self._result = self._parse()
                    self._state = "done"
                except Exception as e:  # noqa: BLE001 - shown to the operator
                    self._state, self._error = "failed", f"no result: {e}"
            self._stage = self._state
            if self._state == "done":
                self._fraction = 1.0

    def _parse(self) -> dict:
        """The summary.json the method wrote (newest of the method folders) and where its outputs are."""
        best = None
        for name in ("multiview", "monocular"):
            p = self.flight.reconstruction_dir(name) / "summary.json"
            if p.exists() and p.stat().st_mtime >= self._t_wall0 - 1 and (best is None or p.stat().st_mtime > best.stat().st_mtime):
                best = p
        if best is None:
            raise JobError(f"no reconstruction summary.json written under {self.flight.path}")
        d = best.parent
        method = next(m for m in ("multiview", "monocular") if self.flight.reconstruction_dir(m) == d)
        return {"summary": json.loads(best.read_text()), "method": method,
                "outputs": {"dir": str(d), "bvh": sorted(str(p) for p in d.glob("*.bvh")),
                            "files": sorted(p.name for p in d.iterdir())}}

    def progress(self) -> tuple[str, str, float]:
        """(state, stage, elapsed_s): state "running", "done", "failed" or "cancelled"."""
        with self._lock:
            end = self._t_end if self._t_end is not None else time.monotonic()
            return self._state, self._stage, end - self._t0

    def fraction(self) -> float:
        """0..1 by the stages passed (1 when done)."""
        with self._lock:
            return 1.0 if self._state == "done" else self._fraction

    def log(self) -> list[str]:
        with self._lock:
            return list(self._lines)

    def cancel(self) -> None:
        if self._proc.poll() is None:
            self._cancelled = True
            log.info("cancelling the reconstruction of %s", self.flight.path)
            os.killpg(self._proc.pid, signal.SIGTERM)

    def wait(self, timeout_s: float | None = None) -> bool:
        self._reader.join(timeout_s)
        return not self._reader.is_alive()

    def result(self) -> dict | None:
        with self._lock:
            if self._state == "failed":
                raise JobError(f"{self._error}; last lines: {' | '.join(self._lines[-5:])}")
            return self._result


def list_flights(root: str | Path) -> list[dict]:
    """The flight folders under ``root`` (newest first): drones, sorties, whether processed."""
    root = Path(root)
    out = []
    if not root.is_dir():
        return out
    for p in sorted(root.iterdir(), key=lambda p: p.stat().st_mtime, reverse=True):
        if not p.is_dir():
            continue
        f = FlightFolder(p)
        try:
            ids = f.drone_ids()
        except Exception as e:  # noqa: BLE001 - a broken folder is listed with its problem
            out.append({"path": str(p), "name": p.name, "drones": [], "error": str(e)})
            continue
        if not ids:
            continue
        recon = [m for m in ("multiview", "monocular") if (f.reconstruction_dir(m) / "summary.json").exists()]
        out.append({"path": str(p), "name": p.name, "drones": ids,
                    "sorties": max(len(f.sorties(d)) for d in ids), "processed": recon,
                    "mb": round(sum(q.stat().st_size for q in p.glob("*.mcap")) / 1e6, 1)})
    return out
