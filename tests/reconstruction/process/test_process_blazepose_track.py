"""BlazePose in MediaPipe's video mode (``keypoints.track_rois``): the landmark region of a frame from the previous
frame's landmarks, the pose detector only where the track starts or is lost. Real model, a portrait shifted a few
pixels per frame as the "video"."""

from __future__ import annotations

import cv2
import numpy as np
import pytest


@pytest.fixture(scope="module")
def video():
    data = pytest.importorskip("skimage.data")
    img = np.ascontiguousarray(data.astronaut()[..., ::-1])  # RGB -> BGR
    frames, boxes = [], []
    for k in range(6):  # the person drifts right and down, 3 px per frame
        A = np.float32([[1, 0, 3 * k], [0, 1, 2 * k]])
        frames.append(cv2.warpAffine(img, A, (img.shape[1], img.shape[0])))
        boxes.append((25 + 3 * k, 20 + 2 * k, 345, 492))
    return frames, np.array(boxes, dtype=float)


@pytest.fixture(scope="module")
def blazepose():
    from reconstruction.keypoints.detectors import load_model

    return load_model("blazepose_full", 1)


def test_frames_that_do_not_follow_each_other_run_the_detector_as_predict_does(blazepose, video):
    frames, boxes = video
    ref = blazepose.predict(frames, boxes, 4)
    track: dict = {}
    got = blazepose.predict(frames, boxes, 4, frame_ids=[0, 2, 4, 6, 8, 10], track=track)
    assert track["detector_runs"] == len(frames)
    np.testing.assert_allclose(got[..., :2], ref[..., :2], atol=1e-2)
    np.testing.assert_allclose(got[..., 2], ref[..., 2], atol=1e-4)


def test_consecutive_frames_follow_the_landmarks_with_one_detector_run(blazepose, video):
    frames, boxes = video
    ref = blazepose.predict(frames, boxes, 4)
    track: dict = {}
    a = blazepose.predict(frames[:3], boxes[:3], 4, frame_ids=[0, 1, 2], track=track)
    b = blazepose.predict(frames[3:], boxes[3:], 4, frame_ids=[3, 4, 5], track=track)  # the track spans calls
    got = np.concatenate([a, b])
    assert track["detector_runs"] == 1
    ok = (ref[..., 2] > 0.5) & (got[..., 2] > 0.5)
    assert ok[1:].sum() > 40  # the tracked frames still find the person
    err = np.hypot(*(got[..., :2] - ref[..., :2]).T).T / boxes[:, 3:4]
    assert np.median(err[ok]) < 0.03, np.median(err[ok])  # the same joints, from a slightly different region
    # a box far from the tracked hip centre (another person, a jump): the detector runs again
    far = boxes[5:6] + [2000, 0, 0, 0]
    blazepose.predict(frames[5:6], far, 4, frame_ids=[6], track=track)
    assert track["detector_runs"] == 2
