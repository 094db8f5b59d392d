"""World placement of the monocular flight path (``reconstruction.monocular.reconstruct.run``) on a demo-like single-drone flight.

The simulated demo flight (``skycap demo --drones 1``) is far harder than the eval harness: the camera is 9 m
away with a 640x360 image (f = 457 px), so the person's RMS image radius is ~24 px with ~5 px of detector
noise, and frames arrive at ~8.7 Hz with uneven intervals (14-600 ms). On it the monocular path used to put
the body on the camera, 9.2 m from the truth (unaligned MPJPE 9199 mm): the track cleaning flagged 66 % of the
keypoints (its threshold was relative to the tiny person only), the orthographic start then had near-zero
poses whose size-implied depth was astronomically large, and the perspective BA moved every root onto the
camera centres (all reprojection residuals saturated, the root smoothness alone left). These tests fly a
synthetic capture with those properties through the same flight code path and check the placement in the
WORLD frame, without any alignment.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from reconstruction.metrics import pa_mpjpe_mm, w_mpjpe_mm
from reconstruction.monocular.perspective import (
    ADULT_BONE_RMS_M,
    PerspectiveConfig,
    perspective_bundle_adjust,
    robust_depth_track,
)
from reconstruction.monocular.reconstruct import MonocularRunConfig, run
from reconstruction.monocular.tracks import temporal_outlier_mask, track_noise_px
from reconstruction.synth import SynthConfig, interpolate_joints, synthesize_capture
from skycap.bvh import read_bvh
from skycap.errors import SkycapError
from skycap.skeleton import COCO17_LIMBS, mocap_to_coco17

from body_fixture import UPRIGHT_BODY




def _demo_like_capture(J: np.ndarray, t_ns: np.ndarray, seed: int = 2):
    """One drone 9 m from the person (8 m orbit radius, 6 m up, 0.15 rad/s), small image, ~8.7 Hz with jittered
    and dropped frames, RTK-grade camera poses."""
    sc = SynthConfig(drones=1, radius_m=8.0, altitude_m=6.0, speed_mps=0.15 * 8.0, camera_rate_hz=12.0, unsync=True,
                     frame_jitter_ms=15.0, noise_px=4.0, outlier_rate=0.05, swap_rate=0.0, miss_rate=0.05,
                     camera_pos_noise_m=0.03, camera_rot_noise_deg=0.5, width_px=640, height_px=360, focal_px=457.0,
                     aim_wobble_deg=1.0)  # fmt: skip
    cap, truth = synthesize_capture(J, t_ns, sc, seed=seed)
    cam = cap.cameras[0]
    keep = np.random.default_rng(seed).random(cam.num_frames) > 0.3  # drop 30 % of the frames: uneven intervals
    cam = dataclasses.replace(cam, t_frame_ns=cam.t_frame_ns[keep], keypoints_px=cam.keypoints_px[keep],
                              confidence=cam.confidence[keep])  # fmt: skip
    cap = dataclasses.replace(cap, cameras=[cam])
    return cap, truth


@pytest.fixture(scope="module")
def demo_like(cmu_dir, tmp_path_factory):
    m = read_bvh(cmu_dir / "002" / "002_05.bvh")
    m = m.slice(1, 1 + int(15 * m.fps), 1)  # 15 s of punching and stepping
    J = mocap_to_coco17(m)
    t_ns = (np.arange(len(J)) * m.frame_time_s * 1e9).astype(np.int64)
    cap, truth = _demo_like_capture(J, t_ns)
    out = tmp_path_factory.mktemp("mono_world")
    summary = run(cap, MonocularRunConfig(rrd=False), out_dir=out).summary
    z = np.load(out / "motion.npz")
    gt = interpolate_joints(truth.t_ns, truth.joints_ned, z["t_ns"])
    return cap, z["joints_ned"], gt, summary


@pytest.mark.shared_data
def test_demo_like_flight_places_the_body_in_the_world(demo_like):
    cap, X, gt, summary = demo_like
    cam = cap.cameras[0]
    T_wc = cam.pose_at(cam.t_frame_ns)
    dist = np.median(np.linalg.norm(gt.mean(1) - T_wc[:, :3, 3], axis=-1))
    assert 8.0 < dist < 11.0  # the setting is the demo's: the person 9-10 m from the camera
    assert X.shape == gt.shape and summary["variant"] == "perspective"
    # WORLD frame, no alignment: the hip centre within 1.5 m of the truth (measured 0.95 m; the old path: 9.4 m,
    # on the camera), and the body neither on the camera nor at an absurd depth in any frame. (One camera 9 m away
    # seeing a 24 px person: the depth is what is left uncertain; started from the truth the BA stays within
    # 0.07 m of it, from the orthographic BA it ends in a flatter pose placed farther, see RESULTS.md.)
    root_err = np.linalg.norm(X[:, 11:13].mean(1) - gt[:, 11:13].mean(1), axis=-1)
    assert np.median(root_err) < 1.5, np.median(root_err)
    assert np.percentile(root_err, 95) < 2.5, np.percentile(root_err, 95)
    cam_dist = np.linalg.norm(X.mean(1) - T_wc[:, :3, 3], axis=-1)
    assert cam_dist.min() > 0.5 * dist and cam_dist.max() < 1.5 * dist
    assert w_mpjpe_mm(X, gt, joints=range(5, 17)) < 1500.0  # old: 9402
    assert pa_mpjpe_mm(X, gt, joints=range(5, 17)) < 150.0  # old: 200
    # upright, and the body's size within 20 % of the truth (the metric scale: size prior + parallax)
    assert np.median(X[:, 0, 2] - X[:, 15:17, 2].mean(-1)) < -1.0
    size = lambda Y: np.median(np.sqrt(((Y - Y.mean(1, keepdims=True)) ** 2).sum(-1).mean(-1)))  # noqa: E731
    assert 0.8 < size(X) / size(gt) < 1.2


def test_track_cleaning_keeps_a_small_noisy_person():
    """A person 25 px in RMS radius with 5 px noise: the noise-aware threshold flags about the gross outliers,
    not most keypoints (the size-relative threshold alone flags the majority)."""
    rng = np.random.default_rng(0)
    T, J = 120, 17
    base = rng.normal(0, 25.0, (1, 2, J))
    t = np.arange(T)[:, None, None]
    W = base + 3.0 * np.sin(0.2 * t + np.arange(J)) + 300.0 + rng.normal(0, 5.0, (T, 2, J))
    out = rng.random((T, J)) < 0.05
    W[:, 0][out] += rng.choice([-1, 1], out.sum()) * rng.uniform(40, 80, out.sum())
    conf = np.ones((T, J))
    old = temporal_outlier_mask(W, conf, noise_mult=0.0)
    new = temporal_outlier_mask(W, conf)
    assert old.mean() > 0.4  # the defect
    assert new.mean() < 0.15
    assert new[out].mean() > 0.9  # the gross outliers are still caught
    assert 4.0 < track_noise_px(W, conf) < 12.0


def test_robust_depth_track_ignores_collapsed_frames():
    T = 60
    size_px = np.full(T, 25.0)
    size_px[10:14] = 1e-7  # a collapsed pose in a few frames (depth would be ~1e8 m)
    size_px[30] = 80.0  # one far too large
    n_obs = np.full(T, 15)
    n_obs[40:43] = 2  # hardly observed frames
    d = robust_depth_track(size_px, 0.4, np.full(T, 450.0), n_obs)
    np.testing.assert_allclose(d, 450.0 * 0.4 / 25.0, rtol=1e-9)
    with pytest.raises(SkycapError, match="usable pose size"):
        robust_depth_track(np.full(5, np.nan), 0.4, np.full(5, 450.0), np.full(5, 10))


def _orbit_scene(T=60, fps=8.0, radius_m=9.0, omega_rad_s=0.6):
    """A rigid adult-sized body standing still, seen from an orbiting perspective camera (noise-free)."""
    from reconstruction.synth import look_at_T_world_cam
    from skycap.frames import intrinsics_matrix

    t = np.arange(T) / fps
    X = np.repeat(UPRIGHT_BODY[None], T, 0) + np.array([1.0, -0.5, 0.0])
    centre = X.mean(1)
    ang = omega_rad_s * t
    cam = np.stack([centre[:, 0] + radius_m * np.cos(ang), centre[:, 1] + radius_m * np.sin(ang), np.full(T, -4.0)], -1)
    T_wc = look_at_T_world_cam(cam, centre)
    K = intrinsics_matrix(457.0, 457.0, 320.0, 180.0)
    Xc = np.einsum("tji,tkj->tki", T_wc[:, :3, :3], X - T_wc[:, None, :3, 3])
    uv = 457.0 * Xc[..., :2] / Xc[..., 2:3] + np.array([320.0, 180.0])
    return X, np.swapaxes(uv, 1, 2), T_wc, K, t


def test_perspective_ba_recovers_depth_from_a_start_on_the_wrong_depth():
    """Started with the whole body 40 % too far along the camera rays (and 30 % too large, so the image fits),
    the BA brings it back: the image size and the adult-size prior fix the depth. The old BA, without a
    cheirality term, could slide the roots onto the camera centres."""
    X, W, T_wc, K, t_s = _orbit_scene()
    p = T_wc[:, None, :3, 3]
    X0 = p + 1.4 * (X - p)
    r_body = float(np.sqrt(np.mean(np.square([np.linalg.norm(X[0, a] - X[0, b]) for a, b in COCO17_LIMBS if min(a, b) >= 5]))))
    cfg = PerspectiveConfig(body_bone_rms_m=r_body, camera_sigma_deg=0.0, stages=2, iters_per_stage=100, bone_prior_sigma=0.0)
    r = perspective_bundle_adjust(W, np.ones(X.shape[:2]), T_wc, K, X0, COCO17_LIMBS, cfg=cfg, t_s=t_s)
    root_err = np.linalg.norm(r.X.mean(1) - X.mean(1), axis=-1)
    assert np.median(np.linalg.norm(X0.mean(1) - X.mean(1), axis=-1)) > 3.0
    assert np.median(root_err) < 0.15, np.median(root_err)
    assert abs(r.body_scale - 1.0) < 0.05
    assert r_body != ADULT_BONE_RMS_M


def test_perspective_ba_rejects_a_start_behind_the_camera():
    X, W, T_wc, K, t_s = _orbit_scene(T=12)
    p = T_wc[:, None, :3, 3]
    with pytest.raises(SkycapError, match="behind or within"):
        perspective_bundle_adjust(W, np.ones(X.shape[:2]), T_wc, K, p - 0.5 * (X - p), COCO17_LIMBS, t_s=t_s)
    with pytest.raises(SkycapError, match="strictly increasing"):
        perspective_bundle_adjust(W, np.ones(X.shape[:2]), T_wc, K, X, COCO17_LIMBS, t_s=t_s[::-1].copy())
