"""Synthetic flights for the offline smoother tests: a person walking a random path (with stops), drones
circling them with slowly drifting GPS offsets, boxes with pixel noise, converted by the onboard geometry."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from onboard.tracking.measurement import box_from_person, measurement_from_box
from skycap.camera import PinholeCamera
from skycap.frames import R_world_body_from_euler, T_world_cam_from_pose

CAM = PinholeCamera(fx_px=900.0, fy_px=900.0, cx_px=640.0, cy_px=360.0, width_px=1280, height_px=720)
PERSON_H = 1.69
CENTER_DOWN = -PERSON_H / 2


def look_at_pose(cam_ned: np.ndarray, target_ned: np.ndarray) -> np.ndarray:
    """T_world_cam of a gimballed camera at cam_ned looking at target_ned (zero roll)."""
    d = np.asarray(target_ned, float) - np.asarray(cam_ned, float)
    yaw = math.atan2(d[1], d[0])
    pitch = -math.atan2(d[2], math.hypot(d[0], d[1]))
    return T_world_cam_from_pose(cam_ned, R_world_body_from_euler(0.0, 0.0, yaw), gimbal_pitch_rad=pitch)


@dataclasses.dataclass
class Scene:
    t_s: np.ndarray  # (T,) truth sample times
    person: np.ndarray  # (T, 3) true person centre
    drones: np.ndarray  # (T, D, 3) true drone positions
    bias: np.ndarray  # (T, D, 3) reported - true
    measurements: list  # PositionMeasurement, time-ordered
    frames: list  # per detection: dict(t_ns, drone, box (4,) noisy, box_true (4,), T_reported (4, 4), cov (6, 6))

    def at(self, t_s: np.ndarray, rows: np.ndarray) -> np.ndarray:
        return np.stack([np.interp(t_s, self.t_s, rows[:, i]) for i in range(rows.shape[1])], -1)


def make_scene(seed: int = 0, duration_s: float = 40.0, n_drones: int = 3, rate_hz: float = 10.0, px_sigma: float = 2.0,
               bias_sigma_m=(1.0, 1.0, 0.5), bias_tau_s: float = 60.0, dt_s: float = 0.01) -> Scene:
    rng = np.random.default_rng(seed)
    T = int(duration_s / dt_s) + 1
    t = np.arange(T) * dt_s
    # person: OU velocity (tau 3 s, ~1 m/s) with a stop in the middle
    v = np.zeros((T, 2))
    for k in range(1, T):
        v[k] = v[k - 1] * math.exp(-dt_s / 3.0) + math.sqrt(2 * 1.0**2 / 3.0 * dt_s) * rng.standard_normal(2)
    stop = (t > 0.4 * duration_s) & (t < 0.55 * duration_s)
    v[stop] = 0.0
    xy = np.cumsum(v * dt_s, axis=0)
    person = np.c_[xy, np.full(T, CENTER_DOWN)]
    # drones: circle the person at 8 m, 6 m up, slowly rotating formation
    drones = np.zeros((T, n_drones, 3))
    for d in range(n_drones):
        a = 2 * math.pi * d / n_drones + 0.1 * t
        drones[:, d, 0] = person[:, 0] + 8.0 * np.cos(a)
        drones[:, d, 1] = person[:, 1] + 8.0 * np.sin(a)
        drones[:, d, 2] = -6.0
    # GPS offsets: Gauss-Markov from the stationary distribution
    sig = np.asarray(bias_sigma_m, float)
    bias = np.zeros((T, n_drones, 3))
    bias[0] = sig * rng.standard_normal((n_drones, 3))
    e = math.exp(-dt_s / bias_tau_s)
    for k in range(1, T):
        bias[k] = e * bias[k - 1] + sig * math.sqrt(1 - e * e) * rng.standard_normal((n_drones, 3))
    meas, frames = [], []
    period = 1.0 / rate_hz
    for d in range(n_drones):
        tk = 0.05 + d * period / n_drones
        while tk < duration_s - 0.05:
            k = int(round(tk / dt_s))
            T_true = look_at_pose(drones[k, d], person[k])
            box_true, _ = box_from_person(person[k], CAM, T_true, PERSON_H)
            box = box_true + rng.normal(0, px_sigma, 4)
            T_rep = T_true.copy()
            T_rep[:3, 3] += bias[k, d]
            cov = np.diag([sig[0] ** 2, sig[1] ** 2, sig[2] ** 2, 1e-5, 1e-5, 1e-5])
            meas.append(measurement_from_box(box, CAM, T_rep, cov, t_ns=int(round(t[k] * 1e9)), source_id=f"drone_{d}",
                                             edge_var_px2=np.full(4, px_sigma**2)))  # fmt: skip
            frames.append(dict(t_ns=int(round(t[k] * 1e9)), drone=d, box=box, box_true=box_true, T_reported=T_rep, cov=cov))
            tk += period
    meas.sort(key=lambda m: m.t_ns)
    frames.sort(key=lambda f: f["t_ns"])
    return Scene(t, person, drones, bias, meas, frames)
