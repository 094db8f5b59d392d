"""Logging set-up shared by every process: the CLI, the simulator nodes and the agent.

Logs go to stderr through the standard :mod:`logging` module; under systemd, journald collects them.
"""

from __future__ import annotations

import logging
import sys


def setup_logging(level: str = "INFO") -> None:
    """Log to stderr (journald picks it up under systemd) with a compact format."""
    logging.basicConfig(
        level=getattr(logging, level.upper(), logging.INFO),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
