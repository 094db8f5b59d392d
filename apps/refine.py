"""``skycap refine FLIGHT_DIR``: the offline smoother over a recorded flight (AirCap step 2).

A thin layer over :func:`reconstruction.track.flight.refine_flight` (the whole flight, or ``--sortie N``). Writes
``refined_track.npz`` and ``refined_track.json`` into the flight folder (see :mod:`reconstruction.track.flight`) and
prints the evaluation table when the flight holds the simulator's ``truth.mcap``. ``--reconstruct`` then runs the
multiview reconstruction with the refined drone positions (:func:`reconstruction.api.reconstruct_flight`,
``MultiviewConfig(use_refined_poses=True)``) into ``FLIGHT_DIR/reconstruction_refined`` and scores it beside the
plain one (``FLIGHT_DIR/reconstruction``, when present) against the truth.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "refine",
        help="smooth a recorded flight offline: refined person track, drone positions and regions of interest",
        description="Robust RTS smoother over every drone's person detections of a recorded flight (AirCap's offline "
        "step 2). Example: skycap refine flights/demo --reconstruct",
    )
    p.add_argument("flight_dir", type=Path, help="flight folder written by the onboard recorder / skycap demo")
    p.add_argument("--person-height-m", type=float, default=None,
                   help="person box height prior (default: the flight's config.toml track.person_height_m, else 1.69)")
    p.add_argument("--camera-position-sigma-m", type=float, default=None,
                   help="camera position std for detections without pose covariance (default: from the flight's RTK/GPS setting)")
    p.add_argument("--measurement-mode", choices=("height_prior", "height_and_ground", "bearing", "onboard"), default="height_prior",
                   help="box -> 3D model (default height_prior: exactly invariant to the drones' offsets)")
    p.add_argument("--offset-tau-s", type=float, default=None, help="correlation time of the drones' position offsets (default 60)")
    p.add_argument("--sortie", type=int, default=None, metavar="N",
                   help="smooth only sortie N of each drone (default: the whole flight, every sortie in order)")
    p.add_argument("--reconstruct", action="store_true",
                   help="then run the multiview reconstruction with the refined drone positions and score it against the truth")
    p.set_defaults(func=_cmd_refine)


def _cmd_refine(args: argparse.Namespace) -> int:
    # imported here: `skycap --help` imports every command module, and these pull in the reconstruction stack
    from evaluation.refined import reconstruct_with_refined_poses
    from flightdata.folder import FlightFolder
    from reconstruction.track.flight import RefineConfig, format_evaluation, refine_flight
    from reconstruction.track.smoother import SmootherConfig

    smoother = SmootherConfig()
    if args.offset_tau_s is not None:
        smoother = dataclasses.replace(smoother, offset_tau_s=args.offset_tau_s)
    mode = None if args.measurement_mode == "onboard" else args.measurement_mode
    cfg = RefineConfig(smoother=smoother, person_height_m=args.person_height_m,
                       camera_position_sigma_m=args.camera_position_sigma_m, measurement_mode=mode)
    flight = FlightFolder(args.flight_dir)
    s = refine_flight(flight, cfg, sortie=args.sortie).summary
    print(f"refined {len(s['drones'])} drones over {s['span_s']:.1f} s: {s['frames_used']} frames used, "
          f"{s['frames_rejected']} rejected, {s['frames_downweighted']} down-weighted -> {flight.refined_npz_path}")
    if "evaluation" in s:
        print(format_evaluation(s["evaluation"]))
    if args.reconstruct:
        rec = reconstruct_with_refined_poses(flight, sortie=args.sortie)
        print(json.dumps(rec, indent=2))
    return 0
