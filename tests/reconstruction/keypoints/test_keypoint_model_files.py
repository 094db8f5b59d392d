"""The keypoint model files as scripts/make_models/ makes them: BlazePose's landmark networks cut to the outputs
skycap reads; the keypoint-shift measure (scripts/make_models/keypoint_shift.py) used to compare model variants."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from reconstruction.keypoints.detectors import BlazePose, load_model

ROOT = Path(__file__).resolve().parents[3]


def _script(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "scripts" / "make_models" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_blazepose_asks_for_the_outputs_it_reads() -> None:
    m = load_model("blazepose_full")
    assert isinstance(m, BlazePose) and m.output_names == list(BlazePose.landmark_outputs)


@pytest.mark.parametrize("name", ["blazepose_full", "blazepose_lite"])
def test_blazepose_landmark_files_hold_only_the_outputs_read(name) -> None:
    m = load_model(name)
    assert [o.name for o in m.session.get_outputs()] == list(BlazePose.landmark_outputs)


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
