"""Fixed example of every skycap message type, and the writer of their golden encodings.

The golden files ``tests/msgs/golden/<type>.msgpack`` are the committed wire format: ``test_golden.py``
fails when ``encode(example)`` no longer gives those bytes, or those bytes no longer decode to the example.
After a deliberate schema change (bump the type's ``SCHEMA_VERSION``), regenerate them with

    python tests/msgs/golden_fixtures.py            # or: SKYCAP_REGEN_GOLDEN=1 python -m pytest tests/msgs

and commit the new files together with the change.
"""

from __future__ import annotations

import sys
from pathlib import Path

from shared_msgs.codec import encode
from shared_msgs.messages import (
    MESSAGE_TYPES,
    BoundingBox,
    CameraFrame,
    CameraInfo,
    CameraStatus,
    GimbalAttitude,
    Command,
    CommandAck,
    Detections,
    DetectorStatus,
    Header,
    Health,
    Keypoints2D,
    GeofenceZone,
    KeepOutZone,
    Message,
    OrbitPlan,
    PersonKeypoints,
    RecorderStatus,
    SimTruth,
    TargetEstimate,
    FormationPlan,
    VehicleState,
    VehicleTruth,
)

GOLDEN_DIR = Path(__file__).resolve().parent / "golden"

T0 = 1_767_225_600_000_000_000  # 2026-01-01T00:00:00Z in ns
EYE4 = (1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0)
T_WORLD_CAM = (0.0, -0.5, 0.866, 12.5, 1.0, 0.0, 0.0, -3.25, 0.0, 0.866, 0.5, -6.0, 0.0, 0.0, 0.0, 1.0)


def hdr(cls: type[Message], sender: str, seq: int, dt_ms: int = 0) -> Header:
    return Header(
        schema_version=cls.SCHEMA_VERSION, sender_id=sender, t_measurement_ns=T0 + dt_ms * 1_000_000,
        t_sent_ns=T0 + dt_ms * 1_000_000 + 2_500_000, seq=seq,
    )


BOX = BoundingBox(
    x_min_px=101.5, y_min_px=52.25, x_max_px=163.0, y_max_px=240.75, score=0.875,
    var_x_min_px2=4.0, var_y_min_px2=2.25, var_x_max_px2=4.5, var_y_max_px2=9.0,
)


