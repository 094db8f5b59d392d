"""The accuracy metrics on synthetic joints with known answers (reconstruction.metrics)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from reconstruction.metrics import (BODY_GROUPS, MetricsError, accuracy_metrics, mpjpe_mm, pa_mpjpe_mm, root_err_mm,
                                    w_mpjpe_mm)
from skycap.skeleton import SCORED_JOINTS


@pytest.fixture(scope="module")
def gt() -> np.ndarray:
    """12 frames of a random but body-sized COCO-17 skeleton (metres) moving about."""
    rng = np.random.default_rng(3)
    return rng.normal(scale=0.4, size=(12, 17, 3)) + rng.normal(scale=2.0, size=(12, 1, 3))


def test_identical_scores_zero(gt):
    m = accuracy_metrics(gt, gt)
    for k in ("mpjpe_mm", "pa_mpjpe_mm", "w_mpjpe_mm", "root_err_mm"):
        assert m[k] == 0.0
    assert m["frames_scored"] == 12 and set(m["per_group_mm"]) == set(BODY_GROUPS) == {"torso", "arms", "legs", "head"}


def test_root_offset_shows_in_world_and_root_error_only(gt):
    """A constant 10 cm root offset: W-MPJPE and root error 100 mm; root-aligned MPJPE and PA-MPJPE 0."""
    pred = gt + np.array([0.06, -0.08, 0.0])
    m = accuracy_metrics(pred, gt, ndigits=None)
    assert m["w_mpjpe_mm"] == pytest.approx(100.0) and m["root_err_mm"] == pytest.approx(100.0)
    assert m["mpjpe_mm"] == pytest.approx(0.0, abs=1e-9) and m["pa_mpjpe_mm"] == pytest.approx(0.0, abs=1e-9)
    assert all(g["w_mpjpe_mm"] == pytest.approx(100.0) and g["mpjpe_mm"] == pytest.approx(0.0, abs=1e-9)
               for g in m["per_group_mm"].values())
    assert w_mpjpe_mm(pred, gt) == pytest.approx(100.0) and root_err_mm(pred, gt) == pytest.approx(100.0)
    assert mpjpe_mm(pred, gt) == pytest.approx(0.0, abs=1e-9)


def test_rigid_and_similarity_transforms_give_pa_zero(gt):
    """Per frame a different rotation, shift and scale: PA-MPJPE 0; the others are not."""
    R = Rotation.random(len(gt), random_state=1).as_matrix()
    s = np.linspace(0.8, 1.2, len(gt))
    pred = s[:, None, None] * np.einsum("tij,tkj->tki", R, gt) + np.array([1.0, 2.0, -0.5])
    m = accuracy_metrics(pred, gt, ndigits=None)
    assert m["pa_mpjpe_mm"] == pytest.approx(0.0, abs=1e-6)
    assert all(g["pa_mpjpe_mm"] == pytest.approx(0.0, abs=1e-6) for g in m["per_group_mm"].values())
    assert m["mpjpe_mm"] > 100 and m["w_mpjpe_mm"] > 100


def test_one_joint_error_known_values(gt):
    """Only the right wrist 13 mm off: W-MPJPE = root-aligned MPJPE = 13/13 over the 13 scored joints (the root is
    not moved); the arms group 13/4; torso, legs and head 0; root error 0."""
    pred = gt.copy()
    pred[:, 10] += np.array([0.005, 0.012, 0.0])  # 13 mm
    m = accuracy_metrics(pred, gt, ndigits=None)
    assert m["w_mpjpe_mm"] == pytest.approx(13.0 / len(SCORED_JOINTS))
    assert m["mpjpe_mm"] == pytest.approx(13.0 / len(SCORED_JOINTS))
    assert m["root_err_mm"] == pytest.approx(0.0)
    g = m["per_group_mm"]
    assert g["arms"]["w_mpjpe_mm"] == pytest.approx(13.0 / 4) and g["torso"]["mpjpe_mm"] == pytest.approx(0.0)
    assert g["legs"]["w_mpjpe_mm"] == 0.0 and g["head"]["mpjpe_mm"] == 0.0
    # the alignment spreads it; it cannot raise the sum of squares (169), so the mean stays <= sqrt(169 / 13)
    assert 0 < m["pa_mpjpe_mm"] <= np.sqrt(169.0 / len(SCORED_JOINTS)) + 1e-9


def test_hip_error_moves_the_root_into_every_joint_of_mpjpe(gt):
    """Left hip 20 mm off: the mid-hip root moves 10 mm, so root-aligned MPJPE sees 10 mm at every other joint."""
    pred = gt.copy()
    pred[:, 11, 2] += 0.020
    m = accuracy_metrics(pred, gt, ndigits=None)
    assert m["root_err_mm"] == pytest.approx(10.0)
    assert m["w_mpjpe_mm"] == pytest.approx(20.0 / 13)
    assert m["mpjpe_mm"] == pytest.approx((10.0 + 10.0 + 11 * 10.0) / 13)  # both hips 10 mm from the new root


def test_suffix_rounding_and_shape_errors(gt):
    m = accuracy_metrics(gt + 0.01234, gt, suffix="_window")
    assert set(m) == {"frames_scored_window", "mpjpe_mm_window", "pa_mpjpe_mm_window", "w_mpjpe_mm_window",
                      "root_err_mm_window", "per_group_mm_window"}
    assert m["w_mpjpe_mm_window"] == round(1000 * np.sqrt(3) * 0.01234, 1)
    with pytest.raises(MetricsError, match="same shape"):
        accuracy_metrics(gt[:, :16], gt)
    with pytest.raises(MetricsError, match="root joints"):
        mpjpe_mm(gt[:, :5], gt[:, :5])
    assert pa_mpjpe_mm(gt, gt, joints=SCORED_JOINTS) == pytest.approx(0.0, abs=1e-9)


def test_a_frame_with_nan_is_left_out(gt):
    pred = gt + np.array([0.0, 0.0, 0.05])
    pred[3, 7] = np.nan
    m = accuracy_metrics(pred, gt, ndigits=None)
    assert m["w_mpjpe_mm"] == pytest.approx(50.0) and m["pa_mpjpe_mm"] == pytest.approx(0.0, abs=1e-6)
