"""The ground-station app's typed configuration (TOML + ``--set``, like every skycap job)."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class NetworkConfig:
    """The listener the drones connect to: the app opens the fleet's rendezvous on ``endpoint``
    (``tls/...`` with ``keys_dir``, the fleet folder from ``skycap keys``; the app presents its ``gcs`` certificate)."""

    endpoint: str = "tls/127.0.0.1:7447"
    keys_dir: str = ""  #: fleet folder (``skycap keys``); empty = INSECURE plaintext (warned, debugging only)
    heartbeat_hz: float = 2.0


@dataclass
class UiConfig:
    table_hz: float = 5.0  #: fleet table / map refresh
    thumbs_hz: float = 1.0  #: thumbnail grid refresh (only visible tiles are decoded)
    stale_s: float = 2.0  #: a drone's values older than this are greyed with their age
    link_lost_s: float = 5.0  #: no message for this long = link lost (alert)
    command_timeout_s: float = 5.0  #: a drone that has not answered a command by then: "no answer"
    map_half_width_m: float = 32.0  #: the map's initial half extent


@dataclass
class ChecklistConfig:
    """Pre-flight checks per drone (gate arming / take-off unless the operator overrides, which is logged)."""

    min_battery_frac: float = 0.5
    min_gps_fix_type: int = 3  #: MAVLink GPS_FIX_TYPE: 3 = 3D fix
    max_position_std_m: float = 2.0
    require_camera: bool = True
    #: the recording folder's free space each drone reports (Health v2 ``recorder.free_disk_bytes``) must be at least
    #: this (GB = 1e9 bytes); a drone that does not report it (an older agent) fails the check
    min_free_disk_gb: float = 2.0
    #: the "detector" check passes for a drone that reports an ONNX model loaded, or that it needs none (orbit mode,
    #: the simulator's detections); True: every drone must run an onboard detector (one that needs none fails)
    require_detector: bool = False


@dataclass
class GeofenceConfig:
    """The operator's fence: a circle around the origin and an altitude band (the agents enforce their own)."""

    radius_m: float = 30.0
    min_altitude_m: float = 2.0
    max_altitude_m: float = 30.0


@dataclass
class GsConfig:
    fleet: str = "default"
    flights_dir: str = "flights"  #: where recorded flights are listed from
    #: the event log (alerts, commands and answers, checklist overrides) is also appended to this file (relative to
    #: ``flights_dir`` unless absolute); "" = kept in the window only
    event_log: str = "gs-events.log"
    network: NetworkConfig = field(default_factory=NetworkConfig)
    ui: UiConfig = field(default_factory=UiConfig)
    checklist: ChecklistConfig = field(default_factory=ChecklistConfig)
    geofence: GeofenceConfig = field(default_factory=GeofenceConfig)
