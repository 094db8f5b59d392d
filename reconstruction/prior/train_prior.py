"""Train the pose prior (:mod:`reconstruction.prior.gmm`) on CMU motion capture BVH files.

    python -m reconstruction.prior.train_prior --cmu ../shared/data/mocap/cmu --out reconstruction/prior/data/pose_prior.npz

Steps: every BVH (CC_Base rig) -> COCO-17 joints (:func:`skycap.skeleton.mocap_to_coco17`, T-pose frame
skipped) at 15 Hz -> per-file skeleton shape (:func:`estimate_shape`) -> joint rotations by
:func:`inverse_kinematics` (smallest rotation per bone, no twist) -> axis-angle (N, 33) -> EM for a
full-covariance Gaussian mixture (k-means++ start, covariance floor ``reg`` rad^2) -> joint limits =
0.5/99.5 percentiles widened by ``margin`` rad. Files listed in ``HELD_OUT`` (the clips the evaluation
table reports) are left out of training and used for the held-out log-likelihood printed at the end.

Data credit: "The data used in this project was obtained from mocap.cs.cmu.edu. The database was created
with funding from NSF EIA-0196217."
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from reconstruction.body.skeleton17 import NUM_POSE, estimate_shape, inverse_kinematics
from skycap.bvh import read_bvh
from skycap.skeleton import mocap_to_coco17

log = logging.getLogger(__name__)

#: Clips reported in the evaluation table; never trained on.
HELD_OUT = ("002_01", "002_05", "005_01", "005_02", "001_01", "003_01")


def poses_from_bvh(path: Path, step: int = 2) -> np.ndarray:
    """Axis-angle poses (N, 11, 3) of a CC_Base BVH, every ``step``-th frame (first frame = T-pose, skipped)."""
    m = read_bvh(path)
    J = mocap_to_coco17(m.slice(1, None, step))
    shape = estimate_shape(J)
    _, R_loc, _ = inverse_kinematics(J, shape)
    return Rotation.from_matrix(R_loc.reshape(-1, 3, 3)).as_rotvec().reshape(-1, NUM_POSE, 3)


def fit_gmm(X: np.ndarray, k: int, iters: int = 100, reg: float = 2e-3, seed: int = 0):
    """EM for a full-covariance GMM. X (N, D) -> (weights (K,), means (K, D), covs (K, D, D))."""
    rng = np.random.default_rng(seed)
    N, D = X.shape
    # k-means++ seeding
    centres = [X[rng.integers(N)]]
    for _ in range(1, k):
        d2 = np.min([((X - c) ** 2).sum(1) for c in centres], axis=0)
        centres.append(X[rng.choice(N, p=d2 / d2.sum())])
    means = np.array(centres)
    covs = np.broadcast_to(np.cov(X.T) + reg * np.eye(D), (k, D, D)).copy()
    w = np.full(k, 1.0 / k)
    prev = -np.inf
    for it in range(iters):
        logp = np.zeros((N, k))
        for j in range(k):
            L = np.linalg.cholesky(covs[j])
            z = np.linalg.solve(L, (X - means[j]).T)
            logp[:, j] = np.log(w[j]) - 0.5 * (z * z).sum(0) - np.log(np.diag(L)).sum() - 0.5 * D * np.log(2 * np.pi)
        mx = logp.max(1, keepdims=True)
        ll = mx[:, 0] + np.log(np.exp(logp - mx).sum(1))
        r = np.exp(logp - ll[:, None])
        nk = r.sum(0) + 1e-9
        w = nk / N
        means = (r.T @ X) / nk[:, None]
        for j in range(k):
            d = X - means[j]
            covs[j] = (r[:, j, None] * d).T @ d / nk[j] + reg * np.eye(D)
        if ll.mean() - prev < 1e-5:
            break
        prev = ll.mean()
    log.info("EM: %d iterations, mean log-likelihood %.2f", it + 1, ll.mean())
    return w, means, covs


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cmu", type=Path, default=Path(__file__).resolve().parents[3] / "shared/data/mocap/cmu")
    ap.add_argument("--out", type=Path, default=Path(__file__).with_name("data") / "pose_prior.npz")
    ap.add_argument("--components", type=int, default=12)
    ap.add_argument("--margin", type=float, default=0.15, help="joint-limit widening (rad)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO)
    files = sorted(args.cmu.rglob("*.bvh"))
    if not files:
        raise SystemExit(f"no BVH files under {args.cmu}")
    train, held = [], []
    for f in tqdm(files, desc="mocap -> poses"):
        (held if f.stem in HELD_OUT else train).append(poses_from_bvh(f))
    Xtr = np.concatenate(train).reshape(-1, 3 * NUM_POSE)
    Xho = np.concatenate(held).reshape(-1, 3 * NUM_POSE) if held else Xtr[:0]
    log.info("training poses %d from %d files; held-out %d from %d files", len(Xtr), len(train), len(Xho), len(held))
    w, mu, cov = fit_gmm(Xtr, args.components)
    lo = np.percentile(Xtr, 0.5, axis=0) - args.margin
    hi = np.percentile(Xtr, 99.5, axis=0) + args.margin
    args.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        args.out, weights=w, means=mu, covs=cov, lo=lo, hi=hi,
        held_out=np.array(HELD_OUT), train_files=np.array([f.stem for f in files if f.stem not in HELD_OUT]),
        credit=np.array("The data used in this project was obtained from mocap.cs.cmu.edu. "
                        "The database was created with funding from NSF EIA-0196217."),
    )  # fmt: skip
    import torch

    from reconstruction.prior.gmm import PosePrior

    prior = PosePrior.load(args.out)
    with torch.no_grad():
        e_tr = prior.energy(torch.tensor(Xtr, dtype=torch.float32)).mean().item()
        e_ho = prior.energy(torch.tensor(Xho, dtype=torch.float32)).mean().item() if len(Xho) else float("nan")
        rnd = torch.empty(2000, Xtr.shape[1]).uniform_(-1.5, 1.5)
        e_rn = prior.energy(rnd).mean().item()
    print(f"mean energy: train {e_tr:.1f}, held-out {e_ho:.1f}, uniform random poses {e_rn:.1f}")
    print(f"wrote {args.out} ({args.out.stat().st_size / 1e3:.0f} kB)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
