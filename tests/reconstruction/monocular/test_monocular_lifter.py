"""The learned single-frame lift (beyond the paper): shipped weights, training geometry, lift accuracy and robustness."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from reconstruction.dictionary.learn_dictionary import EVAL_CLIPS
from reconstruction.metrics import pa_mpjpe_mm
from reconstruction.monocular.dictionary import load_dictionary
from reconstruction.monocular.evaluate import LIMB_JOINTS
from reconstruction.monocular.lifter import (
    DEFAULT_LIFTER,
    LifterConfig,
    LifterError,
    LifterNet,
    PoseLifter,
    ViewSampling,
    camera_rotations,
    training_batch,
)
from reconstruction.monocular.single_frame import initialise
from tests.helpers.paths import REPO

MOTIONS = REPO / "simulator" / "data" / "motions"


@pytest.fixture(scope="module")
def lifter() -> PoseLifter:
    return PoseLifter.load()


def _punch() -> np.ndarray:
    """CMU 002_05 (a held-out clip of both the dictionary and the lifter), 126 poses NED metres."""
    with np.load(MOTIONS / "punch.npz") as z:
        assert "002_05" in str(z["source"])
        return z["joints_ned_m"]


def _orthographic_views(X: np.ndarray, seed: int, px_per_m: float = 300.0):
    """Keypoints W (T, 2, 17) of poses X (T, 17, 3) seen orthographically from random drone-like views."""
    rng = np.random.default_rng(seed)
    T = len(X)
    R = camera_rotations(rng.uniform(-np.pi, np.pi, T), np.radians(rng.uniform(0, 40, T)), np.zeros(T))
    P = np.einsum("nij,nkj->nki", R, X - X.mean(1, keepdims=True))
    return np.swapaxes(px_per_m * P[..., :2] + np.array([960.0, 540.0]), 1, 2)


def test_shipped_lifter_is_documented(lifter):
    assert DEFAULT_LIFTER.is_file() and DEFAULT_LIFTER.stat().st_size < 4_000_000
    assert "mocap.cs.cmu.edu" in lifter.credit
    assert set(EVAL_CLIPS) <= set(lifter.held_out)
    assert lifter.clips and not set(lifter.clips) & set(lifter.held_out)
    assert (DEFAULT_LIFTER.parent / "README.md").is_file() and (DEFAULT_LIFTER.parent / "train_lifter.py").is_file()


def test_training_views_are_the_projection_of_the_target():
    """Far away and without detector errors, the input is the normalised image of the target pose."""
    X = _punch()
    view = ViewSampling(distance_m=(1e6, 1e6 + 1), noise_rel=(0.0, 0.0), drop_rate_max=0.0, outlier_rate_max=0.0)
    x, y = training_batch(X, np.random.default_rng(0), 64, view)
    x, y = x.numpy().astype(float), y.numpy().astype(float)
    assert x.shape == (64, 51) and y.shape == (64, 17, 3)
    np.testing.assert_allclose(x[:, 34:], 1.0)  # every joint visible
    xy = y[..., :2] - y[..., :2].mean(1, keepdims=True)
    np.testing.assert_allclose(np.sqrt((xy**2).sum(-1).mean(1)), 1.0, rtol=1e-5)  # unit RMS image radius
    np.testing.assert_allclose(x[:, :34].reshape(64, 17, 2), xy, atol=1e-4)
    np.testing.assert_allclose(y.mean(1), 0.0, atol=1e-5)
    # the camera looks down at the person (positive elevation): the head is nearer than the feet in depth order
    view_down = ViewSampling(elevation_deg=(45.0, 45.0), roll_sigma_deg=0.0, noise_rel=(0, 0), drop_rate_max=0, outlier_rate_max=0)
    _, y = training_batch(X, np.random.default_rng(1), 32, view_down)
    assert np.all(y[:, 0, 2].numpy() < y[:, 15:17, 2].numpy().mean(1))


def test_lift_of_a_held_out_clip_beats_the_dictionary_init(lifter):
    X = _punch()[::3]
    W = _orthographic_views(X, seed=2)
    res = lifter.lift(W, np.ones((len(X), 17)))
    gt = X
    e_lift = pa_mpjpe_mm(np.swapaxes(res.S, 1, 2), gt, joints=LIMB_JOINTS)
    e_dict = pa_mpjpe_mm(np.swapaxes(initialise(W, None, load_dictionary()).S, 1, 2), gt, joints=LIMB_JOINTS)
    assert e_lift < 60.0 and e_lift < 0.8 * e_dict, (e_lift, e_dict)
    # the returned orthographic form reproduces the keypoints: W ~ R S + t (R with orthonormal rows)
    np.testing.assert_allclose(res.R @ np.swapaxes(res.R, 1, 2), np.broadcast_to(np.eye(2), (len(X), 2, 2)), atol=1e-9)
    rms = np.sqrt(np.mean(np.sum((W - W.mean(-1, keepdims=True)) ** 2, 1), 1))
    assert np.median(np.abs(res.reprojection() - W)) < 0.1 * np.median(rms)
    assert res.inlier.all()


def test_lift_masks_gross_outliers_and_keeps_its_accuracy(lifter):
    X = _punch()[::3]
    T = len(X)
    W = _orthographic_views(X, seed=4)
    clean = pa_mpjpe_mm(np.swapaxes(lifter.lift(W, np.ones((T, 17))).S, 1, 2), X, joints=LIMB_JOINTS)
    bad = np.zeros((T, 17), bool)
    bad[np.arange(T), np.arange(T) % 17] = True  # one joint per frame thrown 0.6 m (180 px) off
    Wb = W.copy()
    Wb[:, 0][bad] += 180.0
    res = lifter.lift(Wb, np.ones((T, 17)))
    assert np.mean(~res.inlier[bad]) > 0.8
    assert np.mean(~res.inlier[~bad]) < 0.05
    err = pa_mpjpe_mm(np.swapaxes(res.S, 1, 2), X, joints=LIMB_JOINTS)
    assert err < clean + 10.0, (err, clean)
    # missing joints (NaN, confidence 0) are not used and do not break the lift
    Wm = W.copy()
    Wm[:, :, 9] = np.nan
    conf = np.ones((T, 17))
    conf[:, 9] = 0.0
    res = lifter.lift(Wm, conf)
    assert not res.inlier[:, 9].any() and np.isfinite(res.S).all()


def test_save_load_round_trip_and_malformed_file(tmp_path):
    net = LifterNet(hidden=16, blocks=1)
    p = PoseLifter(net, clips=("a",), held_out=("b",), credit="c").save(tmp_path / "l.npz")
    back = PoseLifter.load(p)
    assert back.clips == ("a",) and back.held_out == ("b",) and back.credit == "c"
    x = np.random.default_rng(0).normal(size=(3, 17, 2))
    P0, _, _ = PoseLifter(net).predict(x, np.ones((3, 17)))
    P1, _, _ = back.predict(x, np.ones((3, 17)))
    np.testing.assert_allclose(P1, P0, atol=5e-3)  # float16 storage
    with pytest.raises(LifterError, match="do not exist"):
        PoseLifter.load(tmp_path / "missing.npz")
    np.savez(tmp_path / "bad.npz", hidden=16)
    with pytest.raises(LifterError, match="malformed.*train_lifter"):
        PoseLifter.load(tmp_path / "bad.npz")


def test_training_lowers_the_loss():
    from reconstruction.lifter.train_lifter import train

    X = _punch()
    _, losses = train(X - X.mean(1, keepdims=True), steps=150, batch=64, hidden=64, log_every=0)
    assert np.mean(losses[-20:]) < 0.6 * np.mean(losses[:5])


def test_pipeline_takes_the_lifted_start_and_can_leave_it_out():
    """The lift is one more start of the perspective BA (kept when its objective is the lowest)."""
    import dataclasses

    from reconstruction.monocular.pipeline import MonocularConfig, ModelFitConfig, reconstruct_monocular

    from body_fixture import orbit_view

    X = _punch()[::2][:40]
    t = np.arange(len(X)) / 30.0
    W, T_wc, K = orbit_view(X, t, omega_deg_s=30.0)
    cfg = MonocularConfig(model=ModelFitConfig(enabled=False), ablation_no_articulation=False)
    kw = dict(T_world_cam=T_wc, K=K, perspective=True, extended=True, dt_s=1 / 30.0)
    res = reconstruct_monocular(W, None, load_dictionary(), cfg, **kw)
    assert res.lifted is not None and res.lifted.S.shape == (len(X), 3, 17)
    assert res.perspective_start in ("ba_paper", "ba_extended", "lifted")
    e_lift = pa_mpjpe_mm(np.swapaxes(res.lifted.S, 1, 2), X, joints=LIMB_JOINTS)
    e_init = pa_mpjpe_mm(np.swapaxes(res.init.S, 1, 2), X, joints=LIMB_JOINTS)
    assert e_lift < e_init, (e_lift, e_init)
    off = reconstruct_monocular(W, None, load_dictionary(), dataclasses.replace(cfg, lifter=LifterConfig(enabled=False)), **kw)
    assert off.lifted is None and off.perspective_start in ("ba_paper", "ba_extended")
    # the kept start has the lowest objective of those tried
    assert res.ba_perspective.objective_final_sigma[1] <= off.ba_perspective.objective_final_sigma[1] + 1e-9


def test_body_model_is_also_fitted_from_the_lifted_start_and_keeps_the_lower_energy():
    import dataclasses

    from reconstruction.monocular.pipeline import MonocularConfig, ModelFitConfig, reconstruct_monocular
    from reconstruction.multiview.fit import FitConfig

    from body_fixture import orbit_view

    X = _punch()[::2][:30]
    t = np.arange(len(X)) / 30.0
    W, T_wc, K = orbit_view(X, t, omega_deg_s=30.0)
    fit = FitConfig(w_pose_prior=0.5, iters=60, refine_cameras=False, polish_iters=0)
    cfg = MonocularConfig(model=ModelFitConfig(fit=fit), ablation_no_articulation=False)
    kw = dict(T_world_cam=T_wc, K=K, perspective=True, extended=True, dt_s=1 / 30.0)
    one = reconstruct_monocular(W, None, load_dictionary(), dataclasses.replace(cfg, perspective_start="ba_extended"), **kw)
    assert one.model_start == "ba_extended"  # forced start: only that one is fitted
    both = reconstruct_monocular(W, None, load_dictionary(), cfg, **kw)
    assert both.model_start in (both.perspective_start, "lifted")
    assert np.isfinite(both.model.energy)
    if both.perspective_start == "ba_extended":
        assert both.model.energy <= one.model.energy + 1e-9
    with pytest.raises(Exception, match="perspective_start 'nope'.*pick one"):
        reconstruct_monocular(W, None, load_dictionary(), dataclasses.replace(cfg, perspective_start="nope"), **kw)


def test_lifted_start_takes_the_kept_placement_and_keeps_its_posture():
    from scipy.spatial.transform import Rotation

    from reconstruction.monocular.pipeline import _placed_like
    from skycap.skeleton import COCO17, COCO17_LIMBS

    X = _punch()[:20].astype(float)
    rng = np.random.default_rng(0)
    R = Rotation.from_euler("z", 0.7).as_matrix()
    ref = 1.1 * np.einsum("ij,tkj->tki", R, X) + rng.normal(0, 1, (20, 1, 3))  # other place, size, heading
    out = _placed_like(X, ref, COCO17_LIMBS)
    hip = lambda Y: 0.5 * (Y[:, COCO17["left_hip"]] + Y[:, COCO17["right_hip"]])  # noqa: E731
    np.testing.assert_allclose(hip(out), hip(ref), atol=1e-9)  # the kept hip path
    d = lambda Y: Y - hip(Y)[:, None]  # noqa: E731
    np.testing.assert_allclose(d(out), 1.1 * d(X), atol=1e-9)  # the start's posture and heading, the kept size
