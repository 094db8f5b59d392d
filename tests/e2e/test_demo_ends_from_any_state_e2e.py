"""``skycap demo`` finishes whatever state the drones end in (issue 20): drones landed early by a command from a
separate fleet client are reported, not an error -- the demo still writes summary.json and runs the
reconstruction on what was recorded."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import pytest

from tests.helpers.ports import free_tcp_port, free_udp_base

pytestmark = pytest.mark.slow


def test_drones_landed_by_another_client_the_demo_still_summarises_and_reconstructs(tmp_path):
    from comms.security import FleetKeys
    from comms.transport import Transport, TransportConfig
    from groundstation.fleet import FleetClient
    from shared_msgs import keys

    out = tmp_path / "flight"
    # a fleet folder given to the demo: the other client joins the secure fleet with the ground station's certificate
    fleet_keys = FleetKeys.create(tmp_path / "keys", "early", drones=["drone_1", "drone_2"], sim=True, days=2)
    port = free_tcp_port()
    cmd = [sys.executable, "-m", "apps.cli", "demo", "--drones", "2", "--duration", "24", "--out", str(out),
           "--set", f'zenoh_endpoint="tcp/127.0.0.1:{port}"', "--set", f'keys_dir="{fleet_keys.folder}"',
           "--set", f"mavlink_base={free_udp_base(2)}",
           "--set", 'fleet="early"', "--set", "camera_set=[\"camera.width_px=320\", \"camera.height_px=240\"]"]
    demo = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    bus = None
    try:
        time.sleep(3.0)  # the demo's rendezvous first
        bus = Transport.open(TransportConfig.local_peer(f"tls/127.0.0.1:{port}", str(fleet_keys.folder)),
                             "other_client", identity=keys.GCS)
        other = FleetClient("early", bus, heartbeat_hz=0)
        assert other.wait_until(lambda f: len(f.healths) == 2 and all(h.state == "orbit" for h in f.healths.values()),
                                150, "orbit"), other.table()
        time.sleep(12.0)
        acks = other.command("land", wait_s=10, expect=["drone_1", "drone_2"], results=("accepted", "refused"))
        assert {a.result for a in acks.values()} == {"accepted"}, acks
        stdout, _ = demo.communicate(timeout=400)
    finally:
        if demo.poll() is None:
            demo.kill()
        if bus is not None:
            bus.close()
    assert demo.returncode == 0, stdout[-5000:]
    s = json.loads((out / "summary.json").read_text())
    for d in ("drone_1", "drone_2"):
        # down, or still descending under the other client's land when the demo's orbit ended (a loaded machine)
        ended = s["drones"][d]["ended"]
        assert ended.startswith(("on the ground before the final land command", "landing before the final land command")) \
            and "another client's command" in ended, s["drones"][d]
    assert "refused: not airborne" not in stdout
    r = s["reconstruction"]
    assert r["ran"] and r["exit_code"] == 0, (r, (out / "logs" / "reconstruct.log").read_text()[-3000:])
    assert "another client's command" in stdout
