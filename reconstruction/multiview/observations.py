"""Observations of a capture arranged for fitting, and robust triangulation for the initial guess.

* :func:`gather` flattens all cameras' frames into arrays (N frames in all, camera-major, time-sorted
  per camera) with each frame's drone pose, intrinsics, and its place on the output time grid
  (``k`` lower grid index and ``alpha`` in [0, 1]: frame time = (1 - alpha) t_k + alpha t_{k+1}).
* :func:`interpolate_to_grid` resamples each camera's keypoints to the grid times (linear between the
  two neighbouring frames; missing if either is missing or the gap is too long).
* :func:`smooth_poses` — the drone pose tracks smoothed in time (Savitzky-Golay), the
  starting guess for the cameras; :func:`camera_track` fuses the pose samples with the drone's
  velocity and angular velocity instead when the capture has them (:func:`fuse_rates`).
* :func:`triangulate` — confidence-weighted DLT per joint and time, refined by iteratively reweighted
  least squares with Geman-McClure weights (outliers and swapped views lose their weight).
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np

from scipy.ndimage import median_filter
from scipy.signal import savgol_filter
from scipy.spatial.transform import Rotation

from reconstruction.capture import CameraCapture, Capture, CaptureError, interpolate_poses
from skycap.frames import invert_T, make_T


def smooth_poses(t_ns: np.ndarray, T: np.ndarray, window_s: float = 2.0, order: int = 2) -> np.ndarray:
    """Savitzky-Golay smoothing (polynomial ``order``) of a pose track (P, 4, 4) in time: positions and
    (sign-continuous) quaternions; a polynomial trajectory of that order passes unchanged. Returns (P, 4, 4)."""
    P = len(t_ns)
    if P < 5:
        return T.copy()
    dt = float(np.median(np.diff(t_ns))) * 1e-9
    win = int(round(window_s / max(dt, 1e-6))) | 1
    win = min(win, P if P % 2 else P - 1)
    if win < max(5, order + 2):
        return T.copy()
    pos = savgol_filter(T[:, :3, 3], win, order, axis=0, mode="interp")
    q = Rotation.from_matrix(T[:, :3, :3]).as_quat()
    for i in range(1, P):
        if np.dot(q[i], q[i - 1]) < 0:
            q[i] = -q[i]
    q = savgol_filter(q, win, order, axis=0, mode="interp")
    return make_T(Rotation.from_quat(q / np.linalg.norm(q, axis=-1, keepdims=True)).as_matrix(), pos)


def fuse_rates(
    t_ns: np.ndarray,
    T: np.ndarray,
    pos_sigma_m: np.ndarray,
    rot_sigma_rad: np.ndarray,
    vel_world_mps: np.ndarray | None,
    vel_sigma_mps: np.ndarray | None,
    omega_cam_radps: np.ndarray | None,
    omega_sigma_radps: np.ndarray | None,
    T_start: np.ndarray | None = None,
    gn_steps: int = 2,
) -> np.ndarray:
    """The pose track (P, 4, 4) that best explains noisy pose samples together with velocity and
    angular-velocity samples (sparse least squares over all P samples at once; a smoother, not a filter).

    Positions: min sum |p_k - p~_k|^2 / s_p^2 + sum |p_{k+1} - p_k - dt (v_k + v_{k+1}) / 2|^2 / (dt^2 s_v^2 / 2).
    Rotations (Gauss-Newton on world-frame corrections d_k, R_k = exp(d_k) R0_k, from ``T_start`` or
    the samples): min sum |log(R_k R~_k^T)|^2 / s_r^2 + sum |log(exp(-(w_k - b) dt) R_k^T R_{k+1})|^2 /
    (dt^2 s_w^2) with one constant gyro bias ``b`` (weak prior) for the whole track. Sigmas are RMS 3D
    (per axis = /sqrt 3); a missing channel leaves that part of ``T_start`` as it is.
    """
    import scipy.sparse as sparse
    from scipy.sparse.linalg import spsolve

    P = len(t_ns)
    out = (T if T_start is None else T_start).copy()
    if P < 3:
        return out
    dt = np.diff(np.asarray(t_ns, dtype=np.int64)).astype(float) * 1e-9
    if vel_world_mps is not None:
        sp2 = (np.asarray(pos_sigma_m) / np.sqrt(3.0)) ** 2
        sv = np.asarray(vel_sigma_mps) / np.sqrt(3.0)
        wv = 1.0 / (dt**2 * 0.5 * (sv[:-1] ** 2 + sv[1:] ** 2) / 2.0)
        D = sparse.diags([-np.ones(P - 1), np.ones(P - 1)], [0, 1], shape=(P - 1, P))
        A = (sparse.diags(1.0 / sp2) + D.T @ sparse.diags(wv) @ D).tocsc()
        disp = dt[:, None] * 0.5 * (vel_world_mps[:-1] + vel_world_mps[1:])
        rhs = T[:, :3, 3] / sp2[:, None] + D.T @ (wv[:, None] * disp)
        out[:, :3, 3] = np.stack([spsolve(A, rhs[:, j]) for j in range(3)], axis=-1)
    if omega_cam_radps is not None:
        wr = 1.0 / (np.asarray(rot_sigma_rad) / np.sqrt(3.0)) ** 2  # (P,)
        sw = np.asarray(omega_sigma_radps)[:-1] / np.sqrt(3.0)
        ww = 1.0 / (dt * sw) ** 2  # (P-1,)
        wb = 1.0 / np.radians(0.1) ** 2  # gyro bias prior (deg/s scale)
        R_meas = Rotation.from_matrix(T[:, :3, :3])
        n = 3 * P + 3
        rows = np.arange(3 * (P - 1))
        for _ in range(gn_steps):
            R0 = Rotation.from_matrix(out[:, :3, :3])
            r_att = (R_meas * R0.inv()).as_rotvec()  # target of d_k (world frame)
            Q0 = R0[:-1].inv() * R0[1:]
            r_rate = (Rotation.from_rotvec(-omega_cam_radps[:-1] * dt[:, None]) * Q0).as_rotvec()  # at d = 0, b = 0
            Rb = R0[1:].as_matrix()  # d(res)/d(d_{k+1}) = R_{k+1}^T, d(res)/d(d_k) = -R_{k+1}^T, d(res)/db = dt
            RbT = np.transpose(Rb, (0, 2, 1))
            ii, jj, vv = [], [], []
            for a in range(3):
                for c in range(3):
                    ii += [rows[a::3], rows[a::3]]
                    jj += [3 * np.arange(1, P) + c, 3 * np.arange(0, P - 1) + c]
                    vv += [RbT[:, a, c], -RbT[:, a, c]]
                ii.append(rows[a::3]), jj.append(np.full(P - 1, 3 * P + a)), vv.append(dt)
            J = sparse.csr_matrix((np.concatenate(vv), (np.concatenate(ii), np.concatenate(jj))), shape=(3 * (P - 1), n))
            Wr = sparse.diags(np.repeat(ww, 3))
            H = J.T @ Wr @ J + sparse.diags(np.concatenate([np.repeat(wr, 3), np.full(3, wb)]))
            g = -(J.T @ (Wr @ r_rate.reshape(-1))) + np.concatenate([(wr[:, None] * r_att).reshape(-1), np.zeros(3)])
            x = spsolve(H.tocsc(), g)
            out[:, :3, :3] = (Rotation.from_rotvec(x[: 3 * P].reshape(P, 3)) * R0).as_matrix()
    return out


def camera_track(cam: CameraCapture, window_s: float = 2.0, order: int = 2) -> np.ndarray:
    """The camera's best pose track at its own pose samples (P, 4, 4) from the drone's data alone:
    Savitzky-Golay smoothing (:func:`smooth_poses`), then, when the capture carries the drone's velocity
    / angular velocity, the joint least-squares fit of samples and rates (:func:`fuse_rates`)."""
    T = smooth_poses(cam.t_pose_ns, cam.T_world_cam, window_s, order) if window_s > 0 else cam.T_world_cam.copy()
    if cam.has_velocity or cam.has_angular_velocity:
        T = fuse_rates(cam.t_pose_ns, cam.T_world_cam, cam.pos_sigma_m, np.radians(cam.rot_sigma_deg), cam.vel_world_mps,
                       cam.vel_sigma_mps, cam.omega_cam_radps, cam.omega_sigma_radps, T_start=T)  # fmt: skip
    return T


def smoothed_pose_at(cam: CameraCapture, t_ns: np.ndarray, window_s: float = 2.0, order: int = 2) -> np.ndarray:
    """The camera's drone-pose track smoothed in time (:func:`camera_track`) at times (Q,) -> (Q, 4, 4)."""
    return interpolate_poses(cam.t_pose_ns, camera_track(cam, window_s, order), t_ns)


