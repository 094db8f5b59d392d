"""The camera node as a real process on a real Zenoh session: truth in, frames and keypoints out."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from comms.transport import Transport, TransportConfig
from tests.helpers.ports import free_tcp_port
from shared_msgs import keys
from shared_msgs.messages import CameraFrame, CameraInfo, Keypoints2D, SimTruth, VehicleState, VehicleTruth
from simulator.scene.person import PersonSim
from tests.helpers.paths import REPO

FLEET = "camtest"
DRONE = "drone_1"


def wait_for(pred, timeout_s: float, what: str) -> None:
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        if pred():
            return
        time.sleep(0.05)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


@pytest.mark.timeout(120)
def test_camera_process_renders_truth_and_publishes():
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    person = PersonSim()
    got: dict[str, list] = {"info": [], "frame": [], "kp": [], "gt": []}
    lock = threading.Lock()

    def keep(name):
        def cb(rx):
            with lock:
                got[name].append(rx.msg)

        return cb

    with Transport.open(TransportConfig(listen=[endpoint], connect=[]), node_id="test") as bus:
        bus.subscribe(keys.drone_key(FLEET, DRONE, keys.CAMERA_INFO), keep("info"), CameraInfo)
        bus.subscribe(keys.drone_key(FLEET, DRONE, keys.CAMERA_IMAGE), keep("frame"), CameraFrame)
        bus.subscribe(keys.drone_key(FLEET, DRONE, keys.SIM_KEYPOINTS2D), keep("kp"), Keypoints2D)
        bus.subscribe(keys.drone_key(FLEET, DRONE, "sim/keypoints2d_gt"), keep("gt"), Keypoints2D)
        env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
        child = subprocess.Popen(
            [sys.executable, "-m", "simulator.scene.node", "--fleet", FLEET, "--drone-id", DRONE,
             "--zenoh-connect", endpoint, "--set", "camera.width_px=320", "--set", "camera.height_px=180",
             "--set", "camera.rate_hz=10"],
            cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        )  # fmt: skip
        try:
            t0 = time.monotonic()
            pos = (-8.0, 0.0, -4.0)
            q = (1.0, 0.0, 0.0, 0.0)  # facing north, at the person
            n_truth = 0
            while time.monotonic() - t0 < 25 and len(got["frame"]) < 15:
                t_s = time.monotonic() - t0
                st = person.state_at(t_s)
                t_ns = time.time_ns()
                truth = SimTruth(
                    header=SimTruth.make_header(keys.SIM, t_ns),
                    vehicles=[VehicleTruth(drone_id=DRONE, position_ned_m=pos, velocity_ned_m_s=(0.0, 0.0, 0.0),
                                           q_world_body=q, gimbal_pitch_rad=-0.35)],
                    **st.truth_fields(),
                )  # fmt: skip
                bus.publish(keys.sim_key(FLEET, keys.TRUTH), truth)
                est = VehicleState(header=VehicleState.make_header(DRONE, t_ns), position_ned_m=(-7.8, 0.1, -4.0),
                                   velocity_ned_m_s=(0.0, 0.0, 0.0), q_world_body=q)  # fmt: skip
                bus.publish(keys.drone_key(FLEET, DRONE, keys.STATE), est)
                n_truth += 1
                time.sleep(0.05)
            assert child.poll() is None, child.communicate()[0]
            wait_for(lambda: len(got["frame"]) >= 15, 5, "15 camera frames")
            # frames stop when the truth stops (a truth is rendered once)
            time.sleep(0.5)
            n = len(got["frame"])
            time.sleep(0.6)
            assert len(got["frame"]) == n
        finally:
            child.send_signal(signal.SIGTERM)
            try:
                out, _ = child.communicate(timeout=20)
            except subprocess.TimeoutExpired:
                child.kill()
                out, _ = child.communicate()
        assert child.returncode == 0, out
        with lock:
            frames, kps, gts, infos = list(got["frame"]), list(got["kp"]), list(got["gt"]), list(got["info"])
    assert infos and infos[0].width_px == 320
    f = frames[-1]
    img = cv2.imdecode(np.frombuffer(f.data, np.uint8), cv2.IMREAD_COLOR)
    assert img.shape == (180, 320, 3)
    assert np.allclose(np.array(f.T_world_cam).reshape(4, 4)[:3, 3], (-7.8 + 0.1, 0.1, -4.0), atol=1e-6)
    # at 10 Hz from a 20 Hz truth: frame times are about 0.1 s apart
    dts = np.diff([fr.header.t_measurement_ns for fr in frames]) / 1e9
    assert 0.05 < np.median(dts) < 0.2
    assert [fr.frame_index for fr in frames] == list(range(frames[0].frame_index, frames[0].frame_index + len(frames)))
    assert all(k.simulated and k.detector == "sim_noisy_gt" for k in kps)
    assert sum(len(k.persons) for k in kps) >= 0.8 * len(kps)  # the person is in view and mostly detected
    assert all(len(g.persons) == 1 for g in gts)
    assert "camera:" in out and "frames" in out  # the final log line


def test_sim_camera_subcommand_parses():
    import argparse

    from simulator.scene import cli

    parser = argparse.ArgumentParser(prog="skycap")
    cli.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["sim-camera", "--fleet", "f1", "--drone", "drone_2", "--set", "camera.rate_hz=5"])
    assert (args.fleet, args.drone, args.set) == ("f1", "drone_2", ["camera.rate_hz=5"])
    assert callable(args.func)


def test_bad_scene_config_is_a_clear_error(tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "simulator.scene.node", "--fleet", FLEET, "--drone-id", DRONE, "--set", "camera.mount=wobbly"],
        cwd=REPO, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert out.returncode == 2 and "camera.mount='wobbly'" in out.stderr
