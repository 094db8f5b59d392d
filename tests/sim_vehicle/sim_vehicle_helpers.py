"""Helpers for the simulated-vehicle tests: free UDP ports and test configurations."""

from __future__ import annotations

import socket

from simulator.config import SimConfig


def free_udp_port() -> int:
    """A UDP port that nothing on this machine has bound right now (tests run beside demos)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("0.0.0.0", 0))
        return s.getsockname()[1]


def sim_test_config(**overrides) -> SimConfig:
    """A SimConfig on fresh ports (offboard target = a free port, local ports chosen by the OS, no GCS link).

    ``overrides``: attribute paths with ``__`` between levels, e.g. ``failsafe__offboard_loss_action="land"``.
    """
    cfg = SimConfig()
    cfg.ports.offboard_base = free_udp_port()
    cfg.ports.local_base = 0
    cfg.ports.gcs_port = 0
    for dotted, value in overrides.items():
        obj = cfg
        keys = dotted.split("__")
        for k in keys[:-1]:
            obj = getattr(obj, k)
        setattr(obj, keys[-1], value)
    return cfg
