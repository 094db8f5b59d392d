"""skycap messages: the typed, versioned contract between drones, ground station and tools.

Every message is a :class:`msgspec.Struct` carrying a :class:`Header` (schema version, sender, time
of measurement, time of sending) and is encoded as MessagePack with a ``type`` tag
(:mod:`shared_msgs.codec`). The same bytes travel over Zenoh and are written to the flight recorder's
MCAP files (message encoding ``msgpack``).

Conventions (once, for every message): positions and velocities in the flight's local **NED** world
frame (metres, m/s) unless a field says otherwise; rotations as quaternions ``q_*`` in (w, x, y, z)
order; 4x4 transforms ``T_a_b`` row-major, flattened to 16 floats, mapping b coordinates to a;
camera frame = OpenCV optical (x right, y down, z forward); pixel coordinates with the origin at the
top-left pixel's corner; times in nanoseconds since the UNIX epoch (``*_ns``).

Versioning: each message type has ``SCHEMA_VERSION``; a change of fields bumps it and the golden
encodings in ``tests/msgs/golden/``. Decoders refuse other versions with a clear error, except the older ones a
type lists in ``READABLE_VERSIONS`` (fields only added, with defaults), which decode as the current version.
"""

from __future__ import annotations

import time
from typing import ClassVar, Literal

import msgspec

__all__ = [
    "Header",
    "Message",
    "VehicleState",
    "CameraInfo",
    "CameraFrame",
    "CameraStatus",
    "GimbalAttitude",
    "BoundingBox",
    "Detections",
    "PersonKeypoints",
    "Keypoints2D",
    "TargetEstimate",
    "FormationPlan",
    "OrbitPlan",
    "GeofenceZone",
    "KeepOutZone",
    "Command",
    "CommandAck",
    "Health",
    "RecorderStatus",
    "DetectorStatus",
    "VehicleTruth",
    "SimTruth",
    "MESSAGE_TYPES",
    "now_ns",
]


def now_ns() -> int:
    """Wall-clock time in ns since the UNIX epoch (the time base of every ``*_ns`` field)."""
    return time.time_ns()


class Header(msgspec.Struct, kw_only=True):
    """Carried by every message."""

    schema_version: int  #: version of this message type's schema
    sender_id: str  #: "drone_1", "gcs", "sim", ...
    t_measurement_ns: int  #: when the content was measured (image capture, state estimate time)
    t_sent_ns: int  #: when it was sent (set by the transport at publication)
    seq: int = 0  #: per sender and topic sequence number


class Message(msgspec.Struct, kw_only=True, tag_field="type"):
    """Base of all messages; subclasses set ``tag`` (the wire ``type``) and ``SCHEMA_VERSION``."""

    SCHEMA_VERSION: ClassVar[int] = 1
    #: older schema versions this build still decodes, as the current version: those whose fields are a subset of
    #: today's (fields added since then have defaults), so that recorded flights stay readable
    READABLE_VERSIONS: ClassVar[tuple[int, ...]] = ()
    header: Header

    @classmethod
    def make_header(cls, sender_id: str, t_measurement_ns: int | None = None, seq: int = 0) -> Header:
        t = now_ns() if t_measurement_ns is None else int(t_measurement_ns)
        return Header(schema_version=cls.SCHEMA_VERSION, sender_id=sender_id, t_measurement_ns=t, t_sent_ns=t, seq=seq)


LandedState = Literal["unknown", "on_ground", "in_air", "taking_off", "landing"]


