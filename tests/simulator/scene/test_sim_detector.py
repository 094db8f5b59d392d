"""Simulated keypoint and box detectors: their error statistics match the configuration."""

from __future__ import annotations

import numpy as np
import pytest

from simulator.scene.camera import GtProjection
from simulator.scene.config import SimDetectorConfig
from simulator.scene.sim_detector import SimBoxDetector, SimKeypointDetector
from skycap.config import ConfigError
from skycap.skeleton import COCO17_FLIP

W, H = 640, 360


def make_gt(box_h=100.0, visible=None) -> GtProjection:
    rng = np.random.default_rng(42)
    x0, y0 = 250.0, 120.0
    m = 0.05 * box_h
    uv = np.c_[rng.uniform(x0 + m, x0 + 0.4 * box_h - m, 17), rng.uniform(y0 + m, y0 + box_h - m, 17)]
    vis = np.ones(17, bool) if visible is None else visible
    box = np.array([x0, y0, x0 + 0.4 * box_h, y0 + box_h])
    return GtProjection(uv, np.full(17, 8.0), np.ones(17, bool), vis, vis, box, box, False)


def run(cfg: SimDetectorConfig, gt: GtProjection, n: int):
    det = SimKeypointDetector(cfg)
    return [det.detect(gt, W, H) for _ in range(n)]


def test_noise_std_and_confidence_match_config():
    cfg = SimDetectorConfig(miss_prob=0.0, outlier_prob=0.0, swap_prob=0.0, noise_px=2.0, noise_frac_of_height=0.01)
    gt = make_gt(box_h=150.0)
    out = run(cfg, gt, 400)
    err = np.array([o.uv_px - gt.uv_px for o in out])  # (N, 17, 2)
    expected = np.hypot(2.0, 0.01 * 150.0)
    assert out[0].sigma_px == pytest.approx(expected)
    assert err.std() == pytest.approx(expected, rel=0.05)
    assert abs(err.mean()) < 0.05 * expected
    conf = np.array([o.confidence for o in out])
    assert ((conf > 0) & (conf <= 1)).all()
    assert conf.mean() == pytest.approx(cfg.conf_mean * 0.85, rel=0.1)  # scaled down by the error
    # larger errors get lower confidence
    e = np.linalg.norm(err, axis=2).ravel()
    assert np.corrcoef(e, conf.ravel())[0, 1] < -0.3


def test_noise_is_temporally_correlated_when_frame_times_are_given():
    cfg = SimDetectorConfig(miss_prob=0.0, outlier_prob=0.0, swap_prob=0.0, noise_correlation_s=0.15)
    gt = make_gt()
    det = SimKeypointDetector(cfg)
    err = np.array([det.detect(gt, W, H, t_s=0.1 * i).uv_px - gt.uv_px for i in range(1500)])  # (N, 17, 2)
    rho = np.mean([np.corrcoef(err[:-1, j, a], err[1:, j, a])[0, 1] for j in range(17) for a in range(2)])
    assert rho == pytest.approx(np.exp(-0.1 / 0.15), abs=0.05)
    assert err.std() == pytest.approx(det.detect(gt, W, H).sigma_px, rel=0.05)  # same std as white
    white = np.array([det.detect(gt, W, H).uv_px - gt.uv_px for _ in range(800)])
    assert abs(np.corrcoef(white[:-1, 3, 0], white[1:, 3, 0])[0, 1]) < 0.1


def test_miss_outlier_swap_rates_match_config():
    cfg = SimDetectorConfig(miss_prob=0.1, outlier_prob=0.05, swap_prob=0.2, seed=3)
    gt = make_gt()
    out = run(cfg, gt, 1500)
    missed = np.array([o.missed for o in out])
    outl = np.array([o.outlier for o in out])
    swapped = np.array([o.swapped for o in out])
    assert missed.mean() == pytest.approx(0.1, abs=0.01)
    assert outl.mean() == pytest.approx(0.05, abs=0.008)
    assert swapped.mean() == pytest.approx(0.2, abs=0.03)
    for o in out[:200]:
        assert (o.confidence[o.missed] == 0).all()
        c = o.confidence[o.outlier]
        assert ((c >= cfg.outlier_conf_min) & (c <= cfg.outlier_conf_max)).all()
        grown = 0.5 * (o.box_px[2:] - o.box_px[:2]) * cfg.outlier_box_scale
        ctr = 0.5 * (o.box_px[2:] + o.box_px[:2])
        assert (np.abs(o.uv_px[o.outlier] - ctr) <= grown + 1e-9).all()
    # a swapped frame reports joint k near the true position of its mirror joint
    o = next(o for o in out if o.swapped)
    good = ~o.missed & ~o.outlier
    d_flip = np.linalg.norm(o.uv_px - gt.uv_px[list(COCO17_FLIP)], axis=1)[good]
    assert np.median(d_flip) < 4 * o.sigma_px


