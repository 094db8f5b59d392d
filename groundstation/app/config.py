"""The ground-station app's typed configuration (TOML + ``--set``, like every skycap job)."""

from __future__ import annotations

from dataclasses import dataclass, field

from reconstruction.jobs.config import JobsConfig


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
    """The operator's fence: a circle of ``radius_m`` around the origin of the flight's local NED world frame
    (north / east metres from the flight's origin, the frame of every plan and drone position the app shows) and
    an altitude band (metres above the take-off ground). It is sent with every plan (OrbitPlan v2 ``geofence``):
    the app refuses a plan that leaves it, and so do the agents, which also keep their setpoints inside it."""

    radius_m: float = 30.0
    min_altitude_m: float = 2.0
    max_altitude_m: float = 30.0


@dataclass
class KeepOutZoneConfig:
    """An area no drone may enter: a vertical cylinder (infinite height) in the flight's local NED world frame,
    north / east metres from the flight's origin (the map's frame: north up, the origin at the fence's centre).
    Sent with every plan (OrbitPlan v2 ``keepout_zones``); the app and the agents refuse a plan whose orbit circle
    or formation slot enters one, and the agents keep their setpoints out of it. In TOML::

        [[keepout_zones]]
        name = "shed"
        north_m = 14.0
        east_m = -9.0
        radius_m = 4.0

    or ``--set 'keepout_zones=[{name="shed", north_m=14, east_m=-9, radius_m=4}]'``."""

    name: str = ""
    north_m: float = 0.0
    east_m: float = 0.0
    radius_m: float = 3.0


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
    keepout_zones: list[KeepOutZoneConfig] = field(default_factory=list)
    #: where "process flight" runs: a local worker process (default) or a Ray cluster (``jobs.runner = "ray"``,
    #: ``jobs.ray_address``)
    jobs: JobsConfig = field(default_factory=JobsConfig)
    #: ``--set`` overrides of the processing pipeline's ProcessConfig (``skycap process``), e.g.
    #: ``['keypoints.models=["movenet_lightning", "blazepose_full"]']``; empty = its defaults (the keypoint models)
    process_set: list[str] = field(default_factory=list)

    def validate(self) -> "GsConfig":
        """Refuse a fence or zone that cannot be flown (a :class:`skycap.config.ConfigError` naming it)."""
        import math

        from skycap.config import ConfigError

        g = self.geofence
        if not (g.radius_m > 0 and 0 <= g.min_altitude_m < g.max_altitude_m):
            raise ConfigError(f"geofence: radius_m ({g.radius_m}) must be > 0 and 0 <= min_altitude_m "
                              f"({g.min_altitude_m}) < max_altitude_m ({g.max_altitude_m})")
        for i, z in enumerate(self.keepout_zones):
            if not (all(math.isfinite(v) for v in (z.north_m, z.east_m, z.radius_m)) and z.radius_m > 0):
                raise ConfigError(f"keepout_zones[{i}] ({z.name or 'unnamed'}): north_m, east_m, radius_m must be "
                                  f"finite and radius_m > 0 (got {z.north_m}, {z.east_m}, {z.radius_m})")
        return self
