"""Fleet security on real Zenoh sessions on loopback: mutual TLS, the fleet ACL, authenticated sender ids.

One fleet folder per module (``skycap keys`` logic), a rendezvous (the simulator's identity), a ground station,
two drones and a second session holding drone_1's certificate (its camera service). Every "not received"
check is paired with a later message that is received, so a slow network cannot pass it by accident.
"""

from __future__ import annotations

import datetime as dt
import os
import threading
import time

import pytest

from apps.cli import main as skycap_main
from comms.errors import TransportError
from comms.security import FleetKeys, SecurityError
from comms.transport import SecurityConfig, Transport, TransportConfig
from shared_msgs import CameraFrame, Command, VehicleState, encode, keys
from shared_msgs.codec import stamp_sent
from tests.helpers.ports import free_tcp_port

FLEET = "sec"


def wait_for(pred, timeout_s: float, what: str) -> None:
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        if pred():
            return
        time.sleep(0.02)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


class Inbox:
    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.items: list = []

    def __call__(self, rx) -> None:
        with self.lock:
            self.items.append(rx)

    def ids(self) -> list[str]:
        with self.lock:
            return [getattr(rx.msg, "command_id", None) or rx.msg.header.sender_id for rx in self.items]


def command(cid: str, sender: str = "gcs", target: str = "*") -> Command:
    return Command(header=Command.make_header(sender), command_id=cid, target=target, action="land")


def state(sender: str) -> VehicleState:
    return VehicleState(header=VehicleState.make_header(sender), position_ned_m=(0.0, 0.0, -5.0),
                        velocity_ned_m_s=(0.0, 0.0, 0.0), q_world_body=(1.0, 0.0, 0.0, 0.0))


@pytest.fixture(scope="module")
def fleet_keys(tmp_path_factory) -> FleetKeys:
    return FleetKeys.create(tmp_path_factory.mktemp("keys") / "fleet", FLEET, drones=["drone_1", "drone_2"], sim=True)


@pytest.fixture(scope="module")
def net(fleet_keys):
    ep = f"tls/127.0.0.1:{free_tcp_port()}"
    sec = str(fleet_keys.folder)
    opened = {"sim": Transport.open(TransportConfig.rendezvous(ep, keys_dir=sec), "sim")}
    for node in ("gcs", "drone_1", "drone_2"):
        opened[node] = Transport.open(TransportConfig.local_peer(ep, keys_dir=sec), node)
    cam = TransportConfig.local_peer(ep, keys_dir=sec)
    cam.security.identity = "drone_1"
    opened["drone_1_camera"] = Transport.open(cam, "drone_1_camera")
    wait_for(lambda: all(len(t.peers()) >= 4 for t in opened.values()), 15, "the full mesh of 5 secure peers")
    yield ep, opened
    for t in opened.values():
        t.close()


def test_keys_folder_files_and_permissions(fleet_keys):
    assert set(fleet_keys.identities) == {"gcs", "drone_1", "drone_2", "sim"}
    for ident in fleet_keys.identities:
        assert oct(fleet_keys.key_path(ident).stat().st_mode & 0o777) == "0o600"
        assert fleet_keys.check(ident)["days_left"] >= 364
    assert oct(fleet_keys.ca_key_path.stat().st_mode & 0o777) == "0o600"
    with pytest.raises(SecurityError, match="already holds"):
        FleetKeys.create(fleet_keys.folder, FLEET, drones=["drone_1"])


def test_ground_station_commands_reach_every_drone(net):
    _, t = net
    inbox = {d: Inbox() for d in ("drone_1", "drone_2")}
    subs = [t[d].subscribe(keys.gcs_key(FLEET, keys.CMD), inbox[d], Command) for d in inbox]
    try:
        time.sleep(0.5)
        t["gcs"].publish(keys.gcs_key(FLEET, keys.CMD), command("c-ok"))
        wait_for(lambda: all("c-ok" in i.ids() for i in inbox.values()), 5, "the ground station's command")
    finally:
        for s in subs:
            s.close()


def test_a_drone_certificate_cannot_command_or_speak_for_another_drone(net):
    _, t = net
    cmds, states = Inbox(), Inbox()
    subs = [t["drone_1"].subscribe(keys.gcs_key(FLEET, keys.CMD), cmds, Command),
            t["gcs"].subscribe(keys.all_drones_key(FLEET, keys.STATE), states, VehicleState)]
    try:
        time.sleep(0.5)
        # drone_2 sends a command as the ground station, and a state on drone_1's key as drone_1
        t["drone_2"].publish(keys.gcs_key(FLEET, keys.CMD), command("c-from-drone_2"))
        t["drone_2"].publish(keys.drone_key(FLEET, "drone_1", keys.STATE), state("drone_1"))
        time.sleep(0.3)
        t["gcs"].publish(keys.gcs_key(FLEET, keys.CMD), command("c-after"))
        t["drone_2"].publish(keys.drone_key(FLEET, "drone_2", keys.STATE), state("drone_2"))
        wait_for(lambda: "c-after" in cmds.ids() and "drone_2" in states.ids(), 5, "the control messages")
        time.sleep(0.3)
        assert cmds.ids() == ["c-after"], "a drone's certificate must not be able to command"
        assert states.ids() == ["drone_2"], "a drone must not publish under another drone's keys"
    finally:
        for s in subs:
            s.close()


