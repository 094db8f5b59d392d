"""The simulated camera of one drone as a Zenoh process (the network adapter of :class:`CameraNode`).

    skycap sim-camera --fleet demo --drone drone_1 [--zenoh-connect tcp/127.0.0.1:7447] [--config scene.toml] [--set camera.width_px=960]
    python -m simulator.scene.node --fleet demo --drone-id drone_1 ...          (same, without the skycap CLI)

Subscribes to the simulator's ground truth (``skycap/v1/<fleet>/sim/truth``, :class:`SimTruth`) and to the
drone's own state estimate (``skycap/v1/<fleet>/<drone>/state``, :class:`VehicleState`), and at
``camera.rate_hz`` renders the latest truth and publishes on ``skycap/v1/<fleet>/<drone>/<topic>``
(topics in :mod:`simulator.scene.camera_node`). A truth already rendered is not rendered again (a frozen
or stopped simulator produces no frames); a truth older than ``max_truth_age_s`` is not rendered.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np

from shared_msgs import keys
from shared_msgs.messages import Message, SimTruth, VehicleState
from simulator.scene.camera_node import CameraNode, CameraTruth, truth_from_messages
from simulator.scene.config import SceneConfig
from comms.transport import DEFAULT_RENDEZVOUS, Transport, TransportConfig
from skycap.config import add_config_args, load_config
from skycap.errors import SkycapError
from skycap.logsetup import setup_logging
import cv2

log = logging.getLogger(__name__)

__all__ = ["ZenohCameraAdapter", "run_camera_node", "add_node_args", "main"]


class ZenohCameraAdapter:
    """Latest truth/estimate from Zenoh as a truth source; publication as a sink."""

    def __init__(self, bus, fleet: str, drone_id: str, max_truth_age_s: float = 2.0):
        self.bus = bus
        self.fleet = fleet
        self.drone_id = drone_id
        self.max_truth_age_s = max_truth_age_s
        self._lock = threading.Lock()
        self._truth: SimTruth | None = None
        self._truth_rx_mono = 0.0
        self._estimate: VehicleState | None = None
        self._last_rendered_ns: int | None = None
        self._subs = [
            bus.subscribe(keys.sim_key(fleet, keys.TRUTH), self._on_truth, SimTruth),
            bus.subscribe(keys.drone_key(fleet, drone_id, keys.STATE), self._on_state, VehicleState),
        ]

    def _on_truth(self, rx) -> None:
        with self._lock:
            self._truth = rx.msg
            self._truth_rx_mono = time.monotonic()

    def _on_state(self, rx) -> None:
        with self._lock:
            self._estimate = rx.msg

    def truth(self) -> CameraTruth | None:
        with self._lock:
            truth, est, age = self._truth, self._estimate, time.monotonic() - self._truth_rx_mono
        if truth is None or age > self.max_truth_age_s or truth.header.t_measurement_ns == self._last_rendered_ns:
            return None
        ct = truth_from_messages(truth, self.drone_id, est)
        if ct is None:
            return None
        if ct.person_joints_ned_m is not None and not np.any(ct.person_joints_ned_m):
            ct.person_joints_ned_m = None  # all zeros = the simulator has no person
        self._last_rendered_ns = truth.header.t_measurement_ns
        return ct

    def publish(self, topic: str, msg: Message) -> None:
        self.bus.publish(keys.drone_key(self.fleet, self.drone_id, topic), msg, latch=(topic == keys.CAMERA_INFO))

    def close(self) -> None:
        for s in self._subs:
            s.close()


def run_camera_node(cfg: SceneConfig, fleet: str, drone_id: str, bus, stop: threading.Event) -> CameraNode:
    """Run one drone's camera on an open :class:`comms.transport.Transport` until ``stop`` is set."""
    adapter = ZenohCameraAdapter(bus, fleet, drone_id)
    node = CameraNode(drone_id, cfg, adapter.truth, adapter.publish)
    log.info(
        "%s camera: %dx%d at %.1f Hz, hfov %.0f deg, %s mount; truth from %s",
        drone_id, cfg.camera.width_px, cfg.camera.height_px, cfg.camera.rate_hz, cfg.camera.hfov_deg,
        cfg.camera.mount, keys.sim_key(fleet, keys.TRUTH),
    )  # fmt: skip
    try:
        node.run(stop)
    finally:
        adapter.close()
    return node


def add_node_args(p: argparse.ArgumentParser) -> None:

    p.add_argument("--fleet", required=True, help="fleet id (Zenoh key segment)")
    p.add_argument("--drone", "--drone-id", dest="drone", required=True, help="drone id, e.g. drone_1")
    p.add_argument("--zenoh-connect", default=None, help="Zenoh endpoint to join (default: the local rendezvous)")
    p.add_argument("--zenoh-keys", default=None, help="fleet folder from `skycap keys`: the camera presents its "
                   "drone's certificate (mutual TLS + access control)")
    add_config_args(p)


def run_from_args(args: argparse.Namespace) -> int:


    cfg = load_config(SceneConfig, getattr(args, "config", None), getattr(args, "set", [])).validate()
    cv2.setNumThreads(1)  # one camera process per drone on a shared machine: no OpenCV thread pool contention
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    bus = Transport.open(TransportConfig.local_peer(args.zenoh_connect or DEFAULT_RENDEZVOUS, args.zenoh_keys or ""),
                         f"{args.drone}_camera", identity=args.drone)
    try:
        run_camera_node(cfg, args.fleet, args.drone, bus, stop)
    finally:
        bus.close()
    return 0


def main(argv: list[str] | None = None) -> int:

    ap = argparse.ArgumentParser(prog="python -m simulator.scene.node", description=__doc__.splitlines()[0])
    add_node_args(ap)
    ap.add_argument("--log-level", default="INFO")
    args = ap.parse_args(argv)
    setup_logging(args.log_level)

    try:
        return run_from_args(args)
    except SkycapError as e:
        print(f"{Path(sys.argv[0]).name}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
