"""Fixtures of the simulated-vehicle tests: simulators running in background threads."""

from __future__ import annotations

import pytest

from simulator.config import SimConfig
from simulator.runner import SimWorld


@pytest.fixture
def sim_world_factory():
    """Start SimWorlds in background threads; all are stopped at teardown."""
    worlds: list[SimWorld] = []

    def start(cfg: SimConfig) -> SimWorld:
        w = SimWorld(cfg).start_in_thread()
        worlds.append(w)
        return w

    yield start
    for w in worlds:
        w.stop()
