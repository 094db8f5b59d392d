"""Detection -> 3D position measurement of the person (with covariance), as in AirCap's CDT filter.

A person detection is an image box with per-edge pixel variance, taken by a camera whose pose at capture
(``T_world_cam``: camera optical -> world NED) is known up to a 6x6 covariance. Two measurement models:

* **height prior** (:func:`measurement_from_box`, ``mode="height_prior"``): the person is an upright
  segment of height ``person_height_m`` (prior ~1.69 m). The rays through the box's top-centre and
  bottom-centre pixels are intersected (least squares) with a vertical segment of that height; its midpoint
  is the measured centre of the person. This handles a tilted camera exactly (no "range = f H / h"
  small-angle assumption) and degrades gracefully; when the camera looks nearly straight down (top and
  bottom rays nearly parallel to the vertical) the range is unobservable and it raises
  :class:`DegenerateGeometryError` (use ``mode="bearing"``).
* **height prior and ground** (``mode="height_and_ground"``, the default of
  :func:`measurements_from_detections`): a person's feet are on the ground far more reliably than the person
  stands straight (crouching, bending and sitting shrink the box by up to half, which the height prior reads
  as a person twice as far away). The bottom-centre ray meets the ground plane ``down = ground_down_m``
  (uncertain by ``ground_sigma_m``: uneven ground, jumps); the centre is half the prior height above it. The
  two range estimates are fused with their information matrices (edges, height/ground spread, and for the
  ground the camera's height error over the plane, which slides the feet along the ray), fixed at the nominal
  point, and the fused point is propagated like the others. The plane is given in the frame of the camera
  pose: a drone's take-off ground in its own reported frame (``Detections.ground_down_m``), so that a constant
  height error of its estimate moves camera and ground together. Looking down steeply the ground
  term dominates, looking near the horizon the height term does. When the ground ray misses (camera below
  the ground plane, ray above the horizon) it is the height prior alone.
* **bearing only** (``mode="bearing"``): the ray through the box centre placed at ``range_hint_m`` (from the
  filter's prediction), or, without a hint, the ray through the box's bottom centre (the feet) meeting the
  ground plane ``down = ground_down_m``, raised by half the prior height; the covariance is wide (``bearing_range_sigma_m``) along the ray, so in a Kalman
  update it carries only the two bearing directions.

Walking along the view ray, the box's bottom is the nearest foot, which leads the pelvis toward the camera:
with the person's velocity (the filter's prediction; ``person_velocity_ned_mps``), the height and ground
modes move the centre away from the camera by ``stride_lead_s * |v . u|`` (:attr:`MeasurementConfig.stride_lead_s`).

The covariance is first-order propagation ``J diag(inputs) J^T`` of: the four box edges (per-edge pixel
variance, floored at ``min_edge_var_px2``), the person-height prior (``person_height_sigma_m``), the camera
position (3) and the camera orientation (3, small world-frame rotations ``R' = exp([dtheta]_x) R``, the
convention of :attr:`shared_msgs.messages.Detections.T_world_cam_cov`). The Jacobians are closed form
(:func:`_height_prior_point_jac`, :func:`_ground_point_jac`, :func:`_bearing_point_jac`: the chain rule through the
pixel rays, their normalisation and the 2x2 normal equations; the fused point's weights are held at the nominal
point), one model evaluation per box instead of the 25 of central differences, equal to those to ~1e-7 relative
(``tests/onboard/tracking/test_measurement_jacobian.py``). The result
is elongated along the viewing ray (range from box height is much less certain than bearing).

Two covariances are returned: ``cov_m2`` (everything) and ``cov_no_cam_position_m2`` (without the camera
position part that the filter's offset model ``z = p + b`` explains; the rest, the ground point's slide when the
camera's height is off, stays). The cooperative filter uses the latter when the camera position error (GPS
offset) is a filter state, the former otherwise.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from typing import Literal

import numpy as np

from shared_msgs.messages import BoundingBox, Detections
from skycap.camera import PinholeCamera
from skycap.errors import SkycapError

__all__ = [
    "PERSON_HEIGHT_PRIOR_M",
    "PositionMeasurement",
    "MeasurementError",
    "DegenerateGeometryError",
    "MeasurementConfig",
    "measurement_from_box",
    "measurements_from_detections",
    "box_from_person",
]

log = logging.getLogger(__name__)

PERSON_HEIGHT_PRIOR_M = 1.69
"""Prior height of a standing person (AirCap's value), metres."""

MeasurementMode = Literal["height_and_ground", "height_prior", "bearing"]


class MeasurementError(SkycapError, ValueError):
    """A detection that cannot be turned into a measurement (bad numbers, box behind the camera, ...)."""


class DegenerateGeometryError(MeasurementError):
    """Range from the height prior is unobservable (camera looking along the vertical); use bearing mode."""


@dataclasses.dataclass(frozen=True)
class MeasurementConfig:
    person_height_m: float = PERSON_HEIGHT_PRIOR_M
    #: adult height spread plus posture (crouching/bending shrink the box; the ground term covers that)
    person_height_sigma_m: float = 0.15
    ground_sigma_m: float = 0.15  #: the feet's height above the ground plane (uneven ground, steps, jumps)
    #: a walking person's box bottom is the NEAREST foot, which leads the pelvis toward the camera by a share
    #: of the stride when the person walks along the view ray (the stride grows with speed): the measured centre
    #: is then too close to the camera by stride_lead_s * |v . u| (v the person's horizontal velocity, u the
    #: horizontal view direction), and is moved back by that much when the person's velocity is known. Fitted on
    #: the simulator's walking person against ground-truth boxes (bias -0.16 m at |v . u| ~ 1 m/s, -0.02 m
    #: walking across the view). 0 = off.
    stride_lead_s: float = 0.14
    mode: MeasurementMode = "height_and_ground"  #: the model :func:`measurements_from_detections` uses
    min_edge_var_px2: float = 4.0  #: floor for the per-edge variance (detectors report 0 = unknown)
    bearing_range_sigma_m: float = 200.0  #: along-ray std of a bearing-only measurement
    min_vertical_parallax_rad: float = math.radians(10.0)  #: view ray must be at least this far from the vertical
    default_cam_position_var_m2: float = 1.0  #: used when Detections.T_world_cam_cov is empty
    default_cam_rotation_var_rad2: float = 3e-4


@dataclasses.dataclass(frozen=True)
class PositionMeasurement:
    """A 3D measurement of the person's centre (NED) from one detection.

    position_ned_m: (3,); cov_m2 and cov_no_cam_position_m2: (3, 3); camera_position_ned_m: (3,) the
    (reported) camera centre at capture; ``source_id`` the drone whose camera took it.
    """

    t_ns: int
    source_id: str
    position_ned_m: np.ndarray
    cov_m2: np.ndarray
    cov_no_cam_position_m2: np.ndarray
    camera_position_ned_m: np.ndarray
    mode: MeasurementMode
    score: float = 1.0
    #: (3, 3) the camera position covariance the measurement was made with (the sender's positioning grade)
    camera_position_cov_m2: np.ndarray | None = None

    def is_finite(self) -> bool:
        return bool(
            np.all(np.isfinite(self.position_ned_m))
            and np.all(np.isfinite(self.cov_m2))
            and np.all(np.isfinite(self.cov_no_cam_position_m2))
        )


def _rotvec_matrix(w: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation vector (3,) -> (3, 3)."""
    th = math.sqrt(float(w[0] * w[0] + w[1] * w[1] + w[2] * w[2]))
    if th < 1e-12:
        return np.eye(3)
    k = w / th
    Kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(th) * Kx + (1.0 - math.cos(th)) * (Kx @ Kx)


def _rays(K_inv: np.ndarray, R_wc: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """World-frame (unnormalised) ray directions for pixels uv (n, 2) -> (n, 3)."""
    h = np.concatenate([uv, np.ones((uv.shape[0], 1))], axis=1)
    return (R_wc @ (K_inv @ h.T)).T


def _height_prior_point(
    edges: np.ndarray, height_m: float, c: np.ndarray, R_wc: np.ndarray, K_inv: np.ndarray, min_parallax: float
) -> np.ndarray:
    """Centre of the vertical segment of length height_m whose ends lie on the top/bottom-centre rays."""
    x0, y0, x1, y1 = edges
    u = 0.5 * (x0 + x1)
    r = _rays(K_inv, R_wc, np.array([[u, y0], [u, y1]]))
    r_top, r_bot = r[0] / np.linalg.norm(r[0]), r[1] / np.linalg.norm(r[1])
    down = np.array([0.0, 0.0, 1.0])
    # b * r_bot - a * r_top = H * down  (least squares in (b, a))
    # normal equations of the 3x2 system (well conditioned once the view check below passes)
    cb = float(r_top @ r_bot)
    det = 1.0 - cb * cb
    if det < 1e-12:
        raise DegenerateGeometryError("the box's top and bottom rays are parallel (zero-height box?); use mode='bearing'")
    rhs_b, rhs_a = height_m * r_bot[2], -height_m * r_top[2]
    b = (rhs_b + cb * rhs_a) / det
    a = (rhs_a + cb * rhs_b) / det
    r_mid = r_top + r_bot
    sin_view = np.linalg.norm(np.cross(r_mid / np.linalg.norm(r_mid), down))
    if sin_view < math.sin(min_parallax):
        raise DegenerateGeometryError(
            "camera looks along the vertical at the person: range from the height prior is unobservable; use mode='bearing'"
        )
    if a <= 0 or b <= 0:
        raise DegenerateGeometryError(
            f"the box's top and bottom rays do not bracket an upright person in front of the camera (ranges {a:.2f}, {b:.2f} m); use mode='bearing'"
        )
    return c + 0.5 * (a * r_top + b * r_bot)


def _ground_point(edges: np.ndarray, h: float, g: float, c: np.ndarray, R_wc: np.ndarray, K_inv: np.ndarray, ground_down_m: float) -> np.ndarray:
    """Centre of an upright person of height h whose feet (bottom-centre ray) stand g metres above the plane
    ``down = ground_down_m``; raises :class:`MeasurementError` when the ray does not meet that plane ahead."""
    r = _rays(K_inv, R_wc, np.array([[0.5 * (edges[0] + edges[2]), edges[3]]]))[0]
    plane = ground_down_m - g
    if r[2] <= 1e-6 or plane <= c[2]:
        raise MeasurementError("the box's bottom ray does not meet the ground plane below the camera; pass range_hint_m or use mode='height_prior'")
    feet = c + r * (plane - c[2]) / r[2]
    return feet - np.array([0.0, 0.0, 0.5 * h])


def _bearing_point(edges: np.ndarray, c: np.ndarray, R_wc: np.ndarray, K_inv: np.ndarray, range_m: float) -> np.ndarray:
    x0, y0, x1, y1 = edges
    r = _rays(K_inv, R_wc, np.array([[0.5 * (x0 + x1), 0.5 * (y0 + y1)]]))[0]
    return c + range_m * r / np.linalg.norm(r)


def _stride_lead_correction(ray: np.ndarray, velocity_ned_mps: np.ndarray | None, lead_s: float) -> np.ndarray:
    """(3,) shift of a measured centre away from the camera along the horizontal view direction of ``ray``
    (camera -> person): ``lead_s * |v_h . u_h|`` (see :attr:`MeasurementConfig.stride_lead_s`); zero without a
    finite velocity."""
    if velocity_ned_mps is None or lead_s <= 0:
        return np.zeros(3)
    v = np.asarray(velocity_ned_mps, dtype=float).reshape(3)
    u = np.array([ray[0], ray[1], 0.0])
    n = float(np.linalg.norm(u))
    if not np.all(np.isfinite(v)) or n < 1e-9:
        return np.zeros(3)
    u /= n
    return lead_s * abs(float(v[0] * u[0] + v[1] * u[1])) * u


#: the inputs of a measurement model, in Jacobian column order: 4 box edges (px), person height (m), camera
#: position (3, m), camera rotation (3, rad, world frame), ground height (m); and the central-difference steps
_EDGES, _HEIGHT, _CAM_POSITION, _GROUND = [0, 1, 2, 3], 4, [5, 6, 7], 11
_STEPS = np.array([0.5] * 4 + [0.01] + [0.01] * 3 + [1e-4] * 3 + [0.01])


def _unmodelled_camera_cov(J_cam: np.ndarray, pose_cov: np.ndarray) -> np.ndarray:
    """(3, 3) covariance of the part of the camera-position error that the offset model does not explain.

    The filter takes a measurement from a camera reported at ``c + b`` as ``p + b`` (its offset state carries
    ``b``, so :attr:`PositionMeasurement.cov_no_cam_position_m2` leaves the camera position out). That is exact when
    the point moves with the camera (height prior: ``J_cam = I``); a point on the ground plane moves with the
    camera horizontally but slides along the ray when the camera's height over the plane is off (``J_cam``'s down
    column is the slide, ``(d_n, d_e, 0) / -d_d`` per metre). The residual ``(J_cam - I) b`` is noise of such a
    measurement. J_cam: (3, 3) d point / d camera position; pose_cov: (6, 6) with the position block first."""
    M = J_cam - np.eye(3)
    return M @ pose_cov[:3, :3] @ M.T


def _jacobian(model, edges: np.ndarray, H: float, cols=range(12)) -> np.ndarray:
    """(3, len(cols)) central-difference Jacobian of ``model(e, h, dc, dth, g)`` at (edges, H, 0, 0, 0) over
    the input columns ``cols`` (see :data:`_STEPS`)."""
    J = np.zeros((3, len(cols)))
    for j, i in enumerate(cols):
        dp = np.zeros(12)
        dp[i] = _STEPS[i]
        args_p = (edges + dp[:4], H + dp[4], dp[5:8], dp[8:11], dp[11])
        args_m = (edges - dp[:4], H - dp[4], -dp[5:8], -dp[8:11], -dp[11])
        J[:, j] = (model(*args_p) - model(*args_m)) / (2 * _STEPS[i])
    return J


def _unit_jacobian(r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(r / |r|, d(r / |r|) / dr (3, 3))."""
    nr = math.sqrt(float(r @ r))
    n = r / nr
    return n, (np.eye(3) - np.outer(n, n)) / nr


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _ray_jacobian(M: np.ndarray, r: np.ndarray, du: tuple[float, float, float, float], dv: tuple[float, float, float, float]) -> np.ndarray:
    """(3, 12) derivative of the world ray ``r = M [u, v, 1]`` (``M = R K^-1``) over the model inputs: the pixel
    (u, v) depends on the box edges by ``du`` / ``dv`` (4,), and a world-frame rotation ``exp([dth]_x)`` turns the
    ray by ``dth x r`` (columns 8-10: ``-[r]_x``); height, camera position and ground do not move it."""
    J = np.zeros((3, 12))
    J[:, :4] = np.outer(M[:, 0], du) + np.outer(M[:, 1], dv)
    J[:, 8:11] = -_skew(r)
    return J


def _height_prior_point_jac(edges: np.ndarray, h: float, c: np.ndarray, R_wc: np.ndarray, K_inv: np.ndarray,
                            min_parallax: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_height_prior_point` and its closed-form (3, 12) Jacobian over the inputs (see :data:`_STEPS`)."""
    p = _height_prior_point(edges, h, c, R_wc, K_inv, min_parallax)  # the checks and the value
    x0, y0, x1, y1 = edges
    u = 0.5 * (x0 + x1)
    M = R_wc @ K_inv
    r_t = M @ np.array([u, y0, 1.0])
    r_b = M @ np.array([u, y1, 1.0])
    t, Nt = _unit_jacobian(r_t)
    b_, Nb = _unit_jacobian(r_b)
    dt = Nt @ _ray_jacobian(M, r_t, (0.5, 0.0, 0.5, 0.0), (0.0, 1.0, 0.0, 0.0))  # (3, 12)
    db = Nb @ _ray_jacobian(M, r_b, (0.5, 0.0, 0.5, 0.0), (0.0, 0.0, 0.0, 1.0))
    cb = float(t @ b_)
    det = 1.0 - cb * cb
    na = -t[2] + cb * b_[2]  # a = h na / det, b = h nb / det
    nb = b_[2] - cb * t[2]
    a, b = h * na / det, h * nb / det
    # derivatives with respect to t and b (row vectors, 3)
    ez = np.array([0.0, 0.0, 1.0])
    dcb_dt, dcb_db = b_, t
    ddet_dt, ddet_db = -2.0 * cb * dcb_dt, -2.0 * cb * dcb_db
    dna_dt, dna_db = -ez + b_[2] * dcb_dt, cb * ez + b_[2] * dcb_db
    dnb_dt, dnb_db = -cb * ez - t[2] * dcb_dt, ez - t[2] * dcb_db
    da_dt = h * (dna_dt * det - na * ddet_dt) / det**2
    da_db = h * (dna_db * det - na * ddet_db) / det**2
    db_dt = h * (dnb_dt * det - nb * ddet_dt) / det**2
    db_db = h * (dnb_db * det - nb * ddet_db) / det**2
    dp_dt = 0.5 * (np.outer(t, da_dt) + a * np.eye(3) + np.outer(b_, db_dt))
    dp_db = 0.5 * (np.outer(t, da_db) + np.outer(b_, db_db) + b * np.eye(3))
    J = dp_dt @ dt + dp_db @ db
    J[:, 4] = (p - c) / h
    J[:, 5:8] += np.eye(3)
    return p, J


def _ground_point_jac(edges: np.ndarray, h: float, g: float, c: np.ndarray, R_wc: np.ndarray, K_inv: np.ndarray,
                      ground_down_m: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_ground_point` and its closed-form (3, 12) Jacobian (the height column: the centre is h / 2 above
    the feet)."""
    p = _ground_point(edges, h, g, c, R_wc, K_inv, ground_down_m)
    M = R_wc @ K_inv
    r = M @ np.array([0.5 * (edges[0] + edges[2]), edges[3], 1.0])
    depth = ground_down_m - g - c[2]
    s = depth / r[2]
    ez = np.array([0.0, 0.0, 1.0])
    slide = np.eye(3) - np.outer(r, ez) / r[2]  # d feet / d camera position; d feet / d r = s * slide
    J = s * slide @ _ray_jacobian(M, r, (0.5, 0.0, 0.5, 0.0), (0.0, 0.0, 0.0, 1.0))
    J[:, 4] = -0.5 * ez
    J[:, 5:8] = slide
    J[:, 11] = -r / r[2]
    return p, J


def _bearing_point_jac(edges: np.ndarray, c: np.ndarray, R_wc: np.ndarray, K_inv: np.ndarray,
                       range_m: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_bearing_point` and its closed-form (3, 12) Jacobian."""
    M = R_wc @ K_inv
    x0, y0, x1, y1 = edges
    r = M @ np.array([0.5 * (x0 + x1), 0.5 * (y0 + y1), 1.0])
    n, Nr = _unit_jacobian(r)
    J = range_m * Nr @ _ray_jacobian(M, r, (0.5, 0.0, 0.5, 0.0), (0.0, 0.5, 0.0, 0.5))
    J[:, 5:8] = np.eye(3)
    return c + range_m * n, J


def measurement_from_box(
    box: BoundingBox | np.ndarray,
    intrinsics: PinholeCamera,
    T_world_cam: np.ndarray,
    T_world_cam_cov: np.ndarray | None = None,
    *,
    t_ns: int = 0,
    source_id: str = "",
    mode: MeasurementMode = "height_prior",
    range_hint_m: float | None = None,
    ground_down_m: float = 0.0,
    edge_var_px2: np.ndarray | None = None,
    person_velocity_ned_mps: np.ndarray | None = None,
    config: MeasurementConfig = MeasurementConfig(),
) -> PositionMeasurement:
    """One box -> a 3D measurement of the person's centre with covariance.

    Args:
        box: a :class:`BoundingBox`, or (4,) edges (x_min, y_min, x_max, y_max) in pixels with
            ``edge_var_px2`` (4,) beside it.
        intrinsics: the camera's pinhole intrinsics.
        T_world_cam: (4, 4) camera optical -> world NED at capture.
        T_world_cam_cov: (6, 6) covariance of (position m, world-frame rotation rad) or None (defaults
            from ``config``).
        mode: "height_prior" or "bearing" (see module doc).
        range_hint_m: bearing mode: range along the ray to place the point at (e.g. from the filter);
            None = intersect with the plane ``down = ground_down_m - person_height_m / 2``.
        person_velocity_ned_mps: (3,) the person's velocity (e.g. the filter's prediction) or None: the
            height-prior and ground modes then correct the nearest-foot lead (``config.stride_lead_s``).

    Returns:
        :class:`PositionMeasurement`.

    Raises:
        MeasurementError: non-finite input, an empty box, a box behind/off the ground plane;
        DegenerateGeometryError: height prior unusable from this viewpoint.
    """
    if isinstance(box, BoundingBox):
        edges = np.array([box.x_min_px, box.y_min_px, box.x_max_px, box.y_max_px], dtype=float)
        ev = np.array([box.var_x_min_px2, box.var_y_min_px2, box.var_x_max_px2, box.var_y_max_px2], dtype=float)
        score = float(box.score)
    else:
        edges = np.asarray(box, dtype=float).reshape(4)
        ev = np.zeros(4) if edge_var_px2 is None else np.asarray(edge_var_px2, dtype=float).reshape(4)
        score = 1.0
    T = np.asarray(T_world_cam, dtype=float).reshape(4, 4)
    if not (np.all(np.isfinite(edges)) and np.all(np.isfinite(ev)) and np.all(np.isfinite(T))):
        raise MeasurementError("box edges, their variances and T_world_cam must be finite (got NaN/inf); drop the detection")
    if edges[2] <= edges[0] or edges[3] <= edges[1]:
        raise MeasurementError(f"empty box {edges.tolist()}: x_max must exceed x_min and y_max exceed y_min")
    if T_world_cam_cov is None or np.size(T_world_cam_cov) == 0:
        pose_cov = np.diag([config.default_cam_position_var_m2] * 3 + [config.default_cam_rotation_var_rad2] * 3)
    else:
        pose_cov = np.asarray(T_world_cam_cov, dtype=float).reshape(6, 6)
        if not np.all(np.isfinite(pose_cov)):
            raise MeasurementError("T_world_cam_cov contains NaN/inf; send an empty covariance to use defaults")
    ev = np.maximum(ev, config.min_edge_var_px2)
    K_inv = np.linalg.inv(intrinsics.K)
    R0, c0 = T[:3, :3], T[:3, 3]
    H = config.person_height_m

    if mode == "height_and_ground":
        try:
            _ground_point(edges, H, 0.0, c0, R0, K_inv, ground_down_m)
        except MeasurementError:
            mode = "height_prior"  # the feet cannot be put on the ground from here: height prior alone
    mp = config.min_vertical_parallax_rad
    if mode == "height_and_ground":
        # information weights of the two range estimates, from their own spreads (edges + height / ground)
        p_h, Jh = _height_prior_point_jac(edges, H, c0, R0, K_inv, mp)
        p_g, Jg = _ground_point_jac(edges, H, 0.0, c0, R0, K_inv, ground_down_m)
        C_h = Jh[:, :5] @ np.diag([*ev, config.person_height_sigma_m**2]) @ Jh[:, :5].T
        Jg_e = Jg[:, _EDGES + [_GROUND]]
        C_g = Jg_e @ np.diag([*ev, config.ground_sigma_m**2]) @ Jg_e.T
        # a camera position error that the filter's offset (z = p + b) does not explain: the ground point slides
        # along the ray when the camera's height over the ground plane is off (see _unmodelled_camera_cov)
        C_g = C_g + _unmodelled_camera_cov(Jg[:, 5:8], pose_cov)
        # the ground point's vertical is the height prior's (centre = feet + H/2): give it the height spread too
        C_g = C_g + np.diag([0.0, 0.0, (0.5 * config.person_height_sigma_m) ** 2])
        reg = 1e-6 * np.eye(3)
        I_h, I_g = np.linalg.inv(C_h + reg), np.linalg.inv(C_g + reg)
        C_f = np.linalg.inv(I_h + I_g)
        A_h, A_g = C_f @ I_h, C_f @ I_g
        # the fused point A_h p_h + A_g p_g (weights fixed at the nominal point); the height prior's point does
        # not depend on the ground, the ground point's on the height only through the centre's H / 2
        p = A_h @ p_h + A_g @ p_g
        J = A_h @ Jh + A_g @ Jg
    elif mode == "bearing":
        if range_hint_m is None:
            # feet: the bottom-centre ray meets the ground plane; the centre is half the height above it
            p, J = _ground_point_jac(edges, H, 0.0, c0, R0, K_inv, ground_down_m)
        else:
            range_m = float(range_hint_m)
            if not (math.isfinite(range_m) and range_m > 0):
                raise MeasurementError(f"range_hint_m must be finite and > 0, got {range_hint_m}")
            p, J = _bearing_point_jac(edges, c0, R0, K_inv, range_m)
    elif mode == "height_prior":
        p, J = _height_prior_point_jac(edges, H, c0, R0, K_inv, mp)
    else:
        raise MeasurementError(f"unknown measurement mode {mode!r}; use 'height_and_ground', 'height_prior' or 'bearing'")

    if mode in ("height_prior", "height_and_ground"):
        # in front of the camera
        if (R0.T @ (p - c0))[2] <= 0:
            raise MeasurementError("the measured person lies behind the camera; check T_world_cam")
        p = p + _stride_lead_correction(p - c0, person_velocity_ned_mps, config.stride_lead_s)

    if mode == "bearing":
        J[:, 4] = 0.0
    Sigma_in = np.zeros((12, 12))
    Sigma_in[:4, :4] = np.diag(ev)
    Sigma_in[4, 4] = config.person_height_sigma_m**2
    Sigma_in[5:11, 5:11] = pose_cov
    Sigma_in[11, 11] = config.ground_sigma_m**2
    cov = J @ Sigma_in @ J.T
    Sigma_nc = Sigma_in.copy()
    Sigma_nc[5:8, :] = 0.0
    Sigma_nc[:, 5:8] = 0.0
    cov_nc = J @ Sigma_nc @ J.T + _unmodelled_camera_cov(J[:, 5:8], pose_cov)
    if mode == "bearing":
        r = (p - c0) / np.linalg.norm(p - c0)
        along = config.bearing_range_sigma_m**2 * np.outer(r, r)
        cov = cov + along
        cov_nc = cov_nc + along
    cov = 0.5 * (cov + cov.T)
    cov_nc = 0.5 * (cov_nc + cov_nc.T)
    return PositionMeasurement(
        t_ns=int(t_ns),
        source_id=source_id,
        position_ned_m=p,
        cov_m2=cov,
        cov_no_cam_position_m2=cov_nc,
        camera_position_ned_m=c0.copy(),
        mode=mode,
        score=score,
        camera_position_cov_m2=pose_cov[:3, :3].copy(),
    )


def measurements_from_detections(
    det: Detections,
    intrinsics: PinholeCamera,
    *,
    mode: MeasurementMode | None = None,
    fallback_to_bearing: bool = True,
    range_hint_m: float | None = None,
    ground_down_m: float = 0.0,
    min_score: float = 0.0,
    person_velocity_ned_mps: np.ndarray | None = None,
    config: MeasurementConfig = MeasurementConfig(),
) -> list[PositionMeasurement]:
    """Every usable "person" box of a :class:`Detections` message -> measurements (bad boxes are skipped
    and logged; a degenerate height-prior geometry falls back to bearing mode when allowed). ``mode`` None =
    ``config.mode``. The ground plane is the message's own ``ground_down_m`` (the sender's take-off ground in
    the frame of its camera pose) when it carries one, else ``ground_down_m``."""
    mode = config.mode if mode is None else mode
    if det.ground_down_m is not None:
        if not math.isfinite(det.ground_down_m):
            raise MeasurementError(f"Detections.ground_down_m must be finite or None, got {det.ground_down_m!r}")
        ground_down_m = float(det.ground_down_m)
    if len(det.T_world_cam) != 16:
        raise MeasurementError(f"Detections.T_world_cam must have 16 floats, got {len(det.T_world_cam)}")
    T = np.asarray(det.T_world_cam, dtype=float).reshape(4, 4)
    cov = None
    if len(det.T_world_cam_cov) == 36:
        cov = np.asarray(det.T_world_cam_cov, dtype=float).reshape(6, 6)
    elif len(det.T_world_cam_cov) not in (0,):
        raise MeasurementError(f"Detections.T_world_cam_cov must have 36 floats or none, got {len(det.T_world_cam_cov)}")
    out = []
    for b in det.boxes:
        if b.label != "person" or not (b.score >= min_score):
            continue
        kw = dict(t_ns=det.header.t_measurement_ns, source_id=det.header.sender_id, ground_down_m=ground_down_m,
                  person_velocity_ned_mps=person_velocity_ned_mps, config=config)
        try:
            out.append(measurement_from_box(b, intrinsics, T, cov, mode=mode, range_hint_m=range_hint_m, **kw))
        except DegenerateGeometryError:
            if not fallback_to_bearing:
                continue
            try:
                out.append(measurement_from_box(b, intrinsics, T, cov, mode="bearing", range_hint_m=range_hint_m, **kw))
            except MeasurementError as e:
                log.debug("dropped box from %s: %s", det.header.sender_id, e)
        except MeasurementError as e:
            log.debug("dropped box from %s: %s", det.header.sender_id, e)
    return out


def box_from_person(
    center_ned_m: np.ndarray,
    intrinsics: PinholeCamera,
    T_world_cam: np.ndarray,
    person_height_m: float = PERSON_HEIGHT_PRIOR_M,
    aspect_w_over_h: float = 0.4,
) -> tuple[np.ndarray, float]:
    """The image box of an upright person of given height centred at center_ned_m.

    Returns ((4,) x_min, y_min, x_max, y_max in pixels, depth of the centre in m). The box's vertical edges
    are the projections of the head top and feet; its width is ``aspect_w_over_h`` times its height. This is
    the exact inverse of the height-prior model (used by tests and the ROI).
    """
    from skycap.frames import project_points

    c = np.asarray(center_ned_m, dtype=float)
    pts = np.stack([c - [0, 0, 0.5 * person_height_m], c + [0, 0, 0.5 * person_height_m], c])
    uv, z = project_points(intrinsics.K, np.asarray(T_world_cam, dtype=float), pts)
    u = float(uv[2, 0])
    # keep the top/bottom pixels on the centre column like the model (exact for zero camera roll)
    h = float(uv[1, 1] - uv[0, 1])
    w = aspect_w_over_h * abs(h)
    return np.array([u - 0.5 * w, uv[0, 1], u + 0.5 * w, uv[1, 1]]), float(z[2])
