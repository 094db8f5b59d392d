"""Fixtures for the perception tests: the real shipped ONNX models, opened once per session."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

DATA = Path(__file__).resolve().parent / "data"


@pytest.fixture(scope="session")
def detector():
    from onboard.detector.detector import PersonDetector

    return PersonDetector()


@pytest.fixture(scope="session")
def keypoint_detectors():
    from reconstruction.keypoints.detectors import KEYPOINT_MODELS, KeypointConfig, KeypointDetectors

    return KeypointDetectors(KeypointConfig(models=list(KEYPOINT_MODELS)))


@pytest.fixture(scope="session")
def aerial_labels() -> dict:
    return json.loads((DATA / "aerial_people.json").read_text())


@pytest.fixture(scope="session")
def keypoint_labels() -> dict:
    return json.loads((DATA / "keypoint_labels.json").read_text())


@pytest.fixture(scope="session")
def aerial_dir(shared_data: Path) -> Path:
    return shared_data / "images" / "aerial"


@pytest.fixture(scope="session")
def grace_hopper() -> np.ndarray:
    mpl = pytest.importorskip("matplotlib")
    path = Path(mpl.get_data_path()) / "sample_data" / "grace_hopper.jpg"
    img = cv2.imread(str(path))
    assert img is not None, path
    return img


@pytest.fixture(scope="session")
def astronaut() -> np.ndarray:
    data = pytest.importorskip("skimage.data")
    return np.ascontiguousarray(data.astronaut()[..., ::-1])  # RGB -> BGR


@pytest.fixture(scope="session")
def sim_frame():
    """A frame rendered by the simulator (simulator.scene): the person 10 m ahead, 2 m aside, 5 m below the
    camera, which looks at the hips. Its ``T_world_cam`` is set as the attribute ``T_world_cam``."""
    import math

    from scipy.spatial.transform import Rotation

    render = pytest.importorskip("simulator.scene.render")
    from simulator.scene.camera import PinholeCamera, camera_pose
    from simulator.scene.config import CameraConfig, PersonConfig
    from simulator.scene.person import PersonSim

    cfg = CameraConfig(lever_arm_body_m=[0.0, 0.0, 0.0])
    cam = PinholeCamera.from_config(cfg)
    state = PersonSim(PersonConfig()).state_at(4.0)
    hip = state.joints_ned_m[[11, 12]].mean(0)
    pos = hip + np.array([-10.0, 2.0, -5.0])  # 10 m behind, 2 m aside, 5 m up, looking at the hips
    d = hip - pos
    x, y, z, w = Rotation.from_euler("ZYX", [math.atan2(d[1], d[0]), 0.0, 0.0]).as_quat()
    T = camera_pose(cfg, pos, (w, x, y, z), -math.atan2(d[2], math.hypot(d[0], d[1])))
    frame = render.Renderer(cam, cfg, PersonConfig()).render(T, state.joints_ned_m)
    assert frame.gt is not None and frame.gt.box_px is not None
    frame.T_world_cam = np.asarray(T)
    return frame
