"""Transport pieces inside one process: config validation, errors, async delivery, latched values."""

from __future__ import annotations

import asyncio
import time

import pytest

from comms.transport import Transport, TransportConfig, TransportError
from tests.helpers.ports import free_tcp_port
from shared_msgs import OrbitPlan, VehicleState, keys
from skycap.config import load_config
from tests.helpers.paths import REPO


def state(i: int) -> VehicleState:
    return VehicleState(
        header=VehicleState.make_header("drone_1"),
        position_ned_m=(float(i), 0.0, 0.0),
        velocity_ned_m_s=(0.0, 0.0, 0.0),
        q_world_body=(1.0, 0.0, 0.0, 0.0),
    )


def test_config_validation_names_the_field() -> None:
    with pytest.raises(TransportError, match="transport.connect endpoint 'localhost'"):
        TransportConfig(connect=["localhost"]).validate()
    with pytest.raises(TransportError, match="client"):
        TransportConfig(mode="client", connect=[]).validate()
    with pytest.raises(TransportError, match="could never"):
        TransportConfig(listen=[], connect=[]).validate()
    TransportConfig().validate()


def test_config_loads_from_toml_overrides() -> None:
    from dataclasses import dataclass, field

    @dataclass
    class Job:
        transport: TransportConfig = field(default_factory=TransportConfig)

    cfg = load_config(Job, overrides=['transport.connect=["tcp/127.0.0.1:9000"]', "transport.mode='client'"])
    assert cfg.transport.connect == ["tcp/127.0.0.1:9000"] and cfg.transport.mode == "client"


def test_port_in_use_is_a_clear_error() -> None:
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    with Transport.open(TransportConfig.rendezvous(ep), "first"):
        with pytest.raises(TransportError, match="in use"):
            Transport.open(TransportConfig.rendezvous(ep), "second")


def test_closed_transport_refuses_publish(bus_pair) -> None:
    a, _ = bus_pair
    a.close()
    with pytest.raises(TransportError, match="closed"):
        a.publish("skycap/v1/f/drone_1/state", state(0))


def test_async_iterator_and_callback_errors(bus_pair) -> None:
    a, b = bus_pair
    key = keys.drone_key("f", "drone_1", keys.STATE)

    def boom(rx) -> None:
        raise RuntimeError("user bug")

    bad = b.subscribe(key, boom, VehicleState)

    async def main() -> list[float]:
        sub = b.subscribe_async(key, VehicleState, maxsize=1000)
        await asyncio.sleep(0.3)
        for i in range(5):
            a.publish(key, state(i))
        got = []
        async for rx in sub:
            got.append(rx.msg.position_ned_m[0])
            assert rx.t_received_ns >= rx.msg.header.t_sent_ns - 10**9
            if len(got) == 5:
                break
        sub.close()
        return got

    assert asyncio.run(main()) == [0.0, 1.0, 2.0, 3.0, 4.0]
    t_end = time.monotonic() + 5
    while bad.stats.received < 5 and time.monotonic() < t_end:
        time.sleep(0.02)
    assert bad.stats.callback_errors == 5 and bad.stats.received == 5


def test_latched_value_is_served_to_queries(bus_pair) -> None:
    a, b = bus_pair
    key = keys.gcs_key("f", keys.PLAN)
    plan = OrbitPlan(
        header=OrbitPlan.make_header("gcs"), plan_id="p1", center_ned_m=(0.0, 0.0, 0.0), radius_m=8.0,
        altitude_m=6.0, angular_speed_rad_s=0.2,
    )
    a.publish(key, plan, latch=True)
    time.sleep(0.2)
    got = b.query_latest(key, OrbitPlan, timeout_s=2.0)
    assert [r.msg.plan_id for r in got] == ["p1"]
    plan.plan_id = "p2"
    a.publish(key, plan, latch=True)
    assert [r.msg.plan_id for r in b.query_latest(keys.gcs_key("f", "*"), OrbitPlan, timeout_s=2.0)] == ["p2"]


def test_async_iteration_ends_on_close(bus_pair) -> None:
    a, b = bus_pair
    key = keys.drone_key("f", "drone_1", keys.STATE)

    async def main() -> tuple[int, int]:
        sub = b.subscribe_async(key, VehicleState, maxsize=2)
        await asyncio.sleep(0.3)
        for i in range(20):
            a.publish(key, state(i))
        await asyncio.sleep(0.5)
        n = 0
        while sub.get_nowait() is not None:
            n += 1
        loop = asyncio.get_running_loop()
        loop.call_later(0.2, b.close)  # closing the transport ends the iteration of a waiting consumer
        async for _ in sub:
            n += 1
        with pytest.raises(TransportError, match="closed"):
            await sub.get(1.0)
        return n, sub.stats.dropped

    n, dropped = asyncio.run(asyncio.wait_for(main(), 10))
    assert n == 2 and dropped == 18  # bounded queue keeps the newest


def test_rendezvous_topology_start_order_and_mesh() -> None:
    """Peers started before the rendezvous join it when it appears, and keep talking after it exits."""
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    key = keys.drone_key("f", "drone_1", keys.STATE)
    got: list[float] = []
    p1 = Transport.open(TransportConfig.local_peer(ep), "p1")  # no rendezvous yet
    p2 = Transport.open(TransportConfig.local_peer(ep), "p2")
    try:
        p2.subscribe(key, lambda rx: got.append(rx.msg.position_ned_m[0]), VehicleState)
        rv = Transport.open(TransportConfig.rendezvous(ep), "rendezvous")
        t_end = time.monotonic() + 15
        i = 0
        while not got and time.monotonic() < t_end:
            p1.publish(key, state(i))
            i += 1
            time.sleep(0.1)
        assert got, "peers did not meet through the rendezvous"
        rv.close()
        time.sleep(0.5)
        n = len(got)
        p1.publish(key, state(1000))
        t_end = time.monotonic() + 5
        while len(got) == n and time.monotonic() < t_end:
            time.sleep(0.02)
        assert got[-1] == 1000.0, "the peers are not meshed: traffic stopped with the rendezvous"
    finally:
        p1.close()
        p2.close()


@pytest.mark.timeout(60)
def test_process_exits_without_close(tmp_path) -> None:
    """Forgotten close(): the process still exits (zenoh callback threads would block it) and the recorder
    file is finalised."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    from flightdata.flightlog import FlightLog

    here = Path(__file__).resolve().parent
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    mcap = tmp_path / "leaky.mcap"
    r = subprocess.run(
        [sys.executable, str(here / "exit_without_close.py"), f"tcp/127.0.0.1:{free_tcp_port()}", str(mcap)],
        env=env, capture_output=True, text=True, timeout=30,
    )
    assert r.returncode == 0, r.stderr
    log = FlightLog(mcap)
    assert log.finalised and log.topic_counts() == {"health": 1}
