"""Benchmark of the monocular (DroCap) pipeline: single-frame initialisation and bundle adjustment time.

    python bench/bench_monocular.py [--frames 300] [--repeat 3] [--motion FILE.bvh]

Runs on a held-out CMU clip when ../shared/data is present (else a synthetic sequence of dictionary
poses), one orbiting perspective camera (the drone's estimated poses for the perspective BA) at 25 deg/s, 5 px noise, 10 % outliers. Prints a table with the
machine noted. BLAS threads are pinned to 1 (small matrices; the machine is shared).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

torch.set_num_threads(1)

from reconstruction.monocular.ba import BAConfig, bundle_adjust  # noqa: E402
from reconstruction.monocular.dictionary import load_dictionary  # noqa: E402
from reconstruction.monocular.evaluate import EvalSetup, load_motion, make_view  # noqa: E402
from reconstruction.monocular.perspective import orthographic_to_world, perspective_bundle_adjust  # noqa: E402
from reconstruction.monocular.pipeline import MonocularConfig, model_fit, reconstruct_monocular  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import describe_machine  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DEFAULT_MOTION = REPO.parent / "shared" / "data" / "mocap" / "cmu" / "002" / "002_10.bvh"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--motion", type=Path, default=DEFAULT_MOTION)
    args = ap.parse_args()
    d = load_dictionary()
    setup = EvalSetup(clip_seconds=args.frames / 24.0 + 0.5)
    if args.motion.is_file():
        J, t_ns = load_motion(args.motion, setup.clip_seconds)
        view = make_view(J, t_ns, setup)
        src = args.motion.stem
    else:
        raise SystemExit(f"motion {args.motion} not found; pass --motion FILE.bvh (CMU CC_Base rig)")
    W, conf = view.W_px[: args.frames], view.confidence[: args.frames]
    T = W.shape[0]
    cfg = MonocularConfig(ablation_no_articulation=False, ablation_paper_order=False)
    res = reconstruct_monocular(W, conf, d, cfg)
    rows = []
    ti = []
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        reconstruct_monocular(W, conf, d, dataclasses.replace(cfg, ba=dataclasses.replace(cfg.ba, outer_iters=0)))
        ti.append(time.perf_counter() - t0)
    rows.append(("tracks + single-frame init", min(ti), len(res.ba.objective) - 1))
    for name, bcfg in [
        ("BA (default: warm-up, adult L)", cfg.ba),
        ("BA (paper order, gamma=1)", BAConfig.paper()),
        ("BA w/o articulation (gamma=0)", dataclasses.replace(cfg.ba, gamma=0.0)),
        ("BA extended (smooth S, R)", BAConfig.paper(smooth_S=0.5, smooth_R=0.5)),
    ]:
        tb = []
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            r = bundle_adjust(W, res.weights, res.init.S, res.init.R, d.limbs, bcfg)
            tb.append(time.perf_counter() - t0)
        rows.append((name, min(tb), len(r.objective) - 1))
    # the learned single-frame lift (beyond the paper; the pipeline's third start of the perspective BA)
    from reconstruction.monocular.lifter import PoseLifter

    lifter = PoseLifter.load(cfg.lifter.path or None)
    tl = []
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        lifter.lift(W, res.confidence, cfg.lifter)
        tl.append(time.perf_counter() - t0)
    rows.append(("learned single-frame lift (torch)", min(tl), cfg.lifter.rounds))
    # perspective BA in the world with the drone's camera poses, one start (the paper BA placed in the world)
    T_wc = view.T_world_cam[: args.frames]
    pc = cfg.perspective
    X0 = orthographic_to_world(res.ba.S, res.ba.R, W, res.weights, T_wc, view.K, pc.body_rms_radius_m, limbs=d.limbs,
                               bone_rms_m=pc.body_bone_rms_m)  # fmt: skip
    t_s = (view.t_ns[: args.frames] - view.t_ns[0]) * 1e-9
    tp = []
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        rp = perspective_bundle_adjust(W, res.weights, T_wc, view.K, X0, d.limbs, cfg=pc, t_s=t_s)
        tp.append(time.perf_counter() - t0)
    rows.append(("BA perspective (1 start, torch)", min(tp), rp.iterations))
    # the body model fitted after it (model_fit: the multi-view product fit with one camera)
    tm = []
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        model_fit(W, res.confidence, T_wc, view.K, view.t_ns[: args.frames], rp.X, cfg.model)  # as the pipeline
        tm.append(time.perf_counter() - t0)
    # iters: Adam steps + L-BFGS iterations at most (the polish stops when it no longer lowers the energy)
    rows.append(("body model (Adam+L-BFGS, torch)", min(tm), cfg.model.fit.iters + cfg.model.fit.polish_iters))
    print("machine:", describe_machine(f"numpy {np.__version__}", "BLAS threads 1", f"torch {torch.__version__} threads 1"))
    print(f"clip: {src}, {T} frames, 17 joints, dictionary K={d.num_bases}; best of {args.repeat}")
    print(f"load average (1, 5, 15 min) at the end: {os.getloadavg()}")
    print(f"{'stage':<34}{'seconds':>9}{'ms/frame':>10}{'iters':>7}")
    for name, s, it in rows:
        print(f"{name:<34}{s:>9.3f}{1000 * s / T:>10.2f}{it:>7}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
