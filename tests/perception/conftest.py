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
