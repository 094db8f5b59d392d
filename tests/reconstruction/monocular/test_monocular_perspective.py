"""The perspective bundle adjustment with known camera poses (reconstruction.monocular.perspective)."""

from __future__ import annotations

import numpy as np
import pytest

from reconstruction.monocular.linalg import complete_rotation
from reconstruction.monocular.perspective import (
    ADULT_BONES_M,
    PerspectiveConfig,
    bone_lengths,
    orthographic_to_world,
    perspective_bundle_adjust,
)
from skycap.errors import SkycapError
from skycap.skeleton import COCO17_LIMBS

from body_fixture import UPRIGHT_BODY, orbit_view



def _scene(T=48, fps=24.0, omega_deg_s=30.0, yaw_rate_deg_s=20.0):
    """A rigid body walking in a straight line while turning, seen by an orbiting camera (noise-free)."""
    t = np.arange(T) / fps
    yaw = np.radians(yaw_rate_deg_s) * t
    c, s = np.cos(yaw), np.sin(yaw)
    Rz = np.zeros((T, 3, 3))
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -s, s, c, 1.0
    root = np.stack([0.8 * t, 0.2 * t, np.zeros(T)], -1)
    X = np.einsum("tij,kj->tki", Rz, UPRIGHT_BODY) + root[:, None]
    W, T_wc, K = orbit_view(X, t, omega_deg_s)
    return X, W, T_wc, K


def _body_bone_rms() -> float:
    """RMS of UPRIGHT_BODY's limb/torso bone lengths (the perspective BA's size reference)."""
    return float(np.sqrt(np.mean(np.square([np.linalg.norm(UPRIGHT_BODY[a] - UPRIGHT_BODY[b]) for a, b in COCO17_LIMBS if min(a, b) >= 5]))))


def _cfg(**kw):  # noqa: D103
    r = float(np.sqrt(np.mean(np.sum((UPRIGHT_BODY - UPRIGHT_BODY.mean(0)) ** 2, -1))))
    # exact cameras; the size and proportions priors are this body's (as if measured: they differ from the adult's)
    bones = tuple(float(np.linalg.norm(UPRIGHT_BODY[a] - UPRIGHT_BODY[b])) for a, b in ADULT_BONES_M)
    base = dict(body_rms_radius_m=r, body_bone_rms_m=_body_bone_rms(), bone_prior_m=bones, stages=2, iters_per_stage=150,
                camera_sigma_deg=0.0)  # fmt: skip
    base.update(kw)
    return PerspectiveConfig(**base)


def test_recovers_known_world_pose_from_noise_free_projections():
    X, W, T_wc, K = _scene()
    rng = np.random.default_rng(0)
    X0 = X + rng.normal(0, 0.03, X.shape) + np.array([0.15, -0.1, 0.05])  # jittered joints, offset body
    r = perspective_bundle_adjust(W, np.ones(X.shape[:2]), T_wc, K, X0, COCO17_LIMBS, dt_s=1 / 24, cfg=_cfg())
    err_mm = 1000 * np.linalg.norm(r.X - X, axis=-1)
    err0_mm = 1000 * np.linalg.norm(X0 - X, axis=-1)
    assert err0_mm.mean() > 100.0
    assert err_mm.mean() < 10.0, err_mm.mean()  # world frame, no alignment (converges slowly in depth)
    # limb and torso bones within 1 cm (the tiny face bones, ears/eyes, are the least constrained in depth)
    body = [i for i, (a, b) in enumerate(COCO17_LIMBS) if min(a, b) >= 5]
    got = np.median(bone_lengths(r.X, COCO17_LIMBS), 0)[body]
    np.testing.assert_allclose(got, bone_lengths(X[:1], COCO17_LIMBS)[0][body], atol=0.01)


def test_objective_decreases_and_robust_to_outliers():
    X, W, T_wc, K = _scene(T=40)
    rng = np.random.default_rng(1)
    W = W + rng.normal(0, 2.0, W.shape)
    out = rng.random((W.shape[0], W.shape[2])) < 0.1
    W[:, 0][out] += rng.uniform(-200, 200, out.sum())
    W[:, 1][out] += rng.uniform(-200, 200, out.sum())
    X0 = X + rng.normal(0, 0.05, X.shape)
    r = perspective_bundle_adjust(W, np.ones(X.shape[:2]), T_wc, K, X0, COCO17_LIMBS, dt_s=1 / 24, cfg=_cfg())
    f0, f1 = r.objective_final_sigma
    assert f1 < 0.5 * f0
    assert np.all(np.diff(r.objective[1:]) < np.inf)  # finite history
    assert 1000 * np.linalg.norm(r.X - X, axis=-1).mean() < 30.0  # 10 % gross outliers are ignored


def test_orthographic_to_world_places_an_exact_orthographic_pose():
    """A pose given in orthographic camera form (R = camera rows, S = camera-axes pose in pixels) goes back
    to the world where it was, given its true size."""
    X, W, T_wc, K = _scene(T=12, yaw_rate_deg_s=0.0)
    R_cw = np.swapaxes(T_wc[:, :3, :3], 1, 2)
    d = np.linalg.norm(X.mean(1) - T_wc[:, :3, 3], axis=-1)
    S_cam = np.einsum("tij,tkj->tik", R_cw, X - X.mean(1, keepdims=True)) * 1500.0 / d[:, None, None]  # (T,3,J) px
    R = np.tile(np.eye(3)[:2], (len(X), 1, 1))
    assert np.allclose(complete_rotation(R), np.eye(3))
    r0 = float(np.sqrt(np.mean(np.sum((UPRIGHT_BODY - UPRIGHT_BODY.mean(0)) ** 2, -1))))
    Xw = orthographic_to_world(S_cam, R, W, np.ones(X.shape[:2]), T_wc, K, r0)
    # same shape exactly; the centre is on the 2D-centroid ray (perspective: a few cm off the 3D centroid)
    assert np.abs((Xw - Xw.mean(1, keepdims=True)) - (X - X.mean(1, keepdims=True))).max() < 1e-9
    assert np.linalg.norm(Xw.mean(1) - X.mean(1), axis=-1).max() < 0.1


def test_rejects_bad_shapes():
    X, W, T_wc, K = _scene(T=10)
    with pytest.raises(SkycapError, match="X0 must be"):
        perspective_bundle_adjust(W, np.ones(X.shape[:2]), T_wc, K, X[:5], COCO17_LIMBS)
    X0 = X.copy()
    X0[0, 0, 0] = np.nan
    with pytest.raises(SkycapError, match="NaN"):
        perspective_bundle_adjust(W, np.ones(X.shape[:2]), T_wc, K, X0, COCO17_LIMBS)
