"""Learn the monocular pose dictionary from CMU motion capture BVH files (CC_Base rig).

Usage::

    python -m reconstruction.dictionary.learn_dictionary --cmu ../shared/data/mocap/cmu \
        --out reconstruction/dictionary/cmu_coco17_k64.npz

Clips in :data:`EVAL_CLIPS` (used by the monocular evaluation) are never used here. Poses are taken at
10 fps (skipping the prepended T-pose frame), mapped to COCO-17 (``skycap.skeleton.mocap_to_coco17``),
put in the canonical body frame and learned by sparse coding (``reconstruction.monocular.dictionary``).
Mirrored copies (left <-> right) are added to double the data.

Credit: "The data used in this project was obtained from mocap.cs.cmu.edu. The database was created
with funding from NSF EIA-0196217."
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import numpy as np

from reconstruction.monocular.dictionary import (
    DEFAULT_DICTIONARY,
    PoseDictionary,
    canonicalize_poses,
    learn_dictionary,
)
from skycap.bvh import read_bvh
from skycap.skeleton import COCO17_FLIP, mocap_to_coco17

CMU_CREDIT = (
    "The data used in this project was obtained from mocap.cs.cmu.edu. "
    "The database was created with funding from NSF EIA-0196217."
)

#: Held-out clips: the evaluation set of the monocular method (never in the dictionary).
EVAL_CLIPS = ("001_01", "002_01", "002_02", "002_05", "002_10", "003_01", "003_02", "005_01")

log = logging.getLogger("learn_dictionary")


def load_world_poses(cmu_dir: Path, fps: float = 10.0, exclude=EVAL_CLIPS) -> tuple[np.ndarray, list[str]]:
    """World poses (N, 17, 3) NED metres, each centred on its joint mean, from every BVH under ``cmu_dir`` except
    ``exclude`` (skipping the prepended T-pose frame, at ``fps``), each clip followed by its left/right mirror image;
    and the clip names."""
    files = sorted(p for p in Path(cmu_dir).rglob("*.bvh") if p.stem not in set(exclude))
    if not files:
        raise SystemExit(f"no training BVH files under {cmu_dir}; pass the CMU folder with --cmu")
    out = []
    for f in files:
        m = read_bvh(f)
        step = max(1, int(round(m.fps / fps)))
        J = mocap_to_coco17(m.slice(1, None, step))
        out += [J, J[:, list(COCO17_FLIP)] * np.array([1.0, -1.0, 1.0])]  # mirror east <-> west and relabel
    X = np.concatenate(out)
    return X - X.mean(1, keepdims=True), [f.stem for f in files]


def load_training_poses(cmu_dir: Path, fps: float = 10.0, exclude=EVAL_CLIPS) -> tuple[np.ndarray, list[str]]:
    """Canonical poses (N, 3, 17) from every BVH under ``cmu_dir`` except ``exclude``; and the clip names."""
    X, names = load_world_poses(cmu_dir, fps, exclude)
    return canonicalize_poses(X), names


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cmu", type=Path, default=Path(__file__).resolve().parents[2].parent / "shared/data/mocap/cmu")
    ap.add_argument("--out", type=Path, default=DEFAULT_DICTIONARY)
    ap.add_argument("--bases", type=int, default=64)
    ap.add_argument("--lam", type=float, default=0.01)
    ap.add_argument("--iters", type=int, default=30)
    ap.add_argument("--fps", type=float, default=10.0)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    poses, clips = load_training_poses(args.cmu, fps=args.fps)
    log.info("training poses: %d from %d clips", len(poses), len(clips))
    bases, stats = learn_dictionary(poses, num_bases=args.bases, lam=args.lam, iters=args.iters)
    log.info("stats: %s", stats)
    PoseDictionary(bases=bases, mean_pose=poses.mean(0), clips=tuple(clips), credit=CMU_CREDIT).save(args.out)
    log.info("wrote %s", args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
