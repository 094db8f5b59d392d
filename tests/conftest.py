"""Shared fixtures. ``../shared/data`` (beside the checkout) holds real data; tests that need it are
skipped where it is absent (a fresh clone), and always run in CI where it is present."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from tests.helpers.flight import Flight
from tests.helpers.paths import REPO

SHARED_DATA = Path(os.environ.get("SKYCAP_SHARED_DATA", REPO.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data not found at {SHARED_DATA}")
    return SHARED_DATA


@pytest.fixture(scope="session")
def cmu_dir(shared_data: Path) -> Path:
    return shared_data / "mocap" / "cmu"


@pytest.fixture()
def bus_pair():
    """Two real Zenoh sessions on loopback: ``a`` opens the rendezvous, ``b`` a peer joining it."""
    from comms.transport import Transport, TransportConfig
    from tests.helpers.ports import free_tcp_port

    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    a = Transport.open(TransportConfig.rendezvous(ep), "a")
    b = Transport.open(TransportConfig.local_peer(ep), "b")
    yield a, b
    b.close()
    a.close()


@pytest.fixture
def flight(tmp_path):
    """``flight(n, sim_overrides)`` -> a :class:`tests.helpers.flight.Flight`, closed after the test."""
    made = []

    def make(n: int = 1, sim_overrides=None) -> Flight:
        f = Flight(tmp_path, n, sim_overrides)
        made.append(f)
        return f

    yield make
    for f in made:
        f.close()