@dataclasses.dataclass
class Observations:
    """All frames of all cameras. N frames, D detectors (max over cameras; missing = conf 0)."""

    cam: np.ndarray  # (N,) camera index
    t_ns: np.ndarray  # (N,)
    uv: np.ndarray  # (N, D, 17, 2)
    conf: np.ndarray  # (N, D, 17)
    K: np.ndarray  # (N, 3, 3)
    T_est: np.ndarray  # (N, 4, 4) drone-estimated T_world_cam at the frame time
    T_smooth: np.ndarray  # (N, 4, 4) the drone track smoothed in time, at the frame time (starting guess)
    pos_sigma_m: np.ndarray  # (N,)
    rot_sigma_rad: np.ndarray  # (N,)
    k: np.ndarray  # (N,) grid interval
    alpha: np.ndarray  # (N,)
    cam_slices: list  # per camera slice into N


def gather(
    capture: Capture, t_grid_ns: np.ndarray, smooth_window_s: float = 2.0, smooth_order: int = 2, tracks: list[np.ndarray] | None = None
) -> Observations:
    """Flatten the capture's frames (only those within the grid's time span) for fitting. ``T_smooth`` comes
    from ``tracks`` (each camera's :func:`camera_track` at its pose samples) when given, else is computed."""
    t_grid_ns = np.asarray(t_grid_ns, dtype=np.int64)
    if len(t_grid_ns) < 2:
        raise CaptureError("the output time grid needs at least 2 times")
    D = max(c.num_detectors for c in capture.cameras)
    parts: dict[str, list] = {k: [] for k in ("cam", "t", "uv", "conf", "K", "T", "Ts", "ps", "rs")}
    slices, n0 = [], 0
    for ci, c in enumerate(capture.cameras):
        sel = (c.t_frame_ns >= t_grid_ns[0]) & (c.t_frame_ns <= t_grid_ns[-1])
        t = c.t_frame_ns[sel]
        uv = np.zeros((len(t), D, 17, 2))
        cf = np.zeros((len(t), D, 17))
        uv[:, : c.num_detectors] = c.keypoints_px[sel]
        cf[:, : c.num_detectors] = c.confidence[sel]
        ps, rs = c.sigma_at(t)
        parts["cam"].append(np.full(len(t), ci))
        parts["t"].append(t)
        parts["uv"].append(uv)
        parts["conf"].append(np.nan_to_num(cf))
        parts["K"].append(c.K_at(t))
        parts["T"].append(c.pose_at(t))
        if tracks is not None:
            parts["Ts"].append(interpolate_poses(c.t_pose_ns, tracks[ci], t))
        else:
            parts["Ts"].append(smoothed_pose_at(c, t, smooth_window_s, smooth_order) if smooth_window_s > 0 else c.pose_at(t))
        parts["ps"].append(ps)
        parts["rs"].append(np.radians(rs))
        slices.append(slice(n0, n0 + len(t)))
        n0 += len(t)
    t_all = np.concatenate(parts["t"])
    k = np.clip(np.searchsorted(t_grid_ns, t_all, side="right") - 1, 0, len(t_grid_ns) - 2)
    alpha = (t_all - t_grid_ns[k]) / (t_grid_ns[k + 1] - t_grid_ns[k])
    return Observations(
        cam=np.concatenate(parts["cam"]), t_ns=t_all, uv=np.concatenate(parts["uv"]), conf=np.concatenate(parts["conf"]),
        K=np.concatenate(parts["K"]), T_est=np.concatenate(parts["T"]), T_smooth=np.concatenate(parts["Ts"]), pos_sigma_m=np.concatenate(parts["ps"]),
        rot_sigma_rad=np.concatenate(parts["rs"]), k=k, alpha=np.clip(alpha, 0.0, 1.0), cam_slices=slices,
    )  # fmt: skip


