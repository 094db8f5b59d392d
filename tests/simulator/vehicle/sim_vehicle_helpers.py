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


def fast_forward(vehicle, seconds: float, dt_s: float = 0.01, wind=None, each_step=None) -> None:
    """Step a :class:`SimVehicle` (pure, no I/O) ``seconds`` faster than real time.

    ``each_step(vehicle)`` runs before every step (e.g. to keep an offboard setpoint stream alive).
    """
    import numpy as np

    wind = np.zeros(3) if wind is None else wind
    for _ in range(int(round(seconds / dt_s))):
        if each_step is not None:
            each_step(vehicle)
        vehicle.step(vehicle.t_s + dt_s, dt_s, wind)
