"""2D keypoint models on the real ONNX files: hand-labelled portraits, crop geometry, batch path."""

from __future__ import annotations

import numpy as np
import pytest

from reconstruction.keypoints.detectors import (
    BLAZEPOSE_TO_COCO17,
    KEYPOINT_MODELS,
    KeypointConfig,
    KeypointDetectors,
    KeypointInputError,
    crop_to_image,
    draw_keypoints,
    roi_transform,
)
from skycap.skeleton import COCO17, COCO17_NAMES


# --- pure logic -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("up", [(0.0, -1.0), (0.3, -1.0), (1.0, 0.2)])
def test_crop_transform_round_trips_and_puts_the_centre_in_the_middle(up) -> None:
    A = roi_transform((300.0, 200.0), 128.0, 256, up)
    pts = np.random.default_rng(0).uniform(-50, 600, size=(20, 2))
    crop = pts @ A[:, :2].T + A[:, 2]
    assert np.allclose(crop_to_image(crop, A), pts)
    assert np.allclose(A @ [300.0, 200.0, 1.0], [127.5, 127.5])
    # a point one half-side "up" from the centre lands at the top edge
    u = np.asarray(up) / np.hypot(*up)
    assert np.allclose(A @ [*(np.array([300.0, 200.0]) + 64.0 * u), 1.0], [127.5, -0.5])


def test_blazepose_mapping_is_coco17() -> None:
    # BlazePose 33: 0 nose, 2 left eye, 5 right eye, 7/8 ears, 11/12 shoulders, 13/14 elbows, 15/16 wrists,
    # 23/24 hips, 25/26 knees, 27/28 ankles
    assert len(BLAZEPOSE_TO_COCO17) == 17
    assert BLAZEPOSE_TO_COCO17[COCO17["left_shoulder"]] == 11 and BLAZEPOSE_TO_COCO17[COCO17["right_ankle"]] == 28


# --- real models on hand-labelled portraits ---------------------------------------------------------------
@pytest.fixture(scope="module")
def portraits(astronaut, grace_hopper) -> dict:
    return {"astronaut": astronaut, "grace_hopper": grace_hopper}


#: Known weak spot, kept visible instead of widening every tolerance: BlazePose puts the astronaut's right
#: elbow (under the bulky suit sleeve) on the upper arm, 0.11-0.12 of the box height above the bend.
#: BlazePose lite (half of full's CPU time) misses that sleeve worse: the right elbow 0.24 of the box height off (near
#: the shoulder), the right shoulder 0.12; and it puts Grace Hopper's eyes 0.051-0.054 of the box height off.
LOOSER_TOLERANCE = {("blazepose_full", "astronaut", "right_elbow"): 0.15,
                    ("blazepose_lite", "astronaut", "right_elbow"): 0.26,
                    ("blazepose_lite", "astronaut", "right_shoulder"): 0.13,
                    ("blazepose_lite", "grace_hopper", "left_eye"): 0.06,
                    ("blazepose_lite", "grace_hopper", "right_eye"): 0.06}


@pytest.mark.parametrize("image_name", ["astronaut", "grace_hopper"])
def test_every_model_finds_the_labelled_face_shoulders_and_elbows(
    keypoint_detectors, keypoint_labels, portraits, image_name
) -> None:
    lab = keypoint_labels[image_name]
    tol = keypoint_labels["tolerance_fraction_of_box_height"]
    box = lab["box_xywh"]
    people = keypoint_detectors.detect(portraits[image_name], [box])
    assert set(people) == set(KEYPOINT_MODELS)
    failures = []
    for model, persons in people.items():
        (p,) = persons
        assert p.keypoints_px.shape == (17, 2) and p.confidence.shape == (17,)
        assert np.all((p.confidence >= 0) & (p.confidence <= 1))
        for name, xy in lab["keypoints"].items():
            j = COCO17[name]
            err = float(np.hypot(*(p.keypoints_px[j] - xy)))
            limit = LOOSER_TOLERANCE.get((model, image_name, name), tol[name]) * box[3]
            if err > limit:
                failures.append(f"{model} {name}: {err:.0f} px > {limit:.0f}")
            if p.confidence[j] < 0.1:
                failures.append(f"{model} {name}: confidence {p.confidence[j]:.2f}")
    assert not failures, failures


def test_models_disagree_like_independent_detectors(keypoint_detectors, grace_hopper) -> None:
    people = keypoint_detectors.detect(grace_hopper, [(20, 30, 492, 570)])
    a = people["movenet_thunder"][0].keypoints_px
    b = people["blazepose_full"][0].keypoints_px
    d = np.hypot(*(a - b).T)[[0, 1, 2, 5, 6]]
    assert np.all(d > 0.01)  # different networks, not copies of one output


def test_several_people_and_the_json_form(keypoint_detectors, grace_hopper) -> None:
    boxes = [(20, 30, 492, 570), (120, 60, 300, 300)]
    people = keypoint_detectors.detect(grace_hopper, boxes)
    for persons in people.values():
        assert [p.box_xywh for p in persons] == [tuple(map(float, b)) for b in boxes]
    d = people["movenet_lightning"][0].to_dict()
    assert list(d["keypoints"]) == list(COCO17_NAMES)
    msg = people["blazepose_full"][0].to_msg()
    assert len(msg.keypoints_px) == 34 and len(msg.confidence) == 17
    out = draw_keypoints(grace_hopper, people)
    assert out.shape == grace_hopper.shape and not np.array_equal(out, grace_hopper)


def test_recording_batch_path_matches_single_frames(keypoint_detectors, grace_hopper, astronaut) -> None:
    kd = KeypointDetectors(KeypointConfig(models=["movenet_lightning", "blazepose_full"], batch_size=2))
    frames = [grace_hopper, astronaut, grace_hopper, astronaut]
    boxes = np.array([(20, 30, 492, 570), (25, 20, 345, 492), (np.nan,) * 4, (25, 20, 345, 492)])
    out = kd.detect_recording(iter(frames), boxes, progress=False)
    for name, arr in out.items():
        assert arr.shape == (4, 17, 3)
        assert np.all(np.isnan(arr[2, :, :2])) and np.all(arr[2, :, 2] == 0)
        single = keypoint_detectors.detect(astronaut, [boxes[1]])[name][0]
        assert np.allclose(arr[1, :, :2], single.keypoints_px, atol=1e-3)
        assert np.allclose(arr[3], arr[1])
    with pytest.raises(KeypointInputError, match="frames for"):
        kd.detect_recording(iter(frames[:2]), boxes, progress=False)


def test_bad_inputs_give_clear_errors(keypoint_detectors, grace_hopper) -> None:
    with pytest.raises(KeypointInputError, match="unknown keypoint model"):
        KeypointDetectors(KeypointConfig(models=["openpose"]))
    with pytest.raises(KeypointInputError, match="positive width"):
        keypoint_detectors.detect(grace_hopper, [(0, 0, -5, 10)])
    with pytest.raises(KeypointInputError, match="BGR uint8"):
        keypoint_detectors.detect(grace_hopper[..., 0], [(0, 0, 50, 50)])
