"""``skycap eval monocular`` and ``skycap eval monocular-sweep`` (one orbiting drone, DroCap pipeline).

Examples::

    skycap eval monocular --motion ../shared/data/mocap/cmu/002/002_05.bvh --out out/mono
    skycap eval monocular --motion a.bvh b.bvh --angular-velocity 40 --noise-px 3 --out out/mono40
    skycap eval monocular-sweep --motion a.bvh b.bvh --omegas 0 10 25 45 --out out/fig2

Both write ``metrics.json`` (per clip and mean) and the resolved ``config.toml`` into ``--out``; the sweep
also writes ``sweep.json`` and DroCap's Figure 2 as ``figure2.png``.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

log = logging.getLogger(__name__)

_SETUP_FLAGS = {
    "angular_velocity": ("setup.angular_velocity_deg_s", float, "orbit angular velocity, deg/s (default 25)"),
    "radius": ("setup.radius_m", float, "orbit radius, m (default 4)"),
    "altitude": ("setup.altitude_m", float, "camera height above the ground, m (default 2)"),
    "camera": ("setup.camera", str, "synthetic camera: perspective (default) or orthographic"),
    "noise_px": ("setup.noise_px", float, "2D Gaussian noise std, px (default 5)"),
    "outliers": ("setup.outlier_rate", float, "fraction of keypoints that are gross outliers (default 0.10)"),
    "swaps": ("setup.swap_rate", float, "fraction of frames with left/right swapped detections (default 0)"),
    "misses": ("setup.miss_rate", float, "fraction of missing keypoints (default 0)"),
    "fps": ("setup.fps", float, "camera frame rate, Hz (default 24)"),
    "seconds": ("setup.clip_seconds", float, "clip length from the start, s (default 10)"),
    "seed": ("setup.seed", int, "random seed"),
}


def _add_common(p: argparse.ArgumentParser) -> None:
    from skycap.config import add_config_args

    p.add_argument("--motion", nargs="+", type=Path, required=True, help="CMU CC_Base BVH file(s)")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    for name, (_, typ, hlp) in _SETUP_FLAGS.items():
        p.add_argument("--" + name.replace("_", "-"), dest=name, type=typ, default=None, help=hlp)
    p.add_argument("--no-extended", action="store_true", help="skip the extended BA (beyond the paper)")
    p.add_argument("--no-perspective", action="store_true", help="skip the perspective BA with the drone's camera poses")
    add_config_args(p)


def _config(args):
    from reconstruction.monocular.evaluate import EvalMonocularConfig
    from skycap.config import config_from_args

    extra = {key: getattr(args, name) for name, (key, _, _) in _SETUP_FLAGS.items()}
    if args.no_extended:
        extra["extended"] = False
    if args.no_perspective:
        extra["perspective"] = False
    return config_from_args(EvalMonocularConfig, args, extra)


def register_eval(eval_sub: argparse._SubParsersAction) -> None:
    p = eval_sub.add_parser("monocular", help="monocular (one orbiting drone) reconstruction on real mocap")
    _add_common(p)
    p.set_defaults(func=_run_eval)
    s = eval_sub.add_parser("monocular-sweep", help="monocular error vs orbit angular velocity (DroCap Fig. 2)")
    _add_common(s)
    s.add_argument("--omegas", nargs="+", type=float, default=[0, 5, 10, 15, 25, 35, 50], help="deg/s values")
    s.set_defaults(func=_run_sweep)


def _mean_rows(rows: list[dict]) -> dict:
    import numpy as np

    keys = [k for k, v in rows[0].items() if isinstance(v, (int, float)) and k != "frames"]
    mean = {k: float(np.mean([r[k] for r in rows if k in r])) for k in keys}
    mean["frames"] = int(sum(r["frames"] for r in rows))
    groups = rows[0]["per_joint_mm"].keys()
    mean["per_joint_mm"] = {g: float(np.mean([r["per_joint_mm"][g] for r in rows])) for g in groups}
    return mean


def _run_eval(args) -> int:
    from tqdm import tqdm

    from reconstruction.monocular.dictionary import load_dictionary
    from reconstruction.monocular.evaluate import evaluate_clip, write_json
    from skycap.config import save_config

    cfg = _config(args)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    save_config(cfg, out / "config.toml")
    d = load_dictionary(cfg.dictionary or None)
    rows = [evaluate_clip(m, cfg, d) for m in tqdm(args.motion, desc="clips", disable=len(args.motion) < 2)]
    result = dict(_mean_rows(rows)) if len(rows) > 1 else dict(rows[0])
    result["clips"] = rows
    result["dictionary_clips"] = list(d.clips)
    write_json(out / "metrics.json", result)
    print(f"{'clip':<12}{'frames':>7}{'init':>8}{'BA':>8}{'BA-paper':>10}{'BA-noart':>10}{'BA-ext':>8}{'BA-persp':>10}{'world':>8}"
          f"{'model':>8}{'world':>8}  (PA-MPJPE mm, 12 joints; BA-paper = the paper's update order; world = W-MPJPE (no alignment) of the "
          "column before; model = the body model fitted after BA-persp)")  # fmt: skip
    for r in rows + ([dict(result, motion="MEAN")] if len(rows) > 1 else []):
        print(f"{Path(r['motion']).stem:<12}{r['frames']:>7}{r['pa_mpjpe_mm_init']:>8.1f}{r['pa_mpjpe_mm_ba']:>8.1f}"
              f"{r.get('pa_mpjpe_mm_ba_paper_order', float('nan')):>10.1f}{r.get('pa_mpjpe_mm_ba_no_articulation', float('nan')):>10.1f}{r.get('pa_mpjpe_mm_ba_extended', float('nan')):>8.1f}"
              f"{r.get('pa_mpjpe_mm_ba_perspective', float('nan')):>10.1f}{r.get('w_mpjpe_mm_ba_perspective', float('nan')):>8.1f}"
              f"{r.get('pa_mpjpe_mm_model', float('nan')):>8.1f}{r.get('w_mpjpe_mm_model', float('nan')):>8.1f}")  # fmt: skip
    print(f"wrote {out / 'metrics.json'}")
    return 0


def _run_sweep(args) -> int:
    from reconstruction.monocular.evaluate import plot_sweep, sweep, sweep_means, write_json
    from skycap.config import save_config

    cfg = _config(args)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    save_config(cfg, out / "config.toml")
    rows = sweep([str(m) for m in args.motion], cfg, args.omegas)
    means = sweep_means(rows)
    write_json(out / "sweep.json", {"means": means, "rows": rows})
    write_json(out / "metrics.json", means)
    s = cfg.setup
    plot_sweep(means, out / "figure2.png", title=f"{len(args.motion)} CMU clips, {s.camera}, {s.noise_px:g} px noise, "
               f"{100 * s.outlier_rate:g}% outliers, r={s.radius_m:g} m")  # fmt: skip
    print(f"{'deg/s':>6}{'init':>8}{'BA':>8}{'BA-paper':>10}{'BA-noart':>10}{'BA-ext':>8}{'BA-persp':>10}{'model':>8}")
    for i, w in enumerate(means["angular_velocity_deg_s"]):
        print(f"{w:>6g}" + "".join(f"{means[k][i]:>{n}.1f}" if k in means else " " * n for k, n in
              [("pa_mpjpe_mm_init", 8), ("pa_mpjpe_mm_ba", 8), ("pa_mpjpe_mm_ba_paper_order", 10), ("pa_mpjpe_mm_ba_no_articulation", 10), ("pa_mpjpe_mm_ba_extended", 8),
               ("pa_mpjpe_mm_ba_perspective", 10), ("pa_mpjpe_mm_model", 8)]))  # fmt: skip
    print(f"wrote {out / 'figure2.png'}")
    return 0


# ----------------------------------------------------------------------------------- skycap reconstruct


def add_reconstruct_args(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("monocular")
    g.add_argument("--mono-out", type=Path, default=None, help="monocular output folder (default FLIGHT_DIR/reconstruction_monocular)")
    g.add_argument("--mono-camera", default=None, help="camera (drone) name to use (default: the first)")
    g.add_argument("--mono-variant", choices=("paper", "extended", "perspective"), default="perspective",
                   help="monocular BA: the paper's, extended with the drone attitude prior, or perspective in the world "
                        "with the drone's camera poses (default)")  # fmt: skip
    g.add_argument("--mono-body-radius-m", type=float, default=None,
                   help="assumed RMS joint radius of the person, m (default: the dictionary mean pose's; "
                        "perspective: scales the adult bone-length prior by radius / 0.55 m)")  # fmt: skip


def reconstruct_config(args: argparse.Namespace):
    """``skycap reconstruct --method monocular`` options -> (:class:`MonocularRunConfig`, output folder or None)."""
    from reconstruction.monocular.reconstruct import MonocularRunConfig

    cfg = MonocularRunConfig(camera=args.mono_camera, variant=args.mono_variant or "perspective",
                             body_rms_radius_m=args.mono_body_radius_m)
    return cfg, args.mono_out
