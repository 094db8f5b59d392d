"""``skycap refine FLIGHT_DIR``: the offline smoother over a recorded flight (AirCap step 2).

Writes ``refined_track.npz`` and ``refined_track.json`` into the flight folder (see
:mod:`reconstruction.track.flight`) and prints the evaluation table when the flight holds the simulator's
``truth.mcap``. ``--reconstruct`` then runs the multiview reconstruction with the refined drone positions
(``reconstruction/multiview/flight.py``, ``use_refined_poses``) into ``FLIGHT_DIR/reconstruction_refined``
and scores it beside the plain one (``FLIGHT_DIR/reconstruction``, when present) against the truth.
"""

from __future__ import annotations

import argparse
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
    p.add_argument("--reconstruct", action="store_true",
                   help="then run the multiview reconstruction with the refined drone positions and score it against the truth")
    p.set_defaults(func=_cmd_refine)


def _cmd_refine(args: argparse.Namespace) -> int:
    import dataclasses

    from reconstruction.track.flight import format_evaluation, refine_flight
    from reconstruction.track.smoother import SmootherConfig

    cfg = SmootherConfig()
    if args.offset_tau_s is not None:
        cfg = dataclasses.replace(cfg, offset_tau_s=args.offset_tau_s)
    mode = None if args.measurement_mode == "onboard" else args.measurement_mode
    s = refine_flight(args.flight_dir, cfg, person_height_m=args.person_height_m,
                      camera_position_sigma_m=args.camera_position_sigma_m, measurement_mode=mode)
    print(f"refined {len(s['drones'])} drones over {s['span_s']:.1f} s: {s['frames_used']} frames used, "
          f"{s['frames_rejected']} rejected, {s['frames_downweighted']} down-weighted -> {args.flight_dir / 'refined_track.npz'}")
    if "evaluation" in s:
        print(format_evaluation(s["evaluation"]))
    if args.reconstruct:
        rec = reconstruct_with_refined_poses(args.flight_dir)
        print(json.dumps(rec, indent=2))
    return 0


def reconstruct_with_refined_poses(flight_dir: Path) -> dict:
    """Multiview reconstruction with the refined drone positions into ``reconstruction_refined/``; MPJPE of it
    and of the plain ``reconstruction/`` (when present) against the simulator truth; added to
    ``refined_track.json`` under ``reconstruction``."""
    from evaluation.flight import reconstruction_accuracy
    from reconstruction.multiview.flight import reconstruct_flight_dir
    from reconstruction.track.flight import REFINED_JSON

    flight_dir = Path(flight_dir)
    out = flight_dir / "reconstruction_refined"
    reconstruct_flight_dir(flight_dir, argparse.Namespace(mv_out=str(out), mv_use_refined_poses=True))
    js = flight_dir / REFINED_JSON
    summary = json.loads(js.read_text()) if js.is_file() else {}
    window = summary.get("evaluation", {}).get("fleet", {}).get("window_s")
    res = {"refined_poses": reconstruction_accuracy(flight_dir, out / "motion.npz", window_s=window)}
    plain = flight_dir / "reconstruction" / "motion.npz"
    if plain.is_file():
        res["reported_poses"] = reconstruction_accuracy(flight_dir, plain, window_s=window)
    res = {k: {kk: vv for kk, vv in v.items() if not kk.startswith("per_group")} for k, v in res.items()}
    if js.is_file():
        summary["reconstruction"] = res
        js.write_text(json.dumps(summary, indent=2))
    return res
