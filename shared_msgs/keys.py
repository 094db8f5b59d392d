"""Zenoh key expressions: the one place that names them.

Layout: ``skycap/v1/<fleet>/<node>/<topic>`` where ``<node>`` is a drone id (``drone_1``...), ``gcs`` (the
ground station / fleet client) or ``sim`` (the simulator). The ``v1`` segment is the wire generation:
messages inside carry their own per-type schema version.

| key | message | publisher | notes |
| --- | --- | --- | --- |
| ``skycap/v1/<fleet>/<drone>/state`` | VehicleState | agent | autopilot estimate, >= 10 Hz on the wire (recorder keeps all) |
| ``skycap/v1/<fleet>/<drone>/health`` | Health | agent | 1-2 Hz heartbeat |
| ``skycap/v1/<fleet>/<drone>/camera_info`` | CameraInfo | camera | on change and 1 Hz |
| ``skycap/v1/<fleet>/<drone>/camera/image`` | CameraFrame | camera | full rate, drone-local (recorder, detector) |
| ``skycap/v1/<fleet>/<drone>/camera/thumb`` | CameraFrame | camera | small JPEG at ~1 Hz for the ground station |
| ``skycap/v1/<fleet>/<drone>/camera/status`` | CameraStatus | camera | ~1 Hz: connected, frames, dropped |
| ``skycap/v1/<fleet>/<drone>/gimbal`` | GimbalAttitude | agent | the gimbal's reported attitude, recorded |
| ``skycap/v1/<fleet>/<drone>/detections`` | Detections | agent | shared with teammates |
| ``skycap/v1/<fleet>/<drone>/keypoints2d`` | Keypoints2D | detector | |
| ``skycap/v1/<fleet>/<drone>/sim/keypoints2d`` | Keypoints2D (simulated=True) | simulator camera | noisy GT, detector "sim_noisy_gt" |
| ``skycap/v1/<fleet>/<drone>/sim/keypoints2d_gt`` | Keypoints2D (simulated=True) | simulator camera | exact projections, detector "ground_truth" |
| ``skycap/v1/<fleet>/<drone>/sim/detections`` | Detections (mode "simulated") | simulator camera | simulated person boxes |
| ``skycap/v1/<fleet>/<drone>/target`` | TargetEstimate | agent | |
| ``skycap/v1/<fleet>/<drone>/formation/plan`` | FormationPlan | agent (track mode) | MPC plan shared with teammates |
| ``skycap/v1/<fleet>/<drone>/ack`` | CommandAck | agent | answers to commands and plans |
| ``skycap/v1/<fleet>/gcs/cmd`` | Command | ground station | ``target`` field selects drones |
| ``skycap/v1/<fleet>/gcs/plan`` | OrbitPlan | ground station | latest plan (agents also query it) |
| ``skycap/v1/<fleet>/gcs/health`` | Health | ground station | the ground-station heartbeat agents watch |
| ``skycap/v1/<fleet>/sim/truth`` | SimTruth | simulator | ground truth, simulation only |

Liveliness tokens: ``skycap/v1/<fleet>/<node>/alive`` is declared by every running node; watching
``skycap/v1/<fleet>/*/alive`` tells who is present (a token vanishes when its process closes its session
or dies: ``Transport.declare_alive`` / ``Transport.watch_presence``).

Latest values: ``gcs/plan`` (and anything published with ``Transport.publish(..., latch=True)``) is also
served to queries (``Transport.query_latest``), so a node that starts late gets the current plan.

How processes find each other (default: every process a Zenoh peer, multicast scouting off, joining the
rendezvous peer on ``tcp/127.0.0.1:7447`` that the simulator / launcher opens): see :mod:`comms.transport`.
The recorder's MCAP channel of a key is :func:`flightdata.recorder.channel_name`.
"""

from __future__ import annotations

import re

PREFIX = "skycap/v1"
GCS = "gcs"
SIM = "sim"

_SEGMENT = re.compile(r"^[A-Za-z0-9_\-]+$")


def valid_segment(name: str) -> bool:
    """Whether ``name`` can be a key segment (fleet or node id): letters, digits, '_' or '-'."""
    return bool(_SEGMENT.match(str(name)))


def _check(name: str, what: str) -> str:
    if not _SEGMENT.match(name):
        raise ValueError(f"{what} {name!r} must be letters, digits, '_' or '-' (it becomes a Zenoh key segment)")
    return name


def node_key(fleet: str, node: str, topic: str) -> str:
    """``skycap/v1/<fleet>/<node>/<topic>``; topic may contain '/'."""
    return f"{PREFIX}/{_check(fleet, 'fleet id')}/{_check(node, 'node id')}/{topic}"


def drone_key(fleet: str, drone_id: str, topic: str) -> str:
    return node_key(fleet, drone_id, topic)


def gcs_key(fleet: str, topic: str) -> str:
    return node_key(fleet, GCS, topic)


def sim_key(fleet: str, topic: str) -> str:
    return node_key(fleet, SIM, topic)


def all_drones_key(fleet: str, topic: str) -> str:
    """Matches ``topic`` of every node: ``skycap/v1/<fleet>/*/<topic>``."""
    return f"{PREFIX}/{_check(fleet, 'fleet id')}/*/{topic}"


def alive_key(fleet: str, node: str) -> str:
    """The liveliness token key of ``node``."""
    return node_key(fleet, node, ALIVE)


def parse_key(key: str) -> tuple[str, str, str]:
    """(fleet, node, topic) of a skycap key; ValueError for anything else."""
    parts = str(key).split("/")
    if len(parts) < 5 or "/".join(parts[:2]) != PREFIX:
        raise ValueError(f"{key!r} is not a skycap key ({PREFIX}/<fleet>/<node>/<topic>)")
    return parts[2], parts[3], "/".join(parts[4:])


# Topic names (suffixes after the node).
STATE = "state"
HEALTH = "health"
CAMERA_INFO = "camera_info"
CAMERA_IMAGE = "camera/image"
CAMERA_THUMB = "camera/thumb"
CAMERA_STATUS = "camera/status"
GIMBAL = "gimbal"
DETECTIONS = "detections"
KEYPOINTS2D = "keypoints2d"
SIM_KEYPOINTS2D = "sim/keypoints2d"
SIM_KEYPOINTS2D_GT = "sim/keypoints2d_gt"
SIM_DETECTIONS = "sim/detections"
TARGET = "target"
FORMATION_PLAN = "formation/plan"
ACK = "ack"
CMD = "cmd"
PLAN = "plan"
TRUTH = "truth"
ALIVE = "alive"