def interpolate_to_grid(capture: Capture, t_grid_ns: np.ndarray, max_gap_periods: float = 2.5, smooth_window_s: float = 2.0):
    """Per camera keypoints at the grid times: (uv (C, T, D, 17, 2), conf (C, T, D, 17), T_world_cam (C, T, 4, 4), K (C, T, 3, 3))."""
    t_grid_ns = np.asarray(t_grid_ns, dtype=np.int64)
    C, T = capture.num_cameras, len(t_grid_ns)
    D = max(c.num_detectors for c in capture.cameras)
    uv = np.zeros((C, T, D, 17, 2))
    conf = np.zeros((C, T, D, 17))
    Ts = np.zeros((C, T, 4, 4))
    Ks = np.zeros((C, T, 3, 3))
    for ci, c in enumerate(capture.cameras):
        Ts[ci] = smoothed_pose_at(c, t_grid_ns, smooth_window_s) if smooth_window_s > 0 else c.pose_at(t_grid_ns)
        Ks[ci] = c.K_at(t_grid_ns)
        if c.num_frames == 0:
            continue
        tf = c.t_frame_ns
        period = np.median(np.diff(tf)) if len(tf) > 1 else 1e9
        i1 = np.clip(np.searchsorted(tf, t_grid_ns), 0, len(tf) - 1)
        i0 = np.clip(i1 - 1, 0, len(tf) - 1)
        i0 = np.where(tf[i1] == t_grid_ns, i1, i0)
        gap = (tf[i1] - tf[i0]).astype(float)
        a = np.where(gap > 0, (t_grid_ns - tf[i0]) / np.maximum(gap, 1), 0.0)
        inside = (a >= -0.01) & (a <= 1.01) & (gap <= max_gap_periods * period)
        # before the camera's first / after its last frame: hold the nearest frame for up to one period
        # (otherwise the clip's first and last output times lose views and triangulate badly)
        before = (t_grid_ns < tf[0]) & (tf[0] - t_grid_ns <= period)
        after = (t_grid_ns > tf[-1]) & (t_grid_ns - tf[-1] <= period)
        a = np.where(before, 0.0, np.where(after, 1.0, a))
        i0 = np.where(before, 0, i0)
        i1 = np.where(after, len(tf) - 1, i1)
        inside = inside | before | after
        a = np.clip(a, 0, 1)[:, None, None]
        d = c.num_detectors
        uv[ci, :, :d] = (1 - a[..., None]) * c.keypoints_px[i0] + a[..., None] * c.keypoints_px[i1]
        conf[ci, :, :d] = np.minimum(c.confidence[i0], c.confidence[i1]) * inside[:, None, None]
    return uv, conf, Ts, Ks


