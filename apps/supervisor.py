"""The launcher's process supervisor: starts the demo's processes, watches them, stops them in order."""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import time
from pathlib import Path

from skycap.childproc import die_with_parent
from skycap.errors import SkycapError

log = logging.getLogger(__name__)

__all__ = ["ProcessSupervisor"]


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
