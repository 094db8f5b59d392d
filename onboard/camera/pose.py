"""Where the camera pointed when a frame was exposed: the vehicle's reported pose and the gimbal's reported
attitude, interpolated at the frame's capture time, through the camera's mount.

The simulator's camera puts ``T_world_cam`` into every frame; a real camera cannot know it. The agent keeps a
:class:`CameraPoser` fed with its own ``VehicleState`` (NED, the autopilot's estimate) and ``GimbalAttitude``
messages and stamps each real frame's pose before the detector and the tracking filter see it::

    poser = CameraPoser(mount="gimbal", pitch_rad=-0.5, lever_arm_body_m=(0.1, 0.0, 0.05))
    poser.add_state(state)                 # every VehicleState
    poser.add_gimbal(attitude)             # every GimbalAttitude (pitch, yaw relative to the heading)
    T = poser.T_world_cam(t_capture_ns)    # (4, 4) or None when no state is near enough

Position: linear interpolation between the two states around ``t``; attitude: spherical interpolation; gimbal
angles: linear (nearest at the ends). A frame older than the history or more than ``max_extrapolation_s`` past
the newest state gets None (its pose is unknown: better no detection than a wrong one).
"""

from __future__ import annotations

import bisect
from collections import deque

import numpy as np

from skycap.frames import T_world_cam_mount

__all__ = ["CameraPoser"]


class CameraPoser:
    """Short histories of the vehicle's pose and the gimbal's angles, and the camera pose at any time in them."""

    def __init__(self, mount: str, pitch_rad: float, lever_arm_body_m=(0.0, 0.0, 0.0), *, history_s: float = 3.0,
                 max_extrapolation_s: float = 0.2):
        if mount not in ("gimbal", "fixed"):
            raise ValueError(f"camera mount {mount!r}: use 'gimbal' or 'fixed'")
        self.mount = mount
        self.default_pitch_rad = float(pitch_rad)
        self.lever_arm_body_m = np.asarray(lever_arm_body_m, dtype=float)
        self.history_ns = int(history_s * 1e9)
        self.max_extrapolation_ns = int(max_extrapolation_s * 1e9)
        self._t: deque[int] = deque()
        self._p: deque[np.ndarray] = deque()
        self._q: deque[tuple[float, float, float, float]] = deque()
        self._gt: deque[int] = deque()
        self._g: deque[tuple[float, float]] = deque()  # (pitch_rad, yaw_rad relative to the heading)

    # --- inputs -------------------------------------------------------------------------------------------
    def add_state(self, state) -> None:
        """A ``VehicleState`` (its ``header.t_measurement_ns``, ``position_ned_m``, ``q_world_body``); out of
        order or non-finite ones are ignored."""
        t = int(state.header.t_measurement_ns)
        p = np.asarray(state.position_ned_m, dtype=float)
        q = tuple(float(v) for v in state.q_world_body)
        if (self._t and t <= self._t[-1]) or not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
            return
        self._t.append(t)
        self._p.append(p)
        self._q.append(q)
        while self._t and self._t[0] < t - self.history_ns:
            self._t.popleft(), self._p.popleft(), self._q.popleft()

    def add_gimbal(self, attitude) -> None:
        """A ``GimbalAttitude`` (``pitch_rad``, ``yaw_rad`` relative to the vehicle's heading)."""
        t = int(attitude.header.t_measurement_ns)
        g = (float(attitude.pitch_rad), float(attitude.yaw_rad))
        if (self._gt and t <= self._gt[-1]) or not all(np.isfinite(g)):
            return
        self._gt.append(t)
        self._g.append(g)
        while self._gt and self._gt[0] < t - self.history_ns:
            self._gt.popleft(), self._g.popleft()

    # --- output -------------------------------------------------------------------------------------------
    def gimbal_angles(self, t_ns: int) -> tuple[float, float]:
        """(pitch_rad, yaw_rad) of the camera at ``t_ns``: the gimbal's reports interpolated, else the configured
        pitch (and for a fixed mount always the configured pitch)."""
        if self.mount == "fixed" or not self._gt:
            return self.default_pitch_rad, 0.0
        ts = np.asarray(self._gt, dtype=np.int64)
        g = np.asarray(self._g)
        return float(np.interp(t_ns, ts, g[:, 0])), float(np.interp(t_ns, ts, g[:, 1]))

    def T_world_cam(self, t_ns: int) -> np.ndarray | None:
        """(4, 4) camera -> world NED at ``t_ns``, or None when the states do not cover that time."""
        if not self._t:
            return None
        t_ns = int(t_ns)
        if t_ns < self._t[0] or t_ns > self._t[-1] + self.max_extrapolation_ns:
            return None
        i = bisect.bisect_right(self._t, t_ns)
        if i >= len(self._t):  # past the newest state: hold it (extrapolating attitude would add noise)
            p, q = self._p[-1], self._q[-1]
        else:
            t0, t1 = self._t[i - 1], self._t[i]
            a = (t_ns - t0) / (t1 - t0)
            p = (1 - a) * self._p[i - 1] + a * self._p[i]
            w0, w1 = self._q[i - 1], self._q[i]
            from scipy.spatial.transform import Rotation, Slerp  # here: scipy.spatial costs ~0.5 s at the agent's start

            rots = Rotation.from_quat([[w0[1], w0[2], w0[3], w0[0]], [w1[1], w1[2], w1[3], w1[0]]])
            x, y, z, w = Slerp([0.0, 1.0], rots)([a]).as_quat()[0]
            q = (w, x, y, z)
        pitch, yaw = self.gimbal_angles(t_ns)
        return T_world_cam_mount(p, q, self.mount, pitch, yaw, self.lever_arm_body_m)
