"""Two OS processes exchange skycap messages over a real Zenoh session on loopback.

Explicit ``tcp/127.0.0.1:<free port>`` endpoints, multicast scouting off. The child
(``peer_proc.py``) answers commands; the test sends it malformed, wrong-version, wrong-type and NaN
payloads that it must count and survive, and watches its liveliness token come and go.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgspec
import pytest

from comms.transport import Transport, TransportConfig
from tests.helpers.ports import free_tcp_port
from shared_msgs import Command, CommandAck, Health, VehicleState, encode, keys
from tests.helpers.paths import REPO

HERE = Path(__file__).resolve().parent
FLEET = "t2p"
NODE = "drone_7"


def wait_for(pred, timeout_s: float, what: str) -> None:
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        if pred():
            return
        time.sleep(0.02)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


def cmd(command_id: str, action: str = "arm", **params: float) -> Command:
    return Command(
        header=Command.make_header("gcs"), command_id=command_id, target=NODE, action=action, params=params
    )


@pytest.mark.timeout(90)
def test_two_processes_exchange_and_survive_bad_input() -> None:
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    lock = threading.Lock()
    acks: list[CommandAck] = []
    states: list[VehicleState] = []
    healths: list[Health] = []
    joins: list[str] = []
    leaves: list[str] = []

    def keep(store):
        def cb(rx):
            with lock:
                store.append(rx.msg)

        return cb

    cfg = TransportConfig(listen=[endpoint], connect=[], multicast_scouting=False)
    with Transport.open(cfg, node_id="gcs") as bus:
        bus.subscribe(keys.drone_key(FLEET, NODE, keys.ACK), keep(acks), expected_type=CommandAck)
        bus.subscribe(keys.all_drones_key(FLEET, keys.STATE), keep(states), expected_type=VehicleState)
        bus.subscribe(keys.drone_key(FLEET, NODE, keys.HEALTH), keep(healths), expected_type=Health)
        bus.watch_presence(keys.all_drones_key(FLEET, "alive"), on_join=joins.append, on_leave=leaves.append)

        env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
        child = subprocess.Popen(
            [sys.executable, str(HERE / "peer_proc.py"), endpoint, FLEET, NODE],
            cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        )
        try:
            alive_key = keys.alive_key(FLEET, NODE)
            wait_for(lambda: alive_key in joins, 30, "the child's liveliness token (join)")
            assert alive_key in bus.alive(keys.all_drones_key(FLEET, "alive"))

            # First command: resend until the child's subscriber is matched and it answers.
            cmd_key = keys.gcs_key(FLEET, keys.CMD)
            sent_valid = 0
            t_end = time.monotonic() + 20
            while not acks and time.monotonic() < t_end:
                bus.publish(cmd_key, cmd("c1"))
                sent_valid += 1
                time.sleep(0.2)
            wait_for(lambda: bool(acks), 1, "the first ack")

            # Bad input the child must count and survive.
            bus.publish_raw(cmd_key, b"\xc1 not messagepack at all")
            wrong_version = cmd("bad_version")
            wrong_version.header.schema_version = 99
            bus.publish_raw(cmd_key, encode(wrong_version))
            bus.publish_raw(cmd_key, encode(Health(header=Health.make_header("gcs"), role="tool", state="x")))
            bus.publish_raw(cmd_key, encode(cmd("nan", "takeoff", altitude_m=float("nan"))))
            bus.publish_raw(cmd_key, msgspec.msgpack.encode({"type": "command", "header": 3}))

            bus.publish(cmd_key, cmd("c2", "takeoff", altitude_m=10.0))
            sent_valid += 1
            wait_for(lambda: any(a.command_id == "c2" for a in acks), 10, "the ack of c2 (after the bad input)")
            assert {a.command_id for a in acks} == {"c1", "c2"}  # nothing bad was acknowledged
            assert all(a.result == "accepted" and a.header.sender_id == NODE for a in acks)

            wait_for(lambda: len(states) >= 20, 10, "the child's 20 vehicle states")
            assert [s.header.seq for s in states] == list(range(1, 21))
            assert [s.position_ned_m[0] for s in states] == [float(i) for i in range(20)]
            assert all(s.header.t_sent_ns >= s.header.t_measurement_ns for s in states)

            bus.publish(cmd_key, cmd("end", "disarm"))
            wait_for(lambda: bool(healths), 15, "the child's final health report")
            rates = healths[0].rates_hz
            assert rates["malformed"] == 5.0, rates
            # every valid command it received was acknowledged, plus the disarm (c1 copies sent before its
            # subscription was known to us may not have reached it)
            assert rates["received"] == len(acks) + 1 <= sent_valid + 1, rates

            out, _ = child.communicate(timeout=20)
            assert child.returncode == 0, out
            assert "dropped input" in out  # the child logged the bad input
            wait_for(lambda: alive_key in leaves, 15, "the child's token to vanish (leave)")
        finally:
            if child.poll() is None:
                child.kill()
                child.wait()


@pytest.mark.timeout(60)
def test_kill_9_is_seen_as_leave() -> None:
    """A peer that dies without closing (kill -9) disappears from presence."""
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    joins: list[str] = []
    leaves: list[str] = []
    cfg = TransportConfig(listen=[endpoint], connect=[], multicast_scouting=False)
    with Transport.open(cfg, node_id="gcs") as bus:
        bus.watch_presence(keys.all_drones_key(FLEET, "alive"), on_join=joins.append, on_leave=leaves.append)
        env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
        child = subprocess.Popen(
            [sys.executable, str(HERE / "peer_proc.py"), endpoint, FLEET, "drone_9"],
            cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )
        try:
            key = keys.alive_key(FLEET, "drone_9")
            wait_for(lambda: key in joins, 30, "join")
            child.kill()
            child.wait()
            wait_for(lambda: key in leaves, 30, "leave after kill -9")
        finally:
            if child.poll() is None:
                child.kill()
                child.wait()