def test_occluded_joints_are_noisier_less_confident_and_missed_more():
    cfg = SimDetectorConfig(miss_prob=0.0, outlier_prob=0.0, swap_prob=0.0, occluded_miss_prob=0.2, seed=4)
    gt = make_gt()
    occ = np.zeros(17, bool)
    occ[[5, 7, 9, 11, 13, 15]] = True
    gt.occluded = occ
    out = run(cfg, gt, 1500)
    err = np.array([o.uv_px - gt.uv_px for o in out])
    missed = np.array([o.missed for o in out])
    conf = np.array([o.confidence for o in out])
    s = out[0].sigma_px
    ok = ~missed
    assert err[:, ~occ].std() == pytest.approx(s, rel=0.05)
    assert err[:, occ][ok[:, occ]].std() == pytest.approx(2.0 * s, rel=0.05)
    assert missed[:, occ].mean() == pytest.approx(0.2, abs=0.02) and missed[:, ~occ].mean() == 0
    assert conf[:, occ][ok[:, occ]].mean() == pytest.approx(0.5 * conf[:, ~occ].mean(), rel=0.08)


def test_invisible_joints_and_small_people():
    vis = np.ones(17, bool)
    vis[[9, 10, 15]] = False
    gt = make_gt(visible=vis)
    o = SimKeypointDetector(SimDetectorConfig(swap_prob=0.0)).detect(gt, W, H)
    assert (o.confidence[[9, 10, 15]] == 0).all()
    assert SimKeypointDetector(SimDetectorConfig(min_height_px=20)).detect(make_gt(box_h=15), W, H) is None
    o = SimKeypointDetector().detect(make_gt(), W, H)
    pk = o.to_person_keypoints()
    assert len(pk.keypoints_px) == 34 and len(pk.confidence) == 17


def test_seeded_and_reproducible():
    gt = make_gt()
    a = run(SimDetectorConfig(seed=5), gt, 20)
    b = run(SimDetectorConfig(seed=5), gt, 20)
    c = run(SimDetectorConfig(seed=6), gt, 20)
    assert all(np.array_equal(x.uv_px, y.uv_px) for x, y in zip(a, b))
    assert not all(np.array_equal(x.uv_px, y.uv_px) for x, y in zip(a, c))


def test_box_detector_statistics():
    # false alarms scored below 0.25, true detections at >= 0.3: the score tells them apart here
    cfg = SimDetectorConfig(
        box_noise_frac=0.05, box_miss_prob=0.1, box_false_alarm_rate=0.3, box_false_alarm_score_max=0.25, seed=2
    )
    gt = make_gt(box_h=100.0)
    det = SimBoxDetector(cfg)
    n = 2000
    true_hits, fas, errs = 0, 0, []
    for _ in range(n):
        for b in det.detect(gt, W, H):
            e = np.array([b.x_min_px, b.y_min_px, b.x_max_px, b.y_max_px]) - gt.box_px
            if b.score >= 0.3:
                assert np.abs(e).max() < 30
                true_hits += 1
                errs.append(e)
                assert b.var_x_min_px2 == pytest.approx((0.05 * 100) ** 2)
            else:
                fas += 1
            assert b.label == "person" and 0 <= b.x_min_px < b.x_max_px <= W and 0 <= b.y_min_px < b.y_max_px <= H
    assert true_hits / n == pytest.approx(0.9, abs=0.02)
    assert fas / n == pytest.approx(0.3, abs=0.05)
    assert np.std(errs) == pytest.approx(5.0, rel=0.08)
    assert SimBoxDetector(cfg).detect(None, W, H) is not None  # false alarms even without a person


def test_bad_config_is_refused():
    with pytest.raises(ConfigError, match="miss_prob"):
        SimKeypointDetector(SimDetectorConfig(miss_prob=1.5))