class VehicleState(Message, tag="vehicle_state"):
    """The autopilot's own estimate of the vehicle (what MAVSDK telemetry reports), NED world frame."""

    SCHEMA_VERSION: ClassVar[int] = 1
    position_ned_m: tuple[float, float, float]
    velocity_ned_m_s: tuple[float, float, float]
    q_world_body: tuple[float, float, float, float]  #: body FRD -> NED, (w, x, y, z)
    position_cov_m2: tuple[float, float, float] = (1.0, 1.0, 1.0)  #: diagonal (n, e, d) variance
    attitude_cov_rad2: tuple[float, float, float] = (3e-4, 3e-4, 3e-4)  #: diagonal (roll, pitch, yaw)
    velocity_cov_m2_s2: tuple[float, float, float] = (0.01, 0.01, 0.01)  #: diagonal (n, e, d) variance
    latitude_deg: float = 0.0
    longitude_deg: float = 0.0
    altitude_amsl_m: float = 0.0
    gps_fix_type: int = 0  #: MAVLink GPS_FIX_TYPE (3 = 3D fix)
    gps_num_satellites: int = 0
    battery_remaining_frac: float = 1.0  #: 0..1
    battery_voltage_v: float = 0.0
    flight_mode: str = "unknown"  #: MAVSDK FlightMode name, e.g. "OFFBOARD", "HOLD"
    armed: bool = False
    landed_state: LandedState = "unknown"
    health_ok: bool = False  #: global position, home position and armable all ok


class CameraInfo(Message, tag="camera_info"):
    """Intrinsics, distortion and mount extrinsics of one camera."""

    SCHEMA_VERSION: ClassVar[int] = 1
    camera_id: str
    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    distortion_model: Literal["none", "plumb_bob"] = "none"
    distortion: tuple[float, ...] = ()  #: plumb_bob: (k1, k2, p1, p2, k3)
    T_body_cam: tuple[float, ...] = ()  #: 16 floats, camera optical -> body FRD, at zero gimbal angles
    gimbal_pitch_rad: float = 0.0  #: current commanded gimbal pitch (negative = down)
    gimbal_yaw_rad: float = 0.0


class CameraFrame(Message, tag="camera_frame"):
    """One compressed camera image; ``header.t_measurement_ns`` is the capture time (the middle of the exposure
    where the source says when it was, in the system realtime clock; see ``onboard.camera`` for each source's
    latency model).

    Version 2 added ``exposure_s`` and ``source`` (version 1 decodes with them None / "")."""

    SCHEMA_VERSION: ClassVar[int] = 2
    READABLE_VERSIONS: ClassVar[tuple[int, ...]] = (1,)
    camera_id: str
    frame_index: int  #: the source's own frame counter (a gap = frames the source dropped)
    encoding: Literal["jpeg", "png"]
    width_px: int
    height_px: int
    data: bytes
    T_world_cam: tuple[float, ...] = ()  #: 16 floats: camera pose at capture from the vehicle's estimate
    exposure_s: float | None = None  #: exposure time when the source reports it, else None
    source: str = ""  #: the capture source, e.g. "sim", "v4l2:/dev/video0", "gstreamer", "rtsp", "file"


class CameraStatus(Message, tag="camera_status"):
    """Health of one camera capture (published by the camera service at ~1 Hz)."""

    SCHEMA_VERSION: ClassVar[int] = 1
    camera_id: str
    source: str  #: e.g. "v4l2:/dev/video0", "rtsp://...", "gstreamer", "file:flight.mp4"
    connected: bool
    frames: int  #: frames delivered since the service started
    dropped: int  #: frames lost (source counter gaps + frames the service could not keep up with)
    reconnects: int = 0
    rate_hz: float = 0.0  #: measured delivery rate over the last period
    latency_s: float = 0.0  #: the latency model subtracted from arrival times (0 when the source timestamps)
    detail: str = ""  #: why it is disconnected / the last error, empty when fine


class GimbalAttitude(Message, tag="gimbal_attitude"):
    """The gimbal's reported attitude (MAVLink GIMBAL_DEVICE_ATTITUDE_STATUS via MAVSDK's gimbal plugin);
    ``header.t_measurement_ns`` = the time of the gimbal's report. Angles of the camera's forward axis:
    roll and pitch relative to the horizon (negative pitch = down), ``yaw_rad`` relative to the vehicle's heading
    (MAVSDK "forward" frame), ``yaw_north_rad`` relative to north (NED)."""

    SCHEMA_VERSION: ClassVar[int] = 1
    gimbal_id: int
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    yaw_north_rad: float
    angular_velocity_rad_s: tuple[float, float, float] = (0.0, 0.0, 0.0)  #: roll, pitch, yaw rates


