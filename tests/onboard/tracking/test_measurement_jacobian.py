"""The box measurement models' closed-form Jacobians equal central differences of the models themselves, on random
cameras (position, yaw, pitch, roll), persons and boxes; and measurement_from_box's covariances equal those built
from numeric Jacobians (the former implementation) in every mode."""

from __future__ import annotations

import math

import numpy as np
import pytest

import onboard.tracking.measurement as M
from skycap.camera import PinholeCamera
from skycap.frames import R_world_body_from_euler, T_world_cam_from_pose

CAM = PinholeCamera(fx_px=640.0, fy_px=640.0, cx_px=320.0, cy_px=180.0, width_px=640, height_px=360)
K_INV = np.linalg.inv(CAM.K)
PARALLAX = math.radians(10.0)


def _cases(n: int, seed: int = 0):
    """n random (edges, H, c, R, ground_down_m) where the height prior is well defined."""
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < n:
        ground = rng.uniform(-1.0, 1.0)
        person = np.array([rng.uniform(-10, 10), rng.uniform(-10, 10), ground - 0.85])
        a, dist = rng.uniform(0, 2 * math.pi), rng.uniform(4.0, 25.0)
        c = person + np.array([dist * math.cos(a), dist * math.sin(a), -rng.uniform(1.0, 15.0)])
        d = person - c
        yaw = math.atan2(d[1], d[0]) + rng.normal(0, 0.2)
        pitch = -math.atan2(d[2], math.hypot(d[0], d[1])) + rng.normal(0, 0.1)
        T = T_world_cam_from_pose(c, R_world_body_from_euler(rng.normal(0, 0.1), 0.0, yaw), gimbal_pitch_rad=pitch)
        box, _ = M.box_from_person(person, CAM, T)
        edges = box + rng.normal(0, 3.0, 4)
        H = rng.uniform(1.5, 1.9)
        try:
            M._height_prior_point(edges, H, c, T[:3, :3], K_INV, PARALLAX)
            M._ground_point(edges, H, 0.0, c, T[:3, :3], K_INV, ground)
        except M.MeasurementError:
            continue
        out.append((edges, H, c, T[:3, :3].copy(), ground, T))
    return out


CASES = _cases(40)
#: central-difference steps per input (px, m, m, rad, m), halved once for Richardson extrapolation (error O(h^4))
STEPS = np.array([1e-2] * 4 + [1e-3] + [1e-3] * 3 + [1e-5] * 3 + [1e-3])


def _numeric(f, x0: np.ndarray) -> np.ndarray:
    """(3, 12) Richardson-extrapolated central differences of f(x (12,)) at x0."""
    J = np.zeros((3, 12))
    for i in range(12):
        def cd(h):
            d = np.zeros(12)
            d[i] = h
            return (f(x0 + d) - f(x0 - d)) / (2 * h)
        J[:, i] = (4 * cd(STEPS[i] / 2) - cd(STEPS[i])) / 3
    return J


def _x0(edges, H):
    return np.concatenate([edges, [H], np.zeros(7)])


def _rel(Ja: np.ndarray, Jn: np.ndarray) -> float:
    """Largest difference relative to each column's size (columns that are zero must stay zero)."""
    scale = np.maximum(np.abs(Jn).max(axis=0), 1e-12)
    return float(np.max(np.abs(Ja - Jn) / scale))


def _rotated(R, x):
    return M._rotvec_matrix(x[8:11]) @ R


@pytest.mark.parametrize("model", ["height_prior", "ground", "bearing"])
def test_closed_form_jacobians_equal_central_differences(model):
    worst = 0.0
    for edges, H, c, R, ground, _ in CASES:
        if model == "height_prior":
            p, Ja = M._height_prior_point_jac(edges, H, c, R, K_INV, PARALLAX)
            f = lambda x: M._height_prior_point(x[:4], x[4], c + x[5:8], _rotated(R, x), K_INV, PARALLAX)  # noqa: E731
        elif model == "ground":
            p, Ja = M._ground_point_jac(edges, H, 0.0, c, R, K_INV, ground)
            f = lambda x: M._ground_point(x[:4], x[4], x[11], c + x[5:8], _rotated(R, x), K_INV, ground)  # noqa: E731
        else:
            p, Ja = M._bearing_point_jac(edges, c, R, K_INV, 11.0)
            f = lambda x: M._bearing_point(x[:4], c + x[5:8], _rotated(R, x), K_INV, 11.0)  # noqa: E731
        x0 = _x0(edges, H)
        np.testing.assert_allclose(p, f(x0), rtol=0, atol=1e-12)
        worst = max(worst, _rel(Ja, _numeric(f, x0)))
    assert worst < 1e-6, worst


