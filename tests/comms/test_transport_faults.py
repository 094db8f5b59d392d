"""The transport's simulated fault layer (``transport.fault``): receive-side drops and delays of other drones'
messages, over real Zenoh sessions in this process."""

from __future__ import annotations

import threading
import time

import pytest

from comms.faults import FaultConfig
from comms.transport import Transport, TransportConfig, TransportError
from tests.helpers.ports import free_tcp_port
from shared_msgs import VehicleState, keys
from skycap.config import load_config


def state(sender: str, i: int) -> VehicleState:
    return VehicleState(header=VehicleState.make_header(sender), position_ned_m=(float(i), 0.0, 0.0),
                        velocity_ned_m_s=(0.0, 0.0, 0.0), q_world_body=(1.0, 0.0, 0.0, 0.0))


def _collect(bus: Transport, key_expr: str):
    got, lock = [], threading.Lock()

    def cb(rx):
        with lock:
            got.append(rx)

    return bus.subscribe(key_expr, cb, VehicleState), got


def _wait(pred, timeout_s=5.0):
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end and not pred():
        time.sleep(0.02)


def test_fault_config_validates_and_loads_from_overrides():
    with pytest.raises(TransportError, match="drop_prob"):
        TransportConfig(fault=FaultConfig(drop_prob=1.5)).validate()
    with pytest.raises(TransportError, match="delay_s"):
        TransportConfig(fault=FaultConfig(delay_s=-1.0)).validate()
    from dataclasses import dataclass, field

    @dataclass
    class Job:
        transport: TransportConfig = field(default_factory=TransportConfig)

    cfg = load_config(Job, overrides=["transport.fault.drop_prob=0.3", "transport.fault.delay_s=0.2"])
    assert cfg.transport.fault.drop_prob == 0.3 and cfg.transport.fault.active
    assert not TransportConfig().fault.active


def test_drops_a_share_of_other_drones_messages_only():
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    fault = FaultConfig(drop_prob=0.3, seed=3)
    with Transport.open(TransportConfig.rendezvous(ep), "drone_2") as tx, \
            Transport.open(TransportConfig(listen=["tcp/127.0.0.1:0"], connect=[ep], fault=fault), "drone_1") as rx:
        sub, got = _collect(rx, keys.all_drones_key("f", keys.STATE))
        time.sleep(0.5)
        n = 400
        for i in range(n):
            tx.publish(keys.drone_key("f", "drone_2", keys.STATE), state("drone_2", i))  # a teammate's: faulted
            tx.publish(keys.drone_key("f", "drone_1", keys.STATE), state("drone_1", i))  # own key: never touched
            if i % 50 == 0:
                time.sleep(0.01)
        _wait(lambda: sub.stats.received + sub.stats.fault_dropped >= 2 * n)
        own = [r for r in got if "/drone_1/" in r.key]
        mate = [r for r in got if "/drone_2/" in r.key]
        assert len(own) == n
        assert len(mate) + sub.stats.fault_dropped == n and sub.stats.fault_judged == n
        assert 0.2 * n < sub.stats.fault_dropped < 0.4 * n  # 30 % +- ~7 sigma
        assert rx.stats()[next(k for k in rx.stats() if k.startswith(keys.all_drones_key("f", keys.STATE)))]["fault_dropped"] \
            == sub.stats.fault_dropped


def test_delays_teammates_detections_topic_only():
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    fault = FaultConfig(delay_s=0.2, delay_topics=[keys.STATE])  # states stand in for detections here
    with Transport.open(TransportConfig.rendezvous(ep), "drone_2") as tx, \
            Transport.open(TransportConfig(listen=["tcp/127.0.0.1:0"], connect=[ep], fault=fault), "drone_1") as rx:
        sub, got = _collect(rx, keys.all_drones_key("f", keys.STATE))
        time.sleep(0.5)
        for i in range(10):
            tx.publish(keys.drone_key("f", "drone_2", keys.STATE), state("drone_2", i))
            tx.publish(keys.drone_key("f", "drone_1", keys.STATE), state("drone_1", i))
            time.sleep(0.02)
        _wait(lambda: len(got) >= 20)
        lat = {k: [r.latency_ns * 1e-9 for r in got if f"/{k}/" in r.key] for k in ("drone_1", "drone_2")}
        assert len(lat["drone_2"]) == 10 and sub.stats.fault_delayed == 10
        assert min(lat["drone_2"]) >= 0.2 and max(lat["drone_2"]) < 1.0
        assert max(lat["drone_1"]) < 0.15
        # delivered in order
        xs = [r.msg.position_ned_m[0] for r in got if "/drone_2/" in r.key]
        assert xs == sorted(xs)
