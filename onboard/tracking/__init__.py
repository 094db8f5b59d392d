"""Person tracking on board: detection -> 3D measurement, the cooperative (CDT) filter, the detector's ROI."""

from onboard.tracking.filter import CooperativeFilter, FilterStats, TrackEstimate, TrackerConfig, TrackerError
from onboard.tracking.measurement import (
    PERSON_HEIGHT_PRIOR_M,
    DegenerateGeometryError,
    MeasurementConfig,
    MeasurementError,
    PositionMeasurement,
    box_from_person,
    measurement_from_box,
    measurements_from_detections,
)
from onboard.tracking.roi import DetectorPlan, RoiConfig, plan_detection, roi_from_estimate

__all__ = [
    "PERSON_HEIGHT_PRIOR_M",
    "CooperativeFilter",
    "DegenerateGeometryError",
    "DetectorPlan",
    "FilterStats",
    "MeasurementConfig",
    "MeasurementError",
    "PositionMeasurement",
    "RoiConfig",
    "TrackEstimate",
    "TrackerConfig",
    "TrackerError",
    "box_from_person",
    "measurement_from_box",
    "measurements_from_detections",
    "plan_detection",
    "roi_from_estimate",
]