class BoundingBox(msgspec.Struct, kw_only=True):
    """An axis-aligned box in full-image pixels with per-edge variance (px^2)."""

    x_min_px: float
    y_min_px: float
    x_max_px: float
    y_max_px: float
    score: float
    var_x_min_px2: float = 0.0
    var_y_min_px2: float = 0.0
    var_x_max_px2: float = 0.0
    var_y_max_px2: float = 0.0
    label: str = "person"


class Detections(Message, tag="detections"):
    """Person detections in one frame with the camera pose (and covariance) at capture.

    Version 2 added ``ground_down_m`` (version 1 decodes with it None)."""

    SCHEMA_VERSION: ClassVar[int] = 2
    READABLE_VERSIONS: ClassVar[tuple[int, ...]] = (1,)
    camera_id: str
    frame_index: int
    detector: str  #: model name; "simulated" for the simulator's detector
    mode: Literal["roi", "tiles", "full", "simulated"]
    boxes: list[BoundingBox]
    width_px: int
    height_px: int
    T_world_cam: tuple[float, ...]  #: 16 floats
    T_world_cam_cov: tuple[float, ...] = ()  #: 36 floats, 6x6 (position m, rotation rad) or empty
    roi_px: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)  #: x, y, w, h searched (0s = whole)
    #: the ground's down coordinate (m) in the sender's reported frame, the frame of ``T_world_cam``: its reported
    #: down while it stood on the take-off ground, so that a constant height error of its estimate moves camera and
    #: ground together; None = unknown (the receiver uses its configured ground)
    ground_down_m: float | None = None


class PersonKeypoints(msgspec.Struct, kw_only=True):
    """COCO-17 keypoints of one person: 17 (u, v) in pixels and 17 confidences in [0, 1]."""

    keypoints_px: tuple[float, ...]  #: 34 floats, u0, v0, u1, v1, ...
    confidence: tuple[float, ...]  #: 17 floats
    box: BoundingBox | None = None


class Keypoints2D(Message, tag="keypoints2d"):
    """2D keypoints of the people in one frame from one detector."""

    SCHEMA_VERSION: ClassVar[int] = 1
    camera_id: str
    frame_index: int
    detector: str
    simulated: bool  #: True for the simulator's noisy ground-truth projections
    persons: list[PersonKeypoints]


class TargetEstimate(Message, tag="target_estimate"):
    """The fused estimate of the person's position (NED) at ``header.t_measurement_ns``: the capture time of
    the newest detection fused (a receiver predicts to its own time with ``velocity_ned_m_s``); ``status``
    is as of ``header.t_sent_ns``."""

    SCHEMA_VERSION: ClassVar[int] = 1
    position_ned_m: tuple[float, float, float]
    velocity_ned_m_s: tuple[float, float, float]
    covariance: tuple[float, ...]  #: 36 floats, 6x6 over (position, velocity)
    status: Literal["tracking", "predicting", "lost", "searching"] = "tracking"
    num_sources: int = 0


class FormationPlan(Message, tag="formation_plan"):
    """A drone's planned positions over the formation MPC's horizon, shared with its teammates (they keep
    their own plans on their side of the bisecting planes: buffered Voronoi cells)."""

    SCHEMA_VERSION: ClassVar[int] = 1
    t0_ns: int  #: time of the first position
    dt_s: float  #: step between positions
    positions_ned_m: tuple[float, ...]  #: (N + 1) x 3 floats, north, east, down of each step
    fallback: bool = False  #: the plan is the brake-and-hold fallback


