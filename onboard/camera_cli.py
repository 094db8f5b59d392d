"""``skycap camera``: ``probe`` a capture source, ``serve`` a drone's camera over Zenoh, ``calibrate`` it
(:mod:`onboard.camera.calibration_cli`).

This module sits beside :mod:`onboard.camera`, not inside it: ``serve`` loads the agent's configuration
(:mod:`onboard.config`, which itself imports :mod:`onboard.camera`), and a sub-package of ``onboard`` must not
import back the module that imports it (the import-linter "acyclic siblings" contract).
"""

from __future__ import annotations

import argparse
import json
import logging

from skycap.config import add_config_args

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "camera",
        help="the drone's real camera: probe a source, serve it over Zenoh, calibrate it",
        description="Capture from V4L2, GStreamer, RTSP or a file with true capture timestamps. Sources: "
        "v4l2:/dev/video0, gst:<pipeline>, rtsp://host/path, file:<video or image folder>, sim:<drone_id>.",
    )
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])
    cam_sub = p.add_subparsers(dest="camera_command", metavar="SUBCOMMAND")
    _add_probe(cam_sub)
    _add_serve(cam_sub)
    from onboard.camera.calibration_cli import add_parser as add_calibrate

    add_calibrate(cam_sub)


def _add_probe(cam_sub: argparse._SubParsersAction) -> None:
    p = cam_sub.add_parser(
        "probe",
        help="read a source for a few seconds: resolution, fps, frame-interval jitter, latency, drops",
        description="Open SOURCE, read it for --seconds after its first frame and print what it delivered. "
        "Example: skycap camera probe 'gst:videotestsrc is-live=true' --seconds 5",
    )
    p.add_argument("source", help="v4l2:/dev/video0, gst:<pipeline>, rtsp://..., file:<path> or a path, sim:<drone_id>")
    p.add_argument("--seconds", type=float, default=5.0, help="how long to read after the first frame (default 5)")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.add_argument("--size", default=None, metavar="WxH", help="request this frame size (v4l2) / scale to it")
    p.add_argument("--rate", type=float, default=0.0, help="request this frame rate (v4l2) / replay rate (file)")
    p.add_argument("--latency-s", type=float, default=0.0,
                   help="latency subtracted from arrival times for sources without capture timestamps")
    p.add_argument("--fleet", default="default", help="fleet of a sim:<drone_id> source")
    p.add_argument("--zenoh-connect", default=None, help="Zenoh endpoint to join for a sim source")
    p.add_argument("--zenoh-keys", default=None, help="fleet folder from `skycap keys` for a sim source")
    p.set_defaults(func=_run_probe)


def _parse_size(text: str | None) -> tuple[int, int]:
    from onboard.camera.errors import CameraSourceError

    if not text:
        return 0, 0
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise CameraSourceError(f"--size {text!r}: write it as WIDTHxHEIGHT, e.g. 1280x720") from None
    return w, h


def _run_probe(args: argparse.Namespace) -> int:
    from onboard.camera.config import CameraConfig
    from onboard.camera.probe import format_report, probe
    from onboard.camera.sources import open_source, parse_source

    kind, uri = parse_source(args.source)
    w, h = _parse_size(args.size)
    cfg = CameraConfig(source=kind, uri=uri, width_px=w, height_px=h, rate_hz=args.rate, latency_s=args.latency_s)
    transport = None
    if kind == "sim" and args.zenoh_connect:
        from comms.transport import TransportConfig

        transport = TransportConfig.local_peer(args.zenoh_connect, keys_dir=args.zenoh_keys or "")
    src = open_source(cfg, fleet=args.fleet, transport=transport, open_now=False)
    report = probe(src, args.seconds)
    if args.json:
        print(json.dumps(report.to_dict(), indent=2))
    else:
        print(format_report(report))
    return 0 if report.frames else 1


def _add_serve(cam_sub: argparse._SubParsersAction) -> None:
    p = cam_sub.add_parser(
        "serve",
        help="capture the drone's camera and publish it over Zenoh (camera/image, thumb, info, status)",
        description="Run the camera service of an agent config (its [camera], fleet, drone_id and [transport]) "
        "until SIGTERM/SIGINT. Example: skycap camera serve --config agent.toml --set camera.uri='/dev/video2'",
    )
    add_config_args(p)
    p.add_argument("--drone-id", default=None, help="this drone's id (drone_1, drone_2 ...)")
    p.add_argument("--fleet", default=None, help="fleet id")
    p.add_argument("--zenoh-connect", default=None, help="Zenoh endpoint to join, e.g. tls/127.0.0.1:7447")
    p.add_argument("--zenoh-keys", default=None, help="fleet folder from `skycap keys` (transport.security.keys_dir)")
    p.set_defaults(func=_run_serve)


def _run_serve(args: argparse.Namespace) -> int:
    from comms.transport import local_peer_overrides
    from onboard.camera.service import serve
    from onboard.config import AgentConfig
    from skycap.config import config_from_args

    extra = {
        "drone_id": args.drone_id,
        "fleet": args.fleet,
        **local_peer_overrides(args.zenoh_connect, args.zenoh_keys),
    }
    cfg = config_from_args(AgentConfig, args, extra)
    return serve(cfg)