def triangulate(uv: np.ndarray, conf: np.ndarray, T_world_cam: np.ndarray, K: np.ndarray, sigma_px: float = 20.0, iters: int = 6) -> np.ndarray:
    """Robust multi-view triangulation.

    Shapes: uv (C, T, D, 17, 2), conf (C, T, D, 17), T_world_cam (C, T, 4, 4), K (C, T, 3, 3)
    -> points (T, 17, 3); NaN where fewer than two views see a joint.
    """
    C, T, D = uv.shape[:3]
    T_cw = invert_T(T_world_cam)  # (C, T, 4, 4)
    P = np.einsum("ctij,ctjk->ctik", K, T_cw[..., :3, :])  # (C, T, 3, 4)
    # rows: (C, T, D, 17, 2, 4)
    r1 = uv[..., 0:1] * P[:, :, None, None, 2, :] - P[:, :, None, None, 0, :]
    r2 = uv[..., 1:2] * P[:, :, None, None, 2, :] - P[:, :, None, None, 1, :]
    A = np.stack([r1, r2], -2)  # (C, T, D, 17, 2, 4)
    A = np.moveaxis(A, (0, 2), (2, 3)).reshape(T, 17, C * D, 2, 4)  # (T, 17, C*D, 2, 4) after moving axes
    w0 = np.moveaxis(conf, (0, 2), (2, 3)).reshape(T, 17, C * D)
    uvf = np.moveaxis(uv, (0, 2), (2, 3)).reshape(T, 17, C * D, 2)
    Pf = np.broadcast_to(np.moveaxis(np.broadcast_to(P[:, :, None], (C, T, D, 3, 4)), (0, 2), (1, 2)).reshape(T, C * D, 3, 4)[:, None], (T, 17, C * D, 3, 4))
    # normalise rows so each view counts by its confidence, not its depth
    A = A / np.maximum(np.linalg.norm(A, axis=-1, keepdims=True), 1e-9)
    # start: the candidate (every pair of views, and all views) with the lowest robust reprojection cost
    def solve(wt):
        M = (A * wt[..., None, None]).reshape(T, 17, -1, 4)
        _, _, Vt = np.linalg.svd(M)
        Xh = Vt[..., -1, :]
        return Xh[..., :3] / np.where(np.abs(Xh[..., 3:]) < 1e-12, 1e-12, Xh[..., 3:])

    def reproj_e2(X):
        ph = np.einsum("tjvik,tjk->tjvi", Pf, np.concatenate([X, np.ones((T, 17, 1))], -1))
        proj = ph[..., :2] / np.where(np.abs(ph[..., 2:]) < 1e-9, 1e-9, ph[..., 2:])
        return ((proj - uvf) ** 2).sum(-1)

    V = C * D
    cands = [w0]
    for i in range(V):
        for j in range(i + 1, V):
            m = np.zeros(V)
            m[[i, j]] = 1.0
            cands.append(w0 * m)
    best_cost = np.full((T, 17), np.inf)
    X = np.zeros((T, 17, 3))
    for wc in cands:
        ok = (wc > 0).sum(-1) >= 2
        Xc = solve(np.where(ok[..., None], wc, w0))
        e2 = reproj_e2(Xc)
        cost = (w0 * e2 / (e2 + sigma_px**2)).sum(-1)
        cost = np.where(np.isfinite(cost), cost, np.inf)
        better = cost < best_cost
        X[better] = Xc[better]
        best_cost[better] = cost[better]
    w = w0 * (sigma_px**2 / (reproj_e2(X) + sigma_px**2)) ** 2
    for _ in range(iters):
        M = (A * w[..., None, None]).reshape(T, 17, -1, 4)
        _, _, Vt = np.linalg.svd(M)
        Xh = Vt[..., -1, :]
        X = Xh[..., :3] / np.where(np.abs(Xh[..., 3:]) < 1e-12, 1e-12, Xh[..., 3:])
        ph = np.einsum("tjvik,tjk->tjvi", Pf, np.concatenate([X, np.ones((T, 17, 1))], -1))
        proj = ph[..., :2] / np.where(np.abs(ph[..., 2:]) < 1e-9, 1e-9, ph[..., 2:])
        e2 = ((proj - uvf) ** 2).sum(-1)
        w = w0 * (sigma_px**2 / (e2 + sigma_px**2)) ** 2
    nviews = (w0 > 0).sum(-1)
    X[nviews < 2] = np.nan
    return X


