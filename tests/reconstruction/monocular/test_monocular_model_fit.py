"""The body model fitted after the perspective BA (reconstruction.monocular.pipeline.model_fit), and the fit's
explicit start (reconstruction.multiview.fit.fit_capture(init_joints_ned=...))."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from reconstruction.body.model import SkeletonBodyModel
from reconstruction.capture import Capture
from reconstruction.metrics import pa_mpjpe_mm
from reconstruction.monocular.pipeline import ModelFitConfig, model_fit
from reconstruction.multiview.fit import FitConfig, fit_capture

from body_fixture import orbit_view


def _scene(T=48, fps=24.0, omega_deg_s=30.0):
    """A skeleton-model body walking and swinging its limbs, seen by one orbiting camera (noise-free)."""
    model = SkeletonBodyModel()
    t = np.arange(T) / fps
    pose = np.zeros((T, model.num_pose, 3))
    swing = 0.5 * np.sin(2 * np.pi * 1.0 * t)
    pose[:, 0, 0], pose[:, 2, 0] = swing, -swing  # hips (x = left: flexion)
    pose[:, 1, 0], pose[:, 3, 0] = 0.3 + 0.3 * swing, 0.3 - 0.3 * swing  # knees
    pose[:, 6, 2], pose[:, 8, 2] = -1.2, 1.2  # arms down
    pose[:, 7, 1], pose[:, 9, 1] = 0.6 + 0.4 * swing, -0.6 + 0.4 * swing  # elbows
    # body frame (x left, y up, z forward) -> NED standing upright, facing north
    R0 = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    yaw = Rotation.from_euler("z", 0.4 * t[:, None])
    ro = (yaw * Rotation.from_matrix(R0)).as_rotvec()
    tr = np.stack([0.8 * t, 0.2 * t, np.full(T, -0.95)], -1)
    with torch.no_grad():
        X = model(torch.tensor(ro), torch.tensor(pose), torch.tensor(tr), model.mean_shape()).numpy()
    W, T_wc, K = orbit_view(X, t, omega_deg_s)
    t_ns = np.round(t * 1e9).astype(np.int64)
    return X, W, T_wc, K, t_ns


def test_model_fit_refines_a_rough_start_towards_the_truth():
    X, W, T_wc, K, t_ns = _scene()
    rng = np.random.default_rng(0)
    X0 = X + rng.normal(0, 0.04, X.shape) + np.array([0.1, -0.1, 0.05])  # a rough monocular result: jitter, offset
    conf = np.ones(X.shape[:2])
    cfg = ModelFitConfig(fit=FitConfig(w_pose_prior=0.5, iters=300, refine_cameras=False, expected_noise_px=2.0))
    res = model_fit(W, conf, T_wc, K, t_ns, X0, cfg)
    assert res.joints_ned.shape == X.shape and np.all(np.isfinite(res.joints_ned))
    assert set(res.params()) == {"root_orient", "pose", "transl", "shape"}
    pa0, pa = pa_mpjpe_mm(X0, X), pa_mpjpe_mm(res.joints_ned, X)
    assert pa0 > 40.0
    assert pa < 0.6 * pa0, (pa0, pa)
    # the fitted body reprojects onto the keypoints (one camera: depth is the prior's and the start's)
    Xc = np.einsum("tji,tkj->tki", T_wc[:, :3, :3], res.joints_ned - T_wc[:, None, :3, 3])
    uv = 1500.0 * Xc[..., :2] / Xc[..., 2:3] + np.array([960.0, 540.0])
    assert np.median(np.linalg.norm(uv - np.swapaxes(W, 1, 2), axis=-1)) < 5.0


def test_fit_capture_refuses_a_start_of_the_wrong_shape_or_with_nan():
    X, W, T_wc, K, t_ns = _scene(T=12)
    from reconstruction.capture import CameraCapture

    cam = CameraCapture(name="c", t_pose_ns=t_ns, T_world_cam=T_wc, pos_sigma_m=np.full(12, 0.5), rot_sigma_deg=np.full(12, 2.0),
                        t_intrinsics_ns=t_ns[:1], K=K[None], width_px=1920, height_px=1080, t_frame_ns=t_ns,
                        keypoints_px=np.swapaxes(W, 1, 2), confidence=np.ones((12, 17)))  # fmt: skip
    cap = Capture([cam])
    with pytest.raises(ValueError, match=r"shape \(12, 17, 3\)"):
        fit_capture(cap, t_ns, FitConfig(iters=2), progress=False, init_joints_ned=X[:5])
    bad = X.copy()
    bad[3, 4] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        fit_capture(cap, t_ns, FitConfig(iters=2), progress=False, init_joints_ned=bad)


def test_lbfgs_polish_lowers_the_energy_adam_leaves():
    """Adam stops short of the minimum; the L-BFGS polish goes on from there: lower final energy, still the truth."""
    import dataclasses

    X, W, T_wc, K, t_ns = _scene(T=24)
    rng = np.random.default_rng(1)
    X0 = X + rng.normal(0, 0.04, X.shape)
    conf = np.ones(X.shape[:2])
    base = FitConfig(w_pose_prior=0.5, iters=60, refine_cameras=False, expected_noise_px=2.0)
    adam = model_fit(W, conf, T_wc, K, t_ns, X0, ModelFitConfig(fit=base))
    polished = model_fit(W, conf, T_wc, K, t_ns, X0, ModelFitConfig(fit=dataclasses.replace(base, polish_iters=200)))
    assert np.isfinite(adam.energy) and np.isfinite(polished.energy)
    assert polished.energy < adam.energy - 0.01 * abs(adam.energy), (adam.energy, polished.energy)
    assert pa_mpjpe_mm(polished.joints_ned, X) < pa_mpjpe_mm(X0, X)


def test_lbfgs_polish_converges_on_a_quadratic_and_undoes_a_bad_chunk():
    from reconstruction.multiview.fit import lbfgs_polish

    x = torch.tensor([3.0, -2.0], requires_grad=True)
    A = torch.tensor([[4.0, 1.0], [1.0, 2.0]])
    b = torch.tensor([1.0, 1.0])
    E = lbfgs_polish(lambda: 0.5 * x @ A @ x - b @ x, [x], iters=100)
    np.testing.assert_allclose(x.detach().numpy(), np.linalg.solve(A.numpy(), b.numpy()), atol=1e-4)
    assert abs(E - float(-0.5 * b @ torch.linalg.solve(A, b))) < 1e-5
    # an energy that is NaN below y = 0.5 while its minimum lies at 0: a chunk that ends in NaN is undone
    y = torch.tensor([1.0], requires_grad=True)
    E = lbfgs_polish(lambda: (y**2 * torch.where(y > 0.5, 1.0, float("nan"))).sum(), [y], iters=50)
    assert torch.isfinite(y).all() and np.isfinite(E) and y.item() > 0.5
