"""The machine line every benchmark prints: CPU model, logical CPUs, load, Python, plus what the bench adds."""

from __future__ import annotations

import os
import platform
from pathlib import Path


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def describe_machine(*extra: str) -> str:
    """``"<cpu>, N logical CPUs, load avg L, Linux x, Python y[, extra...]"``."""
    load = f"load avg {os.getloadavg()[0]:.2f}" if hasattr(os, "getloadavg") else "load avg ?"
    parts = [cpu_model(), f"{os.cpu_count()} logical CPUs", load, f"{platform.system()} {platform.release()}",
             f"Python {platform.python_version()}", *extra]
    return ", ".join(parts)