def median_in_time(X: np.ndarray, size: int = 5) -> np.ndarray:
    """Running median over time of joint tracks (T, J, 3) (suppresses single-frame outliers)."""
    if len(X) < size:
        return X
    return median_filter(X, size=(size, 1, 1), mode="nearest")


def reject_blunders(X: np.ndarray, size: int = 9, max_dev_m: float = 0.3) -> np.ndarray:
    """Joint tracks (T, J, 3) with points farther than ``max_dev_m`` from their running median (window
    ``size``, mirrored at the ends) set to NaN: a two-view triangulation with one wrong view lands
    anywhere on the good view's ray, and several such frames at a clip's end defeat a short median."""
    X = X.copy()
    if len(X) < 3:
        return X
    h = min(size, len(X) - (1 - len(X) % 2)) // 2
    pad = np.concatenate([X[h:0:-1], X, X[-2 : -h - 2 : -1]]) if h > 0 else X
    win = np.lib.stride_tricks.sliding_window_view(pad, 2 * h + 1, axis=0)  # (T, J, 3, 2h+1)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN windows stay NaN
        med = np.nanmedian(win, axis=-1)
    bad = np.linalg.norm(X - med, axis=-1) > max_dev_m  # NaN compares False
    X[bad] = np.nan
    return X


def fill_gaps(X: np.ndarray) -> np.ndarray:
    """Fill NaN joint positions (T, J, 3) by linear interpolation in time (nearest at the ends)."""
    X = X.copy()
    T = X.shape[0]
    t = np.arange(T)
    for j in range(X.shape[1]):
        ok = np.isfinite(X[:, j, 0])
        if ok.sum() == 0:
            continue
        for a in range(3):
            X[:, j, a] = np.interp(t, t[ok], X[ok, j, a])
    return X