def examples() -> dict[str, Message]:
    """One fully populated message per type, keyed by the type tag (deterministic: no clock, no RNG)."""
    ex: list[Message] = [
        VehicleState(
            header=hdr(VehicleState, "drone_1", 41),
            position_ned_m=(10.5, -3.25, -12.0), velocity_ned_m_s=(1.5, 0.25, -0.125),
            q_world_body=(0.9238795325112867, 0.0, 0.0, 0.3826834323650898),
            position_cov_m2=(0.25, 0.25, 0.5), attitude_cov_rad2=(1e-4, 1e-4, 4e-4),
            velocity_cov_m2_s2=(0.01, 0.01, 0.04),
            latitude_deg=47.397742, longitude_deg=8.545594, altitude_amsl_m=500.25,
            gps_fix_type=3, gps_num_satellites=12, battery_remaining_frac=0.82, battery_voltage_v=15.9,
            flight_mode="OFFBOARD", armed=True, landed_state="in_air", health_ok=True,
        ),
        CameraInfo(
            header=hdr(CameraInfo, "drone_1", 3), camera_id="cam0", width_px=1280, height_px=720,
            fx_px=900.5, fy_px=901.25, cx_px=640.0, cy_px=360.0, distortion_model="plumb_bob",
            distortion=(-0.1, 0.01, 0.001, -0.0005, 0.0), T_body_cam=EYE4, gimbal_pitch_rad=-0.5236, gimbal_yaw_rad=0.0,
        ),
        CameraFrame(
            header=hdr(CameraFrame, "drone_1", 120), camera_id="cam0", frame_index=119, encoding="jpeg",
            width_px=1280, height_px=720, data=bytes(range(256)) + b"\xff\xd9", T_world_cam=T_WORLD_CAM,
            exposure_s=0.004, source="v4l2:/dev/video0",
        ),
        CameraStatus(
            header=hdr(CameraStatus, "drone_1", 7), camera_id="cam0", source="rtsp://127.0.0.1:8554/cam",
            connected=False, frames=1200, dropped=3, reconnects=1, rate_hz=29.75, latency_s=0.0625,
            detail="no frame for 2.0 s; reconnecting",
        ),
        GimbalAttitude(
            header=hdr(GimbalAttitude, "drone_1", 250), gimbal_id=1, roll_rad=0.0, pitch_rad=-0.5, yaw_rad=0.125,
            yaw_north_rad=1.5, angular_velocity_rad_s=(0.0, 0.25, -0.125),
        ),
        Detections(
            header=hdr(Detections, "drone_1", 120), camera_id="cam0", frame_index=119, detector="yolo-person-s",
            mode="roi", boxes=[BOX], width_px=1280, height_px=720, T_world_cam=T_WORLD_CAM,
            T_world_cam_cov=tuple(0.01 if i % 7 == 0 else 0.0 for i in range(36)), roi_px=(64.0, 0.0, 320.0, 320.0),
            ground_down_m=0.375,
        ),
        Keypoints2D(
            header=hdr(Keypoints2D, "sim", 120), camera_id="cam0", frame_index=119, detector="simulated",
            simulated=True,
            persons=[PersonKeypoints(
                keypoints_px=tuple(100.0 + 0.5 * i for i in range(34)),
                confidence=tuple(round(0.5 + 0.025 * i, 3) for i in range(17)), box=BOX,
            )],
        ),
        TargetEstimate(
            header=hdr(TargetEstimate, "drone_2", 57), position_ned_m=(20.0, 5.5, 0.0),
            velocity_ned_m_s=(0.75, -0.25, 0.0), covariance=tuple(0.1 if i % 7 == 0 else 0.0 for i in range(36)),
            status="tracking", num_sources=3,
        ),
        FormationPlan(
            header=hdr(FormationPlan, "drone_3", 41), t0_ns=T0 + 2_000_000_000, dt_s=0.1,
            positions_ned_m=tuple(0.5 * i for i in range(9)), fallback=False,
        ),
        OrbitPlan(
            header=hdr(OrbitPlan, "gcs", 2), plan_id="plan-0002", center_ned_m=(20.0, 5.5, 0.0), radius_m=12.0,
            altitude_m=8.0, angular_speed_rad_s=0.15, direction=-1, start_time_ns=T0 + 5_000_000_000,
            phase_offset_rad={"drone_1": 0.0, "drone_2": 2.0943951023931953, "drone_3": 4.1887902047863905},
            gimbal_pitch_rad=None, min_separation_m=4.0, max_speed_m_s=6.0, mode="track",
            geofence=GeofenceZone(center_ne_m=(5.0, -2.5), radius_m=40.0, min_altitude_m=3.0, max_altitude_m=25.0),
            keepout_zones=[KeepOutZone(name="tree line", north_m=-10.0, east_m=12.5, radius_m=4.0)],
        ),
        Command(
            header=hdr(Command, "gcs", 9), command_id="cmd-0009", target="*", action="takeoff",
            params={"altitude_m": 8.0}, max_age_s=3.0,
        ),
        CommandAck(
            header=hdr(CommandAck, "drone_3", 4), command_id="cmd-0009", result="refused",
            reason="stale: sent 7.2 s ago, max_age_s=3.0",
        ),
        Health(
            header=hdr(Health, "drone_1", 88), role="agent", state="orbit", ok=False,
            warnings=["ground station heartbeat lost"], cpu_percent=37.5,
            rates_hz={"state": 50.0, "camera/image": 10.0},
            recorder=RecorderStatus(file="sortie-003_drone_1.mcap", recording=True, bytes_written=52_428_800,
                                    messages_written=123_456, dropped=7, free_disk_bytes=8_589_934_592, ok=True),
            detector=DetectorStatus(required=True, loaded=True, model="yolox_s_person.onnx", rate_hz=9.5),
        ),
        SimTruth(
            header=hdr(SimTruth, "sim", 600),
            vehicles=[VehicleTruth(drone_id="drone_1", position_ned_m=(10.0, -3.0, -12.0),
                                   velocity_ned_m_s=(1.5, 0.25, 0.0), q_world_body=(1.0, 0.0, 0.0, 0.0),
                                   gimbal_pitch_rad=-0.5, gimbal_yaw_rad=0.25)],
            person_joints_ned_m=tuple(0.125 * i for i in range(51)), person_root_ned_m=(20.0, 5.5, -0.95),
            person_heading_rad=1.25, person_motion="cmu_02_01",
        ),
    ]
    out = {type(m).__struct_config__.tag: m for m in ex}
    assert set(out) == {t.__struct_config__.tag for t in MESSAGE_TYPES}, "add an example for every message type"
    return out


def golden_path(tag: str) -> Path:
    return GOLDEN_DIR / f"{tag}.msgpack"


def write_golden() -> list[Path]:
    """(Re)write every golden file from :func:`examples`; returns the paths."""
    GOLDEN_DIR.mkdir(parents=True, exist_ok=True)
    paths = []
    for tag, msg in examples().items():
        p = golden_path(tag)
        p.write_bytes(encode(msg))
        paths.append(p)
    return paths


if __name__ == "__main__":
    for p in write_golden():
        print(f"wrote {p} ({p.stat().st_size} bytes)")
    sys.exit(0)