def _numeric_cov(mode, edges, H, c0, R0, ground, pose_cov, ev, cfg):
    """measurement_from_box's covariances as the former implementation built them: numeric Jacobians of the model
    (for the fused mode, of the fused model with weights from the numeric Jacobians of its two parts)."""
    hp = lambda x: M._height_prior_point(x[:4], x[4], c0 + x[5:8], _rotated(R0, x), K_INV, PARALLAX)  # noqa: E731
    gp = lambda x: M._ground_point(x[:4], x[4], x[11], c0 + x[5:8], _rotated(R0, x), K_INV, ground)  # noqa: E731
    x0 = _x0(edges, H)
    if mode == "height_prior":
        J = _numeric(hp, x0)
    elif mode == "bearing":
        J = _numeric(gp, x0)
        J[:, 4] = 0.0
    else:
        Jh, Jg = _numeric(hp, x0), _numeric(gp, x0)
        C_h = Jh[:, :5] @ np.diag([*ev, cfg.person_height_sigma_m**2]) @ Jh[:, :5].T
        Jge = Jg[:, [0, 1, 2, 3, 11]]
        C_g = Jge @ np.diag([*ev, cfg.ground_sigma_m**2]) @ Jge.T + M._unmodelled_camera_cov(Jg[:, 5:8], pose_cov)
        C_g = C_g + np.diag([0.0, 0.0, (0.5 * cfg.person_height_sigma_m) ** 2])
        I_h, I_g = np.linalg.inv(C_h + 1e-6 * np.eye(3)), np.linalg.inv(C_g + 1e-6 * np.eye(3))
        C_f = np.linalg.inv(I_h + I_g)
        J = _numeric(lambda x: C_f @ I_h @ hp(x) + C_f @ I_g @ gp(x), x0)
    S = np.zeros((12, 12))
    S[:4, :4] = np.diag(ev)
    S[4, 4] = cfg.person_height_sigma_m**2
    S[5:11, 5:11] = pose_cov
    S[11, 11] = cfg.ground_sigma_m**2
    S_nc = S.copy()
    S_nc[5:8, :] = S_nc[:, 5:8] = 0.0
    return J @ S @ J.T, J @ S_nc @ J.T + M._unmodelled_camera_cov(J[:, 5:8], pose_cov)


@pytest.mark.parametrize("mode", ["height_prior", "height_and_ground", "bearing"])
def test_measurement_covariances_equal_the_numeric_ones(mode):
    rng = np.random.default_rng(1)
    cfg = M.MeasurementConfig(person_height_m=1.69)
    for edges, _, c, R, ground, T in CASES[:15]:
        A = rng.normal(size=(6, 6))
        pose_cov = 1e-2 * A @ A.T * np.outer(np.r_[[1.0] * 3, [0.01] * 3], np.r_[[1.0] * 3, [0.01] * 3])
        pose_cov = 0.5 * (pose_cov + pose_cov.T) + np.diag([0.04] * 3 + [3e-4] * 3)
        ev = rng.uniform(4.0, 30.0, 4)
        m = M.measurement_from_box(edges, CAM, T, pose_cov, mode=mode, ground_down_m=ground, edge_var_px2=ev, config=cfg)
        assert m.mode == mode
        cov, cov_nc = _numeric_cov(mode, edges, cfg.person_height_m, c, R, ground, pose_cov, ev, cfg)
        if mode == "bearing":
            r = (m.position_ned_m - c) / np.linalg.norm(m.position_ned_m - c)
            cov = cov + cfg.bearing_range_sigma_m**2 * np.outer(r, r)
            cov_nc = cov_nc + cfg.bearing_range_sigma_m**2 * np.outer(r, r)
        for got, want in ((m.cov_m2, cov), (m.cov_no_cam_position_m2, cov_nc)):
            np.testing.assert_allclose(got, 0.5 * (want + want.T), rtol=1e-6, atol=1e-9 * np.abs(want).max())