class GeofenceZone(msgspec.Struct, kw_only=True):
    """The fence a plan must stay inside (OrbitPlan version 2): a vertical cylinder in the flight's local NED
    world frame (north / east metres from the flight's origin, the frame of ``center_ned_m``) and an altitude band
    (metres above the take-off ground, the frame of ``altitude_m``)."""

    center_ne_m: tuple[float, float] = (0.0, 0.0)
    radius_m: float = 30.0
    min_altitude_m: float = 2.0
    max_altitude_m: float = 30.0


class KeepOutZone(msgspec.Struct, kw_only=True):
    """An area no drone may enter (OrbitPlan version 2): a vertical cylinder of infinite height (a building, a
    tree line, spectators), in the flight's local NED world frame (north / east metres from the origin)."""

    name: str = ""
    north_m: float
    east_m: float
    radius_m: float


PlanMode = Literal["", "orbit", "track"]


class OrbitPlan(Message, tag="orbit_plan"):
    """A shared orbit around a point: every drone flies its phase slot of one circle.

    Drone k's angle at time t: ``phase_offset_rad[k] + direction * angular_speed_rad_s * (t - start_time)``,
    measured in the NED horizontal plane from north towards east; its position is
    ``center + radius * (cos, sin, 0)`` at ``down = -altitude_m``; camera yaw points at the centre.

    ``mode = "track"`` (a tracking formation, flown by agents configured ``mode = "track"``): ``center_ned_m`` is
    the operator's start guess of the person, ``radius_m`` / ``altitude_m`` the stand-off kept from the person,
    ``phase_offset_rad`` the slot angles around the person (``angular_speed_rad_s`` 0). ``mode = ""``: not said
    (version 1, or a sender that does not care): each agent flies it in its own configured mode.

    Version 2 added ``mode``, ``geofence`` and ``keepout_zones`` (version 1 decodes with "", None and none):
    the agents refuse a plan that leaves the fence or enters a zone, and keep their setpoints out of them.
    """

    SCHEMA_VERSION: ClassVar[int] = 2
    READABLE_VERSIONS: ClassVar[tuple[int, ...]] = (1,)
    plan_id: str
    center_ned_m: tuple[float, float, float]  #: the point looked at (person position on the ground)
    radius_m: float
    altitude_m: float  #: height above the ground (down = -altitude_m)
    angular_speed_rad_s: float  #: >= 0
    direction: Literal[1, -1] = 1  #: 1 = clockwise seen from above (north -> east), -1 = anticlockwise
    start_time_ns: int = 0  #: shared phase origin; 0 = "when received"
    phase_offset_rad: dict[str, float] = msgspec.field(default_factory=dict)  #: per drone id
    gimbal_pitch_rad: float | None = None  #: None = point the camera at the centre
    min_separation_m: float = 3.0
    max_speed_m_s: float = 5.0
    mode: PlanMode = ""  #: version 2: "orbit", "track" (tracking formation) or "" (not said)
    geofence: GeofenceZone | None = None  #: version 2: the fence the agents enforce (None: only their own limits)
    keepout_zones: list[KeepOutZone] = msgspec.field(default_factory=list)  #: version 2


CommandAction = Literal["arm", "takeoff", "start", "pause", "land", "return", "disarm"]


class Command(Message, tag="command"):
    """An operator command; ``target`` is a drone id or "*" for the whole fleet."""

    SCHEMA_VERSION: ClassVar[int] = 1
    command_id: str
    target: str
    action: CommandAction
    params: dict[str, float] = msgspec.field(default_factory=dict)
    max_age_s: float = 5.0  #: refused as stale if received later than this after t_sent_ns


class CommandAck(Message, tag="command_ack"):
    """The answer to a :class:`Command` (or to a plan: ``command_id`` = plan id)."""

    SCHEMA_VERSION: ClassVar[int] = 1
    command_id: str
    result: Literal["accepted", "refused", "completed", "failed"]
    reason: str = ""


