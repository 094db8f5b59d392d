"""Child processes that cannot outlive their launcher.

:class:`ProcessSupervisor` starts a launcher's processes (each in its own session with its own log), watches
them and stops them in order. A launcher (the demo, ``skycap gs --sim``) starts simulators, cameras and agents in their own sessions (so that
it can signal each group). If the launcher itself dies (a crash, SIGKILL), those children would keep running,
flying and holding ports: :func:`die_with_parent` (a ``preexec_fn``) asks the Linux kernel to send the child
SIGTERM when its parent exits (``prctl(PR_SET_PDEATHSIG)``); an agent then lands and closes its recording as on
any SIGTERM. Elsewhere it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from skycap.errors import SkycapError

log = logging.getLogger(__name__)

__all__ = ["ProcessSupervisor", "die_with_parent"]

_PR_SET_PDEATHSIG = 1


def die_with_parent() -> None:
    """``preexec_fn`` of :class:`subprocess.Popen`: SIGTERM to this child when the launcher exits (Linux)."""
    if not sys.platform.startswith("linux"):
        return
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    if libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0) != 0:
        return  # best effort: the launcher still stops its children on a clean exit
    if os.getppid() == 1:  # the launcher died before prctl took effect
        os.kill(os.getpid(), signal.SIGTERM)


class ProcessSupervisor:
    """Child processes, each in its own process group with its own log file (``<log_dir>/<name>.log``)."""

    def __init__(self, log_dir: Path):
        self.log_dir = log_dir
        self.items: list[tuple[str, subprocess.Popen]] = []

    def start(self, name: str, cmd: list[str]) -> subprocess.Popen:
        f = open(self.log_dir / f"{name}.log", "w")
        log.info("starting %s: %s", name, " ".join(cmd))
        p = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, start_new_session=True,
                                 preexec_fn=die_with_parent)  # never outlive this launcher
        self.items.append((name, p))
        return p

    def dead(self) -> dict[str, int]:
        """Exit codes of the children that have exited."""
        return {n: p.returncode for n, p in self.items if p.poll() is not None}

    def check_alive(self, skip: set[str] | frozenset = frozenset()) -> None:
        for name, p in self.items:
            if name not in skip and p.poll() is not None:
                raise SkycapError(f"{name} exited early (code {p.returncode}); see {self.log_dir / (name + '.log')}")

    def stop(self, names: list[str] | None = None, timeout_s: float = 30.0) -> dict[str, int]:
        """SIGTERM the named processes (all if None), wait, SIGKILL what is left; returns exit codes."""
        chosen = [(n, p) for n, p in self.items if names is None or n in names]
        for n, p in chosen:
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        codes = {}
        t_end = time.monotonic() + timeout_s
        for n, p in chosen:
            try:
                codes[n] = p.wait(max(0.1, t_end - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.error("%s did not stop within %.0f s: killing it", n, timeout_s)
                os.killpg(p.pid, signal.SIGKILL)
                codes[n] = p.wait()
        return codes
