"""``skycap harness``: the flight-grade evaluation harness (:mod:`evaluation.harness`)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from skycap.config import add_config_args


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "harness", help="score the multiview reconstruction on real motion with the flight's errors and the real models",
        description="Virtual drones orbit a mocap clip with the simulator's estimator errors (RTK or GPS grade); the "
        "keypoint models run on the rendered Anny person; the multiview fit is scored (metrics.json). Example: "
        "skycap harness --motion ../shared/data/mocap/cmu/002/002_05.bvh --frames 25 --out out/h")
    p.add_argument("--motion", required=True, type=Path, help="CMU CC_Base-rig BVH file (the ground truth)")
    p.add_argument("--out", required=True, type=Path, help="output folder (metrics.json, config.toml, exports)")
    p.add_argument("--keypoints", choices=("models", "sim"), default=None,
                   help="models (default): the keypoint models on rendered images; sim: simulated 2D")
    p.add_argument("--pose-errors", choices=("flight", "white"), default=None,
                   help="flight (default): the simulator's estimator errors; white: the original harness's white noise")
    p.add_argument("--position-grade", choices=("rtk", "gps"), default=None, help="estimator preset (default rtk)")
    p.add_argument("--drones", type=int, default=None, help="number of drones (default 3)")
    p.add_argument("--frames", type=int, default=None, help="output frames at the camera rate (default 100 = 10 s at 10 Hz)")
    p.add_argument("--start", type=int, default=None, help="first output frame (default 0)")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--no-export", action="store_true", help="write metrics.json and config.toml only")
    add_config_args(p)
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from evaluation.harness import HarnessConfig, run_harness
    from skycap.config import config_from_args
    from skycap.errors import SkycapError

    extra = {"motion": str(args.motion), "out": str(args.out), "keypoints": args.keypoints,
             "pose_errors": args.pose_errors, "position_grade": args.position_grade, "synth.drones": args.drones,
             "frames": args.frames, "start": args.start, "seed": args.seed, "export": False if args.no_export else None}
    cfg = config_from_args(HarnessConfig, args, extra)
    if (Path(cfg.out) / "metrics.json").exists():
        raise SkycapError(f"{cfg.out} already holds a harness run (metrics.json); pass a new --out folder")
    m = run_harness(cfg)
    keys = ("keypoints_source", "position_grade", "frames", "clip_s", "mpjpe_mm", "pa_mpjpe_mm", "w_mpjpe_mm",
            "root_err_mm", "camera_pos_err_m_before", "camera_pos_err_m_after", "camera_rot_err_deg_before",
            "camera_rot_err_deg_after", "render_ms_per_frame", "keypoints_ms_per_frame", "fit_seconds")
    print(json.dumps({k: m[k] for k in keys if k in m}, indent=2))
    return 0
