"""``skycap eval multiview`` and the multiview hooks of ``skycap reconstruct`` (see :mod:`reconstruction.cli`)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from skycap.config import add_config_args


def register_eval(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("multiview", help="fly virtual drones around real motion, reconstruct it, score it")
    p.add_argument("--motion", required=True, type=Path, help="CMU CC_Base-rig BVH file (the ground truth)")
    p.add_argument("--out", required=True, type=Path, help="output folder (metrics.json, BVH, NPZ, CSV, RRD, config.toml)")
    p.add_argument("--method", choices=("product", "paper"), default=None, help="fitting method (default product)")
    p.add_argument("--drones", type=int, default=None, help="number of drones (default 3)")
    p.add_argument("--radius", type=float, default=None, help="orbit radius m (default 8)")
    p.add_argument("--altitude", type=float, default=None, help="orbit altitude m (default 8)")
    p.add_argument("--speed", type=float, default=None, help="orbit speed m/s (default 1)")
    p.add_argument("--camera-rate", type=float, default=None, help="camera frames per second (default 30)")
    p.add_argument("--sync", action="store_true", help="synchronise the cameras (default: not synchronised)")
    p.add_argument("--noise-px", type=float, default=None, help="2D keypoint noise sigma px (default 5)")
    p.add_argument("--outlier-rate", type=float, default=None, help="fraction of wrong keypoints (default 0.1)")
    p.add_argument("--swap-rate", type=float, default=None, help="fraction of left/right-swapped detections (default 0.02)")
    p.add_argument("--miss-rate", type=float, default=None, help="fraction of missing keypoints (default 0.05)")
    p.add_argument("--detectors", type=int, default=None, help="2D detectors per camera (default 1)")
    p.add_argument("--cam-pos-noise", type=float, default=None, help="drone camera position error RMS m (default 0.5)")
    p.add_argument("--cam-rot-noise", type=float, default=None, help="drone camera rotation error RMS deg (default 2)")
    p.add_argument("--cam-drift", type=float, default=None, help="fraction of the camera error that is bias/drift (default 0)")
    p.add_argument("--frames", type=int, default=None, help="output frames (at the camera rate; default 300, 0 = all)")
    p.add_argument("--start", type=int, default=None, help="first output frame (default 0)")
    p.add_argument("--device", default=None, help="torch device, e.g. cpu or cuda (default cpu)")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--no-export", action="store_true", help="write metrics.json and config.toml only")
    add_config_args(p)
    p.set_defaults(func=_eval)


def _eval(args: argparse.Namespace) -> int:
    from reconstruction.multiview.evaluate import EvalConfig, run_eval
    from skycap.config import config_from_args

    extra = {
        "motion": str(args.motion), "out": str(args.out), "fit.method": args.method, "fit.device": args.device,
        "synth.drones": args.drones, "synth.radius_m": args.radius, "synth.altitude_m": args.altitude,
        "synth.speed_mps": args.speed, "synth.camera_rate_hz": args.camera_rate,
        "synth.unsync": False if args.sync else None, "synth.noise_px": args.noise_px,
        "synth.outlier_rate": args.outlier_rate, "synth.swap_rate": args.swap_rate, "synth.miss_rate": args.miss_rate,
        "synth.detectors": args.detectors, "synth.camera_pos_noise_m": args.cam_pos_noise,
        "synth.camera_rot_noise_deg": args.cam_rot_noise, "synth.camera_noise_drift_fraction": args.cam_drift,
        "frames": args.frames, "start": args.start, "seed": args.seed, "export": False if args.no_export else None,
    }  # fmt: skip
    cfg = config_from_args(EvalConfig, args, extra)
    m = run_eval(cfg)
    keys = ("method", "frames", "mpjpe_mm", "pa_mpjpe_mm", "w_mpjpe_mm", "root_err_mm", "keypoints_source",
            "position_grade", "camera_pos_err_m_before", "camera_pos_err_m_after",
            "camera_rot_err_deg_before", "camera_rot_err_deg_after", "fit_seconds")  # fmt: skip
    print(json.dumps({k: m[k] for k in keys}, indent=2))
    return 0


def add_reconstruct_args(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("multiview")
    g.add_argument("--mv-fit", choices=("product", "paper"), default="product", help="multiview fitting method (default product)")
    g.add_argument("--mv-device", default="cpu", help="torch device for the multiview fit (default cpu)")
    g.add_argument("--mv-out", type=Path, default=None, help="multiview output folder (default FLIGHT_DIR/reconstruction)")
    g.add_argument("--mv-use-refined-poses", action="store_true",
                   help="drone positions minus the offsets of FLIGHT_DIR/refined_track.npz (run `skycap refine` first); "
                        "off by default: it helps on GPS-grade flights' pose, not on RTK-grade ones (reconstruction/track/README.md)")


def reconstruct_config(args: argparse.Namespace):
    """``skycap reconstruct --method multiview`` options -> (:class:`MultiviewConfig`, output folder or None)."""
    from reconstruction.multiview.fit import FitConfig
    from reconstruction.multiview.run import MultiviewConfig

    fit = FitConfig(method=args.mv_fit or "product", device=args.mv_device or "cpu")
    return MultiviewConfig(fit=fit, use_refined_poses=bool(args.mv_use_refined_poses)), args.mv_out
