"""Learn the keypoint detectors' joint offsets (:mod:`reconstruction.multiview.offsets`) from simulated flights with
truth, and score them on flights they were not learned from.

Per detector and COCO-17 joint, the offset o (forward, left, up metres, in the body frame of the TRUE joints) that
minimises the detector's 2D residuals ``|Pi(T_true_cam, K, J_true + R_body_true @ o) - uv|`` (Cauchy, 8 px,
weighted by the keypoint's confidence) over every frame of every camera of the training flights: the true joints
at the frame's capture time projected through the true camera (the simulator's camera model on the true vehicle
pose and gimbal). The keypoints are the ones the fit saw: ``<flight>/reconstruction/capture.npz`` as ``skycap
process`` exported it (the fused models by default).

    python -m evaluation.learn_offsets learn F1 F2 F3 --out reconstruction/multiview/data/joint_offsets.toml
    python -m evaluation.learn_offsets crossval F1 F2 F3 F4 --out-dir out/offsets   # leave one flight out

``crossval``: for each flight, the offsets learned on the OTHER flights (other motions and body shapes), then the
flight refitted (:func:`evaluation.ablation.run_ablation`, recorded poses) without and with them and scored against
its truth (steady-orbit window).
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

from evaluation.ablation import _lever_arm, read_truth, run_ablation, true_camera_track
from flightdata.folder import FlightFolder
from reconstruction.capture import Capture, interpolate_poses
from reconstruction.multiview.fit import FitConfig
from reconstruction.multiview.offsets import JointOffsetTable, body_frame
from skycap.errors import SkycapError
from skycap.skeleton import COCO17_NAMES

log = logging.getLogger(__name__)

__all__ = ["OffsetObservations", "flight_observations", "solve_offsets", "learn_offsets", "crossval"]


class LearnOffsetsError(SkycapError):
    """A flight the offsets cannot be learned from."""


class OffsetObservations(dict):
    """detector name -> dict of arrays over keypoint observations (M,): ``joint``, ``uv`` (M, 2), ``conf``,
    ``J`` (M, 3) true joint, ``R_body`` (M, 3, 3), ``R_wc`` (M, 3, 3), ``p_wc`` (M, 3), ``K`` (M, 3, 3)."""

    def extend(self, other: "OffsetObservations") -> "OffsetObservations":
        for d, o in other.items():
            if d in self:
                self[d] = {k: np.concatenate([self[d][k], v]) for k, v in o.items()}
            else:
                self[d] = dict(o)
        return self


def capture_of(flight: FlightFolder) -> Capture:
    p = flight.reconstruction_dir("multiview") / "capture.npz"
    if not p.is_file():
        raise LearnOffsetsError(f"{p} does not exist: run `skycap process {flight.path}` (keypoint models) first")
    return Capture.load(p)


def flight_observations(flight_dir, capture: Capture | None = None, min_confidence: float = 0.05) -> OffsetObservations:
    """Every keypoint of the flight's capture with its true joint, true body frame and true camera."""
    flight = flight_dir if isinstance(flight_dir, FlightFolder) else FlightFolder(flight_dir)
    capture = capture_of(flight) if capture is None else capture
    names = [c.name for c in capture.cameras]
    truth = read_truth(flight.truth_path, names)
    lever = _lever_arm(flight, names)
    out = OffsetObservations()
    for c in capture.cameras:
        tf = c.t_frame_ns
        inside = (tf >= truth.t_ns[0]) & (tf <= truth.t_ns[-1])
        if not inside.any():
            continue
        tf = tf[inside]
        Tc = interpolate_poses(truth.t_ns, true_camera_track(truth, c.name, lever), tf)
        J = truth.joints_at(tf)  # (F, 17, 3)
        Rb = body_frame(J)
        K = c.K_at(tf)
        for d, det in enumerate(c.detectors):
            conf = c.confidence[inside, d]  # (F, 17)
            f_i, j_i = np.nonzero(conf > min_confidence)
            o = {"joint": j_i, "uv": c.keypoints_px[inside, d][f_i, j_i], "conf": conf[f_i, j_i], "J": J[f_i, j_i],
                 "R_body": Rb[f_i], "R_wc": Tc[f_i, :3, :3], "p_wc": Tc[f_i, :3, 3], "K": K[f_i]}
            out.extend(OffsetObservations({det: o}))
    return out


