"""The simulated camera renders from each vehicle's TRUE gimbal attitude (pitch to the horizon, yaw relative to the
heading), reports it in CameraInfo; the truth publisher carries the simulated gimbal's angles."""

from __future__ import annotations

import math

import numpy as np
import pytest

from shared_msgs import keys
from shared_msgs.codec import decode, encode
from shared_msgs.messages import CameraInfo, SimTruth
from simulator.config import SimConfig
from simulator.runner import SimWorld
from simulator.scene.camera_node import SIM_KEYPOINTS2D_GT, CameraNode, CameraTruth, truth_from_messages
from simulator.scene.config import CameraConfig, SceneConfig
from simulator.scene.person import PersonSim
from simulator.truth import TruthPublisher


@pytest.fixture(scope="module")
def person():
    return PersonSim()


def _node_and_truth(person, gimbal_yaw_deg: float):
    """A vehicle heading north, the person 8 m away 90 deg to its right (east), 4 m below the camera."""
    joints = person.state_at(0.0).joints_ned_m
    hips = joints[11:13].mean(axis=0)
    pos = hips + np.array([0.0, -8.0, -4.0])
    pitch = -math.atan2(4.0, 8.0)
    sent = []
    node = CameraNode("drone_1", SceneConfig(camera=CameraConfig(width_px=320, height_px=180)),
                      lambda: CameraTruth(1_000, pos, np.array([1.0, 0.0, 0.0, 0.0]), pitch, joints,
                                          gimbal_yaw_rad=math.radians(gimbal_yaw_deg)),
                      lambda topic, msg: sent.append((topic, msg)))
    return node, pitch


def test_camera_renders_from_the_gimbal_yaw_and_reports_it(person):
    node, pitch = _node_and_truth(person, 90.0)  # the gimbal turned to the person
    out = node.step()
    (p,) = out[SIM_KEYPOINTS2D_GT].persons
    uv = np.asarray(p.keypoints_px).reshape(17, 2)
    hips_uv = uv[11:13].mean(axis=0)
    assert np.allclose(hips_uv, [160.0, 90.0], atol=3.0)  # looked at: in the image centre
    info = out[keys.CAMERA_INFO]
    assert isinstance(info, CameraInfo)
    assert info.gimbal_yaw_rad == pytest.approx(math.radians(90.0)) and info.gimbal_pitch_rad == pytest.approx(pitch)
    node, _ = _node_and_truth(person, 0.0)  # looking ahead: the person is out of view
    assert node.step()[SIM_KEYPOINTS2D_GT].persons == []


def test_truth_carries_the_simulated_gimbal_and_the_camera_reads_it():
    class Bus:
        def __init__(self):
            self.sent = []

        def publish(self, key, msg):
            self.sent.append(msg)

    cfg = SimConfig()
    cfg.vehicles.count = 2
    cfg.gimbal.initial_pitch_deg = -20.0
    world = SimWorld(cfg)
    g = world.vehicles[1].gimbal
    g.set_angles(math.radians(-50.0), math.radians(30.0))
    for _ in range(300):
        g.step(0.01)
    bus = Bus()
    pub = TruthPublisher(world, bus, "f", with_person=False, gimbal_pitch_rad=math.radians(-5.0))
    pub.publish(123, world.truths(123))
    truth = decode(encode(bus.sent[0]), SimTruth)
    v0, v1 = truth.vehicles
    assert (v0.gimbal_pitch_rad, v0.gimbal_yaw_rad) == pytest.approx((math.radians(-20.0), 0.0))  # initial pitch
    assert (v1.gimbal_pitch_rad, v1.gimbal_yaw_rad) == pytest.approx((math.radians(-50.0), math.radians(30.0)))
    ct = truth_from_messages(truth, "drone_2")
    assert ct.gimbal_yaw_rad == pytest.approx(math.radians(30.0))
    # no gimbal: the fleet-wide fixed pitch, yaw 0
    cfg.gimbal.enabled = False
    bus2 = Bus()
    world2 = SimWorld(cfg)
    TruthPublisher(world2, bus2, "f", with_person=False, gimbal_pitch_rad=math.radians(-5.0)).publish(1, world2.truths(1))
    assert bus2.sent[0].vehicles[0].gimbal_pitch_rad == pytest.approx(math.radians(-5.0))
