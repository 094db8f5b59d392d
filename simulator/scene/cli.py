"""``skycap sim-camera``: one drone's simulated camera (see :mod:`simulator.scene.node`);
``skycap sim-preview``: the scene seen from an orbiting camera, as a video (:mod:`simulator.scene.preview`)."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "sim-camera",
        help="run one drone's simulated camera: render the simulator's truth, publish frames and simulated keypoints",
        description="Render the simulated person from one drone's camera at camera.rate_hz and publish CameraInfo, "
        "CameraFrame, simulated Keypoints2D/Detections on skycap/v1/<fleet>/<drone>/... (config: SceneConfig).",
    )
    from simulator.scene.node import add_node_args

    add_node_args(p)
    p.set_defaults(func=_run)
    register_preview(sub)


def _run(args: argparse.Namespace) -> int:
    from simulator.scene.node import run_from_args

    return run_from_args(args)


def register_preview(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "sim-preview",
        help="render the simulated person from an orbiting camera to a video + contact sheet (no flight)",
    )
    from simulator.scene.preview import add_args

    add_args(p)
    p.set_defaults(func=_run_preview)


def _run_preview(args: argparse.Namespace) -> int:
    from simulator.scene.preview import run_from_args

    return run_from_args(args)