def _project(X, R_wc, p_wc, K):
    pc = np.einsum("mji,mj->mi", R_wc, X - p_wc)
    z = np.maximum(pc[:, 2:], 0.1)
    return np.einsum("mij,mj->mi", K[:, :2, :2], pc[:, :2] / z) + K[:, :2, 2]


def solve_offsets(obs: dict, robust_px: float = 8.0, min_obs: int = 20) -> tuple[np.ndarray, dict]:
    """Per joint, the offset (17, 3) m minimising the robust (Cauchy) 2D residual (see the module doc), and per joint the
    number of observations and the median residual before / after (px). Joints with fewer than ``min_obs``
    observations get 0."""
    off = np.zeros((17, 3))
    stats = {}
    for j in range(17):
        s = obs["joint"] == j
        if s.sum() < min_obs:
            continue
        J, Rb, R, p, K, uv, w = (obs[k][s] for k in ("J", "R_body", "R_wc", "p_wc", "K", "uv", "conf"))
        sw = np.sqrt(w)[:, None]

        def res(o):
            return ((_project(J + Rb @ o, R, p, K) - uv) * sw).ravel()

        r = least_squares(res, np.zeros(3), loss="cauchy", f_scale=robust_px, x_scale=0.05)
        off[j] = r.x
        e0 = np.linalg.norm(_project(J, R, p, K) - uv, axis=-1)
        e1 = np.linalg.norm(_project(J + Rb @ r.x, R, p, K) - uv, axis=-1)
        stats[COCO17_NAMES[j]] = {"n": int(s.sum()), "median_px_before": round(float(np.median(e0)), 2),
                                  "median_px_after": round(float(np.median(e1)), 2)}
    return off, stats


def learn_offsets(flights: list, captures: dict | None = None) -> tuple[JointOffsetTable, dict]:
    """The table learned from ``flights`` (flight folders; ``captures``: flight path -> Capture to use instead of
    the exported one), and per detector the per-joint fit statistics."""
    obs = OffsetObservations()
    for f in flights:
        obs.extend(flight_observations(f, (captures or {}).get(str(f))))
    if not obs:
        raise LearnOffsetsError(f"no keypoints in {flights}")
    offs, srcs, stats = {}, {}, {}
    for det, o in obs.items():
        offs[det], stats[det] = solve_offsets(o)
        srcs[det] = {"flights": [str(f) for f in flights], "motions": [_motion_of(FlightFolder(f)) for f in flights],
                     "camera_set": [_camera_set_of(FlightFolder(f)) for f in flights], "observations": int(len(o["joint"])),
                     "learned_by": "python -m evaluation.learn_offsets", "date": time.strftime("%Y-%m-%d")}
    return JointOffsetTable(offs, srcs), stats


def _motion_of(flight: FlightFolder) -> str:
    try:
        s = json.loads((flight.path / "summary.json").read_text())
        return str((s.get("motion") or {}).get("file", ""))
    except (OSError, ValueError):
        return ""


def _camera_set_of(flight: FlightFolder) -> str:
    """The flight's camera overrides (person model, body seed) from its ``config.toml``, as one string."""
    import tomllib

    try:
        return "; ".join(tomllib.loads((flight.path / "config.toml").read_text()).get("camera_set", []))
    except (OSError, ValueError):
        return ""


