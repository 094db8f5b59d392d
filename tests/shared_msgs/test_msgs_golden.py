"""Golden encodings: the committed bytes of every message type are the wire format.

A change that alters them (renamed/reordered/retyped field, new tag) fails here. If the change is
deliberate: bump the type's SCHEMA_VERSION, run ``python tests/msgs/golden_fixtures.py`` (or set
``SKYCAP_REGEN_GOLDEN=1``) and commit the regenerated files with the change.
"""

from __future__ import annotations

import os

import msgspec
import pytest

from golden_fixtures import GOLDEN_DIR, examples, golden_path, write_golden
from shared_msgs.codec import TYPE_BY_TAG, decode, encode

EXAMPLES = examples()

if os.environ.get("SKYCAP_REGEN_GOLDEN") == "1":
    write_golden()


def test_one_golden_file_per_message_type() -> None:
    on_disk = sorted(p.stem for p in GOLDEN_DIR.glob("*.msgpack"))
    assert on_disk == sorted(TYPE_BY_TAG), (
        "tests/msgs/golden/ must hold exactly one <type>.msgpack per message type; "
        "run python tests/msgs/golden_fixtures.py after adding or removing a type"
    )


@pytest.mark.parametrize("tag", sorted(EXAMPLES))
def test_encoding_matches_golden_bytes(tag: str) -> None:
    golden = golden_path(tag).read_bytes()
    assert encode(EXAMPLES[tag]) == golden, (
        f"the wire encoding of {tag} changed; if deliberate, bump its SCHEMA_VERSION and regenerate the golden "
        f"files (python tests/msgs/golden_fixtures.py)"
    )


@pytest.mark.parametrize("tag", sorted(EXAMPLES))
def test_golden_bytes_decode_to_the_example(tag: str) -> None:
    golden = golden_path(tag).read_bytes()
    msg = decode(golden, type(EXAMPLES[tag]))
    assert msg == EXAMPLES[tag]
    raw = msgspec.msgpack.decode(golden)  # generic MessagePack view: tag and header are on the wire
    assert raw["type"] == tag
    assert raw["header"]["schema_version"] == type(EXAMPLES[tag]).SCHEMA_VERSION
    assert set(raw) == {"type", *type(EXAMPLES[tag]).__struct_fields__}


def test_older_readable_versions_decode_as_the_current_version() -> None:
    """Recorded flights stay readable: Detections version 1 (before ``ground_down_m``) decodes as version 2 with
    the new field at its default; a version a type does not list is still refused, naming both versions."""
    from shared_msgs import Detections
    from shared_msgs.codec import MessageError

    old = (GOLDEN_DIR / "older" / "detections.v1.msgpack").read_bytes()
    assert msgspec.msgpack.decode(old)["header"]["schema_version"] == 1
    msg = decode(old, Detections)
    assert msg.header.schema_version == Detections.SCHEMA_VERSION == 2 and msg.ground_down_m is None
    current = EXAMPLES["detections"]
    assert msgspec.structs.replace(msg, header=current.header, ground_down_m=current.ground_down_m) == current
    raw = msgspec.msgpack.decode(old)
    raw["header"]["schema_version"] = 0
    with pytest.raises(MessageError, match="schema version 0"):
        decode(msgspec.msgpack.encode(raw), Detections)


def test_camera_frame_version_1_decodes_as_version_2() -> None:
    """CameraFrame version 1 (before ``exposure_s`` and ``source``) decodes with them at their defaults."""
    from shared_msgs import CameraFrame

    msg = decode((GOLDEN_DIR / "older" / "camera_frame.v1.msgpack").read_bytes(), CameraFrame)
    assert msg.header.schema_version == CameraFrame.SCHEMA_VERSION == 2
    assert msg.exposure_s is None and msg.source == ""
    assert msg.data == EXAMPLES["camera_frame"].data and msg.T_world_cam == EXAMPLES["camera_frame"].T_world_cam


def test_sim_truth_version_1_decodes_as_version_2() -> None:
    """SimTruth version 1 (before ``VehicleTruth.gimbal_yaw_rad``) decodes with the gimbal yaw 0."""
    from shared_msgs import SimTruth

    msg = decode((GOLDEN_DIR / "older" / "sim_truth.v1.msgpack").read_bytes(), SimTruth)
    assert msg.header.schema_version == SimTruth.SCHEMA_VERSION == 2
    v, ex = msg.vehicles[0], EXAMPLES["sim_truth"].vehicles[0]
    assert v.gimbal_yaw_rad == 0.0 and v.gimbal_pitch_rad == ex.gimbal_pitch_rad and v.position_ned_m == ex.position_ned_m


def test_health_version_1_decodes_as_version_2_with_recorder_and_detector_not_reported() -> None:
    """Health version 1 (an older agent: before ``recorder`` and ``detector``) decodes with both None, which the
    ground station shows as "not reported"; version 2 round-trips its nested statuses."""
    from shared_msgs import DetectorStatus, Health, RecorderStatus

    old = (GOLDEN_DIR / "older" / "health.v1.msgpack").read_bytes()
    assert msgspec.msgpack.decode(old)["header"]["schema_version"] == 1
    msg = decode(old, Health)
    assert msg.header.schema_version == Health.SCHEMA_VERSION == 2
    assert msg.recorder is None and msg.detector is None
    ex = EXAMPLES["health"]
    assert msg.state == ex.state and msg.warnings == ex.warnings and msg.rates_hz == ex.rates_hz
    v2 = decode(encode(ex), Health)
    assert isinstance(v2.recorder, RecorderStatus) and v2.recorder.free_disk_bytes == 8_589_934_592
    assert isinstance(v2.detector, DetectorStatus) and v2.detector.loaded and v2.detector.model == "yolox_s_person.onnx"


def test_orbit_plan_version_1_decodes_as_version_2_without_mode_fence_or_zones() -> None:
    """OrbitPlan version 1 (before ``mode``, ``geofence`` and ``keepout_zones``) decodes with mode "" (each agent
    flies it in its own mode), no fence and no zones; version 2 round-trips the fence and the zones."""
    from shared_msgs import GeofenceZone, KeepOutZone, OrbitPlan

    old = (GOLDEN_DIR / "older" / "orbit_plan.v1.msgpack").read_bytes()
    assert msgspec.msgpack.decode(old)["header"]["schema_version"] == 1
    msg = decode(old, OrbitPlan)
    assert msg.header.schema_version == OrbitPlan.SCHEMA_VERSION == 2
    assert msg.mode == "" and msg.geofence is None and msg.keepout_zones == []
    ex = EXAMPLES["orbit_plan"]
    assert msg.phase_offset_rad == ex.phase_offset_rad and msg.radius_m == ex.radius_m
    v2 = decode(encode(ex), OrbitPlan)
    assert v2.mode == "track" and isinstance(v2.geofence, GeofenceZone) and v2.geofence.radius_m == 40.0
    assert isinstance(v2.keepout_zones[0], KeepOutZone) and v2.keepout_zones[0].name == "tree line"