def test_a_forged_sender_id_is_refused(net):
    _, t = net
    cmds = Inbox()
    sub = t["drone_1"].subscribe(keys.gcs_key(FLEET, keys.CMD), cmds, Command)
    try:
        time.sleep(0.5)
        # a ground station (allowed on gcs/cmd) claiming to be drone_2, then an honest command
        t["gcs"].publish_raw(keys.gcs_key(FLEET, keys.CMD), encode(stamp_sent(command("c-forged", sender="drone_2"))))
        t["gcs"].publish(keys.gcs_key(FLEET, keys.CMD), command("c-honest"))
        wait_for(lambda: "c-honest" in cmds.ids(), 5, "the honest command")
        assert cmds.ids() == ["c-honest"]
        assert sub.stats.forged == 1 and "drone_2" in sub.stats.last_error
    finally:
        sub.close()


def test_camera_images_stay_on_their_drone(net):
    _, t = net
    frames = {n: Inbox() for n in ("gcs", "drone_2", "drone_1_camera")}
    key = keys.drone_key(FLEET, "drone_1", keys.CAMERA_IMAGE)
    subs = [t[n].subscribe(key, frames[n], CameraFrame) for n in frames]
    try:
        time.sleep(0.5)
        frame = CameraFrame(header=CameraFrame.make_header("drone_1"), camera_id="cam0", frame_index=1,
                            encoding="jpeg", width_px=8, height_px=8, data=b"\xff\xd8")
        t["drone_1"].publish(key, frame)
        wait_for(lambda: frames["drone_1_camera"].ids(), 5, "the image at the drone's own camera service")
        time.sleep(0.5)
        assert not frames["gcs"].ids() and not frames["drone_2"].ids()
    finally:
        for s in subs:
            s.close()


def _outsider_cannot_join(ep: str, t: dict, outsider_cfg: TransportConfig) -> None:
    got = Inbox()
    cmds = Inbox()
    sub = t["drone_1"].subscribe(keys.gcs_key(FLEET, keys.CMD), cmds, Command)
    with Transport.open(outsider_cfg, "gcs") as o:
        spy = o.subscribe(f"{keys.PREFIX}/{FLEET}/**", got)
        try:
            deadline = time.monotonic() + 2.0
            while time.monotonic() < deadline:
                o.publish(keys.gcs_key(FLEET, keys.CMD), command("c-outsider"))
                t["drone_1"].publish(keys.drone_key(FLEET, "drone_1", keys.STATE), state("drone_1"))
                time.sleep(0.2)
            t["gcs"].publish(keys.gcs_key(FLEET, keys.CMD), command("c-after-outsider"))
            wait_for(lambda: "c-after-outsider" in cmds.ids(), 5, "the ground station's command")
            assert o.peers() == [], "the outsider must not get a link"
            assert [i for i in got.ids() if i != "c-outsider"] == [], "the outsider received fleet traffic"
            assert cmds.ids() == ["c-after-outsider"], "the outsider's command reached a drone"
        finally:
            spy.close()
            sub.close()


def test_an_outsider_without_certificate_can_neither_receive_nor_command(net):
    ep, t = net
    plain = f"tcp/{ep.partition('/')[2]}"
    _outsider_cannot_join(ep, t, TransportConfig(listen=["tcp/127.0.0.1:0"], connect=[plain]))


def test_an_outsider_with_another_fleets_certificate_is_refused(net, tmp_path):
    ep, t = net
    other = FleetKeys.create(tmp_path / "other", FLEET, drones=["drone_1"])  # same names, another CA
    _outsider_cannot_join(ep, t, TransportConfig.local_peer(ep, keys_dir=str(other.folder)))


def test_unusable_keys_are_refused_with_the_file_and_the_fix(fleet_keys, tmp_path):
    future = dt.datetime.now(dt.timezone.utc) + dt.timedelta(days=400)
    with pytest.raises(SecurityError, match="expired on .* issue a new one"):
        fleet_keys.check("drone_1", now=future)
    with pytest.raises(SecurityError, match="not in .*fleet.toml"):
        fleet_keys.check("drone_9")
    k = FleetKeys.create(tmp_path / "f", FLEET, drones=["drone_1"])
    os.chmod(k.key_path("drone_1"), 0o644)
    with pytest.raises(SecurityError, match="chmod 600"):
        k.check("drone_1")
    k.key_path("gcs").unlink()
    with pytest.raises(SecurityError, match=r"gcs\.key is missing"):
        k.check("gcs")
    (k.folder / "drone_1.pem").write_bytes(fleet_keys.cert_path("drone_1").read_bytes())
    os.chmod(k.key_path("drone_1"), 0o600)
    with pytest.raises(SecurityError, match="not signed by this fleet's CA"):
        k.check("drone_1")
    with pytest.raises(SecurityError, match="fleet.toml is missing"):
        FleetKeys.load(tmp_path)
    with pytest.raises(TransportError, match="plaintext .* write it as tls/127.0.0.1:7447"):
        TransportConfig(listen=["tls/127.0.0.1:0"], connect=["tcp/127.0.0.1:7447"], security=SecurityConfig(keys_dir=str(k.folder))).validate()
    with pytest.raises(SecurityError, match="drone_9"):
        Transport.open(TransportConfig.local_peer("tls/127.0.0.1:1", keys_dir=str(k.folder)), "drone_9")


def test_keys_command_creates_adds_and_checks(tmp_path, capsys):
    folder = tmp_path / "fleet"
    assert skycap_main(["keys", "create", "--keys", str(folder), "--fleet", "f9", "--drones", "drone_1"]) == 0
    assert skycap_main(["keys", "add", "--keys", str(folder), "drone_2", "--role", "drone"]) == 0
    assert skycap_main(["keys", "check", "--keys", str(folder)]) == 0
    out = capsys.readouterr().out
    assert "drone_2: ok (drone, fleet f9" in out and "gcs: ok (gcs" in out
    assert FleetKeys.load(folder).identities == {"gcs": "gcs", "drone_1": "drone", "drone_2": "drone"}
    assert skycap_main(["keys", "check", "--keys", str(folder), "drone_3"]) != 0
