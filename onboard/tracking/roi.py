"""Where the detector should look next: the fused estimate projected into this drone's camera.

:func:`roi_from_estimate` projects the predicted person (an upright segment of the prior height centred
at the estimate) into the camera and grows the box by ``n_sigma`` standard deviations of the projected
position covariance (first-order, the projection's 2x3 Jacobian) plus a margin. :func:`plan_detection`
turns the estimate into the detector's next mode (``Detections.mode``): "roi" with the region, "tiles" or
"full" when the region is too large or the person is out of view, and the "lost -> search" decision.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import numpy as np

from onboard.tracking.filter import TrackEstimate
from onboard.tracking.measurement import PERSON_HEIGHT_PRIOR_M, box_from_person
from skycap.camera import PinholeCamera
from skycap.frames import invert_T

__all__ = ["RoiConfig", "DetectorPlan", "roi_from_estimate", "plan_detection"]


@dataclasses.dataclass(frozen=True)
class RoiConfig:
    person_height_m: float = PERSON_HEIGHT_PRIOR_M
    aspect_w_over_h: float = 0.5  #: person box width / height (arms, walking)
    n_sigma: float = 3.0
    margin_frac: float = 0.25  #: extra on each side, fraction of the person box size
    min_size_px: float = 96.0  #: detector input is never smaller than this
    max_area_frac: float = 0.5  #: a larger ROI is not worth it: detect on tiles instead
    search_after_s: float = 3.0  #: no detection accepted for this long -> search (AirCap: re-acquire)


@dataclasses.dataclass(frozen=True)
class DetectorPlan:
    """The detector's next job: ``mode`` as in :attr:`Detections.mode`, the ROI (x, y, w, h) in pixels for
    "roi", whether the drone should search (person lost), and why."""

    mode: Literal["roi", "tiles", "full"]
    roi_px: tuple[float, float, float, float] | None
    search: bool
    reason: str


def roi_from_estimate(
    position_ned_m: np.ndarray,
    position_cov_m2: np.ndarray,
    intrinsics: PinholeCamera,
    T_world_cam: np.ndarray,
    config: RoiConfig = RoiConfig(),
) -> tuple[float, float, float, float] | None:
    """The region of interest (x, y, w, h) in pixels, clipped to the image, or None when the person's
    predicted region is behind the camera or entirely outside the image.

    position_ned_m: (3,) predicted centre of the person; position_cov_m2: (3, 3); T_world_cam: (4, 4).
    """
    p = np.asarray(position_ned_m, dtype=float)
    T = np.asarray(T_world_cam, dtype=float).reshape(4, 4)
    T_cw = invert_T(T)
    pc = T_cw[:3, :3] @ p + T_cw[:3, 3]
    if pc[2] <= 0.1:
        return None
    box, _ = box_from_person(p, intrinsics, T, config.person_height_m, config.aspect_w_over_h)
    # d(u, v)/d(p_world) = d(u, v)/d(p_cam) R_cw
    x, y, z = pc
    Jc = np.array([[intrinsics.fx_px / z, 0.0, -intrinsics.fx_px * x / z**2], [0.0, intrinsics.fy_px / z, -intrinsics.fy_px * y / z**2]])
    J = Jc @ T_cw[:3, :3]
    S = J @ np.asarray(position_cov_m2, dtype=float).reshape(3, 3) @ J.T
    su, sv = np.sqrt(np.maximum(np.diag(S), 0.0)) * config.n_sigma
    w0, h0 = box[2] - box[0], box[3] - box[1]
    x0 = box[0] - su - config.margin_frac * w0
    x1 = box[2] + su + config.margin_frac * w0
    y0 = box[1] - sv - config.margin_frac * h0
    y1 = box[3] + sv + config.margin_frac * h0
    # minimum size about the centre
    cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
    half_w = max(0.5 * (x1 - x0), 0.5 * config.min_size_px)
    half_h = max(0.5 * (y1 - y0), 0.5 * config.min_size_px)
    x0, x1, y0, y1 = cx - half_w, cx + half_w, cy - half_h, cy + half_h
    W, Hh = float(intrinsics.width_px), float(intrinsics.height_px)
    if x1 <= 0 or y1 <= 0 or x0 >= W or y0 >= Hh:
        return None
    x0, y0 = max(x0, 0.0), max(y0, 0.0)
    x1, y1 = min(x1, W), min(y1, Hh)
    return float(x0), float(y0), float(x1 - x0), float(y1 - y0)


def plan_detection(
    estimate: TrackEstimate | None,
    intrinsics: PinholeCamera,
    T_world_cam: np.ndarray,
    t_now_ns: int,
    config: RoiConfig = RoiConfig(),
) -> DetectorPlan:
    """The detector's next mode from the filter's estimate (None = no track).

    * no track, or no accepted detection for ``search_after_s`` -> "full" frame and ``search=True``
      (the formation's failsafe holds and searches);
    * track predicted outside this camera's view -> "full", no search (teammates still see the person);
    * ROI larger than ``max_area_frac`` of the image -> "tiles";
    * otherwise "roi" with the region.
    """
    if estimate is None:
        return DetectorPlan("full", None, True, "no track")
    since_s = (t_now_ns - estimate.t_last_measurement_ns) * 1e-9
    if since_s > config.search_after_s:
        return DetectorPlan("full", None, True, f"no detection for {since_s:.1f} s")
    roi = roi_from_estimate(estimate.position_ned_m, estimate.covariance[:3, :3], intrinsics, T_world_cam, config)
    if roi is None:
        return DetectorPlan("full", None, False, "person predicted outside this camera's view")
    if roi[2] * roi[3] > config.max_area_frac * intrinsics.width_px * intrinsics.height_px:
        return DetectorPlan("tiles", None, False, "predicted region too large for an ROI")
    return DetectorPlan("roi", roi, False, "tracking")


def box_in_roi(box_xyxy, roi_xywh, tol_px: float = 1.0) -> bool:
    """Whether the box (x0, y0, x1, y1) lies inside the ROI (x, y, w, h), within tol_px."""
    x, y, w, h = roi_xywh
    if w <= 0 or h <= 0:
        return False
    return (box_xyxy[0] >= x - tol_px and box_xyxy[1] >= y - tol_px and box_xyxy[2] <= x + w + tol_px
            and box_xyxy[3] <= y + h + tol_px)