def crossval(flights: list, out_dir, fit: FitConfig | None = None, held_out: list | None = None) -> dict:
    """Leave one flight out: offsets learned on the others, the held-out flight fitted without and with them.
    ``held_out``: score only these of ``flights`` (default all; e.g. one per process). Each held-out flight's
    result goes to ``out_dir/crossval_<flight>.json`` and its table to ``out_dir/offsets_without_<flight>.toml``."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    fit = fit or FitConfig()
    folders = [FlightFolder(f) for f in flights]
    caps = {str(f.path): capture_of(f) for f in folders}
    results = {}
    chosen = None if held_out is None else {FlightFolder(h).path.resolve() for h in held_out}
    for k, held in enumerate(folders):
        if chosen is not None and held.path.resolve() not in chosen:
            continue
        train = [f.path for i, f in enumerate(folders) if i != k]
        table, _ = learn_offsets(train, {str(p): caps[str(p)] for p in train})
        tpath = table.save(out_dir / f"offsets_without_{held.path.name}.toml")
        import dataclasses

        with_cfg = dataclasses.replace(fit, joint_offsets=str(tpath))
        t = run_ablation(held, capture=caps[str(held.path)], fit=fit, rows=["recorded"], fit_variants={"offsets": with_cfg})
        row = {"motion": _motion_of(held), "trained_on": [str(p) for p in train]}
        for name, key in (("recorded", "without"), ("offsets", "with")):
            r = t["rows"][name]
            row[key] = {m: r.get(m) for m in ("mpjpe_mm_window", "pa_mpjpe_mm_window", "w_mpjpe_mm_window",
                                              "root_err_mm_window", "mpjpe_mm", "pa_mpjpe_mm", "w_mpjpe_mm",
                                              "root_err_mm", "fit_seconds")}
        results[str(held.path)] = row
        log.info("held out %s: %s", held.path, row)
        (out_dir / f"crossval_{held.path.name}.json").write_text(json.dumps({str(held.path): row}, indent=2))
    return results


def format_crossval(results: dict) -> str:
    lines = [f"{'flight':<28s} {'motion':<10s} {'MPJPE':>13s} {'PA':>13s} {'W-MPJPE':>13s} {'root':>13s}   "
             "(steady window, mm: without -> with offsets)"]
    for f, r in results.items():
        cells = []
        for m in ("mpjpe_mm_window", "pa_mpjpe_mm_window", "w_mpjpe_mm_window", "root_err_mm_window"):
            a, b = r["without"].get(m), r["with"].get(m)
            cells.append(f"{a:6.1f}->{b:6.1f}" if a is not None and b is not None else f"{'-':>13s}")
        lines.append(f"{Path(f).name:<28s} {Path(r['motion']).stem:<10s} " + " ".join(cells))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from skycap.config import load_config

    ap = argparse.ArgumentParser(prog="python -m evaluation.learn_offsets", description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    a1 = sub.add_parser("learn", help="learn a table from flights")
    a1.add_argument("flights", nargs="+")
    a1.add_argument("--out", required=True, help="the TOML table to write (refused if it exists, unless --force)")
    a1.add_argument("--force", action="store_true")
    a2 = sub.add_parser("crossval", help="leave one flight out: learn on the others, score the held-out flight")
    a2.add_argument("flights", nargs="+")
    a2.add_argument("--out-dir", required=True)
    a2.add_argument("--held-out", action="append", default=None, metavar="FLIGHT",
                    help="score only this flight (repeatable; default every flight)")
    a2.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="FitConfig overrides")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if a.cmd == "learn":
        if Path(a.out).exists() and not a.force:
            raise SystemExit(f"{a.out} exists: give another --out or --force to replace it")
        table, stats = learn_offsets([Path(f) for f in a.flights])
        table.save(a.out)
        for det, off in table.offsets_body_m.items():
            print(f"{det}:")
            for j, n in enumerate(COCO17_NAMES):
                st = stats[det].get(n, {})
                print(f"  {n:<15s} fwd/left/up mm {np.round(off[j] * 1e3, 1)}  n={st.get('n')} median px "
                      f"{st.get('median_px_before')} -> {st.get('median_px_after')}")
        print(f"wrote {a.out}")
    else:
        fit = load_config(FitConfig, None, a.set)
        res = crossval(a.flights, a.out_dir, fit, a.held_out)
        print(format_crossval(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
