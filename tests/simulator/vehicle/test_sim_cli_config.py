"""``skycap sim`` as a real process (SIGTERM stops it cleanly) and SimConfig through skycap.config."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time

import pytest
from pymavlink.dialects.v20 import common as mavlink
from sim_vehicle_helpers import free_udp_port

from simulator.config import SimConfig
from skycap.config import ConfigError, load_config, save_config

pytestmark = pytest.mark.timeout(60)


def test_config_loads_from_toml_and_overrides(tmp_path):
    p = tmp_path / "sim.toml"
    p.write_text(
        "physics_hz = 150.0\n[vehicles]\ncount = 3\n"
        "spawn_ne_m = [[0.0, 0.0], [5.0, 0.0], [0.0, 5.0]]\n[wind]\nmean_speed_m_s = 4.0\n"
    )
    cfg = load_config(SimConfig, p, ["battery.start_percent=30", "ports.offboard_base=15540"]).validate()
    assert cfg.vehicles.count == 3 and cfg.physics_hz == 150.0 and cfg.wind.mean_speed_m_s == 4.0
    assert cfg.battery.start_percent == 30.0 and cfg.ports.offboard_base == 15540
    assert cfg.spawn_ned_m(2) == (0.0, 5.0, 0.0)
    back = load_config(SimConfig, save_config(cfg, tmp_path / "out" / "config.toml"))
    assert back == cfg
    with pytest.raises(ConfigError, match="wind.speed"):
        load_config(SimConfig, None, ["wind.speed=3"])
    bad = load_config(SimConfig, None, ["vehicles.count=2", "vehicles.spawn_ne_m=[[1.0, 2.0]]"])
    with pytest.raises(ConfigError, match="spawn_ne_m"):
        bad.validate()
    with pytest.raises(ConfigError, match="offboard_loss_action"):
        load_config(SimConfig, None, ["failsafe.offboard_loss_action='rtl'"]).validate()


def test_skycap_sim_process_streams_mavlink_and_stops_on_sigterm(tmp_path):
    port = free_udp_port()
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", port))
    sock.settimeout(0.2)
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "apps.cli",
            "sim",
            "--drones",
            "1",
            "--out",
            str(tmp_path),
            "--set",
            f"ports.offboard_base={port}",
            "--set",
            "ports.local_base=0",
            "--set",
            "ports.gcs_port=0",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    try:
        mav = mavlink.MAVLink(None, 255, 190)
        hb, t_end = None, time.monotonic() + 20.0
        while hb is None and time.monotonic() < t_end:
            try:
                data, _ = sock.recvfrom(4096)
            except socket.timeout:
                continue
            for m in mav.parse_buffer(data) or []:
                if m.get_type() == "HEARTBEAT":
                    hb = m
        assert hb is not None and hb.autopilot == mavlink.MAV_AUTOPILOT_PX4
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
        sock.close()
    assert proc.returncode == 0, out
    assert "SIGTERM received, stopping" in out and "simulator stopped" in out
    assert (tmp_path / "config.toml").is_file()