class RecorderStatus(msgspec.Struct, kw_only=True):
    """An agent's flight recorder as its health reports it (Health version 2).

    ``recording`` False: no recording open (none configured, or a failed one not replaced yet: ``error`` says
    why). ``free_disk_bytes`` is the free space of the recording folder's file system (``shutil.disk_usage``,
    refreshed every few seconds; -1: not known)."""

    file: str = ""  #: the current recording's file name ("" when none is open)
    recording: bool = False
    bytes_written: int = 0  #: bytes the current recording has written (before compression of the file's chunks)
    messages_written: int = 0
    dropped: int = 0  #: messages dropped by the current recording (disk too slow: its queue was full)
    free_disk_bytes: int = -1
    ok: bool = True  #: False after a recording failure (``error``), until a new recording is open and working
    error: str = ""  #: why not ``ok`` / not ``recording``, or why ``free_disk_bytes`` is unknown ("" otherwise)


class DetectorStatus(msgspec.Struct, kw_only=True):
    """The onboard person detector as an agent's health reports it (Health version 2).

    ``required`` False: this drone flies without an onboard detector (orbit mode, simulated keypoints; or
    track mode with the simulator's detections) and ``model`` says so; True: an ONNX ``model`` is configured and
    ``loaded`` says whether its session is open."""

    required: bool
    loaded: bool = False
    model: str = ""  #: the model's name, or why there is none ("none (orbit mode: simulated keypoints)")
    rate_hz: float = 0.0  #: detections the detector delivered per second (0 when it has none)
    error: str = ""


class Health(Message, tag="health"):
    """Heartbeat and health of a process (agent, ground station, simulator).

    Version 2 added ``recorder`` and ``detector`` (agents fill them; version 1, from an older agent, decodes
    with both None: not reported)."""

    SCHEMA_VERSION: ClassVar[int] = 2
    READABLE_VERSIONS: ClassVar[tuple[int, ...]] = (1,)
    role: Literal["agent", "ground_station", "simulator", "tool"]
    state: str  #: e.g. agent state machine: "idle", "armed", "takeoff", "orbit", "landing", "landed"
    ok: bool = True
    warnings: list[str] = msgspec.field(default_factory=list)
    cpu_percent: float = 0.0
    rates_hz: dict[str, float] = msgspec.field(default_factory=dict)
    recorder: RecorderStatus | None = None  #: agents only (version 2); None: not reported
    detector: DetectorStatus | None = None  #: agents only (version 2); None: not reported


class VehicleTruth(msgspec.Struct, kw_only=True):
    """Simulator ground truth of one vehicle (NED) and of its camera gimbal (true angles: pitch relative to the
    horizon, negative = down; yaw relative to the vehicle's heading, positive = right)."""

    drone_id: str
    position_ned_m: tuple[float, float, float]
    velocity_ned_m_s: tuple[float, float, float]
    q_world_body: tuple[float, float, float, float]
    gimbal_pitch_rad: float = 0.0
    gimbal_yaw_rad: float = 0.0  #: SimTruth version 2


class SimTruth(Message, tag="sim_truth"):
    """Simulator ground truth: vehicles and the person (COCO-17 joints, NED metres).

    Version 2 added ``VehicleTruth.gimbal_yaw_rad`` (version 1 decodes with it 0: the gimbal looked ahead)."""

    SCHEMA_VERSION: ClassVar[int] = 2
    READABLE_VERSIONS: ClassVar[tuple[int, ...]] = (1,)
    vehicles: list[VehicleTruth]
    person_joints_ned_m: tuple[float, ...]  #: 51 floats, COCO-17 (x, y, z) each
    person_root_ned_m: tuple[float, float, float]
    person_heading_rad: float = 0.0
    person_motion: str = ""  #: name of the clip being played


MESSAGE_TYPES: tuple[type[Message], ...] = (
    VehicleState,
    CameraInfo,
    CameraFrame,
    CameraStatus,
    GimbalAttitude,
    Detections,
    Keypoints2D,
    TargetEstimate,
    FormationPlan,
    OrbitPlan,
    Command,
    CommandAck,
    Health,
    SimTruth,
)
