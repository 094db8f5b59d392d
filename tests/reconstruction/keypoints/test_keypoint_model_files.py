"""The derived keypoint model files (scripts/make_models/quantize_keypoints.py): BlazePose's landmark network cut
to the outputs skycap reads, the int8 variants close to their float models, the keypoint-shift measure."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from reconstruction.keypoints import KEYPOINT_MODELS
from reconstruction.keypoints.detectors import BlazePose, blazepose_detector_name, load_model

ROOT = Path(__file__).resolve().parents[3]


def _script(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "scripts" / "make_models" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_blazepose_landmark_file_holds_only_the_outputs_read() -> None:
    m = load_model("blazepose_full")
    assert isinstance(m, BlazePose)
    assert [o.name for o in m.session.get_outputs()] == list(BlazePose.landmark_outputs)
    assert m.output_names == list(BlazePose.landmark_outputs)


def test_int8_landmarks_run_with_the_int8_pose_detector() -> None:
    assert blazepose_detector_name("blazepose_full") == "blazepose_detector"
    assert blazepose_detector_name("blazepose_full_int8") == "blazepose_detector_int8"


@pytest.fixture(scope="module")
def person_crops():
    """The person of skimage's astronaut portrait, cut as each network's crop (real image, not noise)."""
    data = pytest.importorskip("skimage.data")
    from reconstruction.keypoints.detectors import crop_person

    img = np.ascontiguousarray(data.astronaut()[..., ::-1])
    box = (120.0, 20.0, 330.0, 490.0)  # x, y, w, h: head to below the waist
    return {s: crop_person(img, box, s, 1.25)[0][None] for s in (192, 224, 256)}


@pytest.mark.parametrize("name", [n for n in KEYPOINT_MODELS if n.endswith("_int8")])
def test_int8_model_keypoints_stay_near_the_float_model(name, person_crops) -> None:
    f32, q = load_model(name.removesuffix("_int8")), load_model(name)
    crops = person_crops[f32.input_px]
    a, b = f32.predict_crops(crops)[0], q.predict_crops(crops)[0]
    both = (a[:, 2] > 0.3) & (b[:, 2] > 0.3)
    assert both.sum() >= 8, (a[:, 2], b[:, 2])
    d = np.linalg.norm(a[both, :2] - b[both, :2], axis=1) / np.hypot(*crops.shape[1:3])
    # int8 moves a joint by a few tenths of a percent of the crop diagonal on this portrait; a broken quantisation
    # (saturated u8s8 products, wrong scales) throws joints across the crop
    assert np.median(d) < 0.02 and d.max() < 0.08, d
    assert np.all(np.abs(a[both, 2] - b[both, 2]) < 0.25)


def test_keypoint_shift_is_in_percent_of_the_box_diagonal() -> None:
    shift_stats = _script("keypoint_shift").shift_stats
    ref = np.zeros((2, 17, 3))
    ref[..., 2] = 0.9
    var = ref.copy()
    var[..., 0] += 3.0  # 3 px right
    var[1, 5, 2] = 0.0  # not found by the variant: not counted
    box = np.array([[0, 0, 30.0, 40.0], [0, 0, 30.0, 40.0]])  # diagonal 50 px
    s = shift_stats(ref, var, box)
    assert s["joints"] == 33
    assert s["median_pct"] == pytest.approx(6.0) and s["p90_pct"] == pytest.approx(6.0)
