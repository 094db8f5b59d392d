"""The plug-in interface of the onboard perception pipeline."""

from __future__ import annotations

from typing import Protocol

from shared_msgs import CameraFrame, CameraInfo, Message, VehicleState

__all__ = ["PerceptionStage"]


class PerceptionStage(Protocol):
    """One step of the onboard perception pipeline (detector, keypoints, tracker ...).

    ``process(frame, info, state)`` gets a camera frame, the latest camera info and the vehicle state at
    hand, and returns ``(topic, message)`` pairs to publish on this drone's keys and record.
    """

    name: str

    def process(self, frame: CameraFrame, info: CameraInfo | None, state: VehicleState | None) -> list[tuple[str, Message]]: ...
