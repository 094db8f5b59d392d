"""Body model forward/gradients, skeleton IK/FK, the learned pose prior, and the shared metrics."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from reconstruction.body import skeleton17 as sk
from reconstruction.body.model import SkeletonBodyModel
from reconstruction.metrics import pa_mpjpe_mm, similarity_procrustes, w_mpjpe_mm
from reconstruction.prior import PosePrior, load_default_prior
from reconstruction.synth import procedural_walker


def test_model_forward_matches_walker_and_is_batched():
    J, _, shape, pose, ro, tr = procedural_walker(6)
    m = SkeletonBodyModel()
    out = m(torch.tensor(ro), torch.tensor(pose), torch.tensor(tr), torch.tensor(shape))
    assert out.shape == (6, 17, 3)
    np.testing.assert_allclose(out.numpy(), J, atol=1e-9)
    # limb lengths are the shape's
    assert np.allclose(np.linalg.norm(J[:, 13] - J[:, 15], axis=-1), shape[2])
    # left is left: facing north, the left hip is west (negative east)
    assert np.all(J[:, 11, 1] < J[:, 12, 1])


def test_model_gradients_match_finite_differences():
    torch.manual_seed(0)
    m = SkeletonBodyModel()
    ro = (torch.randn(2, 3) * 0.5).double().requires_grad_()
    pose = (torch.randn(2, sk.NUM_POSE, 3) * 0.3).double().requires_grad_()
    tr = torch.randn(2, 3).double().requires_grad_()
    shape = torch.tensor(sk.DEFAULT_SHAPE).requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b, c, d: m(a, b, c, d), (ro, pose, tr, shape), eps=1e-6, atol=1e-5)
    # zero-rotation gradient is finite (Rodrigues is smooth at 0)
    z = torch.zeros(1, 3, dtype=torch.float64, requires_grad=True)
    m(z, torch.zeros(1, sk.NUM_POSE, 3, dtype=torch.float64), torch.zeros(1, 3, dtype=torch.float64), torch.tensor(sk.DEFAULT_SHAPE)).sum().backward()
    assert torch.all(torch.isfinite(z.grad))


def test_inverse_kinematics_recovers_rigid_skeleton():
    rng = np.random.default_rng(3)
    shape = sk.DEFAULT_SHAPE * rng.uniform(0.9, 1.1, sk.NUM_SHAPE)
    shape[4] = 0.0  # spine_z: estimate_shape measures the trunk along the spine
    R_root = Rotation.random(5, random_state=1).as_matrix()
    R_loc = Rotation.from_rotvec(rng.normal(0, 0.5, (5 * sk.NUM_POSE, 3))).as_matrix().reshape(5, sk.NUM_POSE, 3, 3)
    tr = rng.normal(size=(5, 3))
    J = sk.forward_kinematics_np(R_root, R_loc, tr, shape)[:, sk.COCO_TO_NODE]
    trunk_limbs = [0, 1, 2, 3, 4, 5, 6, 7]  # measured exactly; the face only approximately (head turns)
    np.testing.assert_allclose(sk.estimate_shape(J)[trunk_limbs], shape[trunk_limbs], atol=1e-9)
    R0, RL, t = sk.inverse_kinematics(J, shape)
    back = sk.forward_kinematics_np(R0, RL, t, shape)[:, sk.COCO_TO_NODE]
    np.testing.assert_allclose(back, J, atol=1e-9)


def test_prior_scores_real_poses_above_random(cmu_dir):
    from reconstruction.prior.train_prior import HELD_OUT, poses_from_bvh

    prior = load_default_prior()
    assert isinstance(prior, PosePrior) and prior.dim == 3 * sk.NUM_POSE
    real = torch.tensor(poses_from_bvh(cmu_dir / "002" / f"{HELD_OUT[0]}.bvh", step=8), dtype=torch.float32)  # held out of training
    gen = torch.Generator().manual_seed(0)
    rnd = (torch.rand(len(real), sk.NUM_POSE, 3, generator=gen) * 2 - 1) * 1.2
    e_real, e_rnd = prior.energy(real), prior.energy(rnd)
    assert e_real.median() + 50 < e_rnd.median()
    assert (e_real[:, None] < e_rnd[None]).float().mean() > 0.95  # ranks real above random
    assert prior.limit_penalty(real).mean() < 0.01 < prior.limit_penalty(rnd).mean()
    # differentiable
    p = real[:3].clone().requires_grad_()
    prior.energy(p).sum().backward()
    assert torch.all(torch.isfinite(p.grad))


def test_prior_weights_are_small_and_credited():
    from reconstruction.prior.gmm import DEFAULT_PRIOR_PATH

    assert DEFAULT_PRIOR_PATH.stat().st_size < 5e6
    z = np.load(DEFAULT_PRIOR_PATH)
    assert "mocap.cs.cmu.edu" in str(z["credit"])
    assert not set(z["held_out"].tolist()) & set(z["train_files"].tolist())


def test_metrics_hand_computed():
    gt = np.zeros((1, 3, 3))
    gt[0, 1] = [1.0, 0, 0]
    gt[0, 2] = [0, 1.0, 0]
    pred = gt.copy()
    pred[0, :, 2] += 0.003  # every joint 3 mm off along z
    pred[0, 0, 0] += 0.004  # joint 0: (4, 0, 3) mm -> 5 mm
    assert w_mpjpe_mm(pred, gt) == pytest.approx((5 + 3 + 3) / 3)
    assert w_mpjpe_mm(pred, gt, joints=[1, 2]) == pytest.approx(3.0)
    # a similarity transform (scale 2, 90 deg about z, shift) is removed exactly by PA
    R = np.array([[0, -1.0, 0], [1.0, 0, 0], [0, 0, 1.0]])
    X = np.random.default_rng(0).normal(size=(4, 6, 3))
    Y = 2.0 * X @ R.T + np.array([1.0, -2.0, 0.5])
    assert pa_mpjpe_mm(Y, X) == pytest.approx(0.0, abs=1e-9)
    assert w_mpjpe_mm(Y, X) > 100
    s, R_est, t = similarity_procrustes(X[0], Y[0])
    assert s == pytest.approx(2.0) and np.allclose(R_est, R) and np.allclose(t, [1.0, -2.0, 0.5])
    # hand case: points (-1,0,0),(1,0,0) vs (-2,1,0),(2,1,0): scale 2, shift (0,1,0), PA error 0
    assert pa_mpjpe_mm(np.array([[[-1.0, 0, 0], [1.0, 0, 0]]]), np.array([[[-2.0, 1, 0], [2.0, 1, 0]]])) == pytest.approx(0, abs=1e-9)
    # non-similar residual: after alignment, symmetric +-1 mm perturbations remain 1 mm
    A = np.array([[[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]]])
    B = A.copy()
    B[0, :, 2] = np.array([1, -1, -1, 1]) * 1e-3
    assert pa_mpjpe_mm(A, B) == pytest.approx(1.0, rel=1e-6)
