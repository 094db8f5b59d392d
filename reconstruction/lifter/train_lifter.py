"""Train the monocular pipeline's single-frame lifter (:mod:`reconstruction.monocular.lifter`) on CMU motion capture.

Usage::

    python -m reconstruction.lifter.train_lifter --cmu ../shared/data/mocap/cmu \\
        --out reconstruction/lifter/cmu_coco17_lifter.npz

Poses: every BVH under ``--cmu`` except :data:`HELD_OUT` (the monocular evaluation clips of the dictionary,
``EVAL_CLIPS``, and four more clips of dance and climbing on which the lift is evaluated), at 30 fps, mapped to
COCO-17 (``skycap.skeleton.mocap_to_coco17``), plus their left/right mirror images. Each training step draws 512
poses, each seen from a random drone-like viewpoint (:class:`reconstruction.monocular.lifter.ViewSampling`) with
detector noise, dropped joints and gross outliers; the loss is the mean absolute joint error of the centred
camera-frame pose. AdamW with a one-cycle learning rate, seeds fixed (numpy and torch): about 5 min on 2 CPU cores.

Credit: "The data used in this project was obtained from mocap.cs.cmu.edu. The database was created with funding
from NSF EIA-0196217."
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np
import torch

from reconstruction.dictionary.learn_dictionary import CMU_CREDIT, EVAL_CLIPS, load_world_poses
from reconstruction.monocular.lifter import DEFAULT_LIFTER, LifterNet, PoseLifter, ViewSampling, training_batch

#: Never trained on: the monocular evaluation clips and four clips the lift is scored on (dance, climbing).
HELD_OUT = EVAL_CLIPS + ("001_14", "005_04", "005_07", "005_12")

log = logging.getLogger("train_lifter")


def train(poses: np.ndarray, steps: int, batch: int = 512, lr: float = 2e-3, hidden: int = 512, blocks: int = 2,
          seed: int = 0, view: ViewSampling | None = None, log_every: int = 500) -> tuple[LifterNet, list[float]]:  # fmt: skip
    """Train a :class:`LifterNet`; returns it (eval mode) and the loss per step (mean absolute error, radius units)."""
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    net = LifterNet(hidden, blocks)
    opt = torch.optim.AdamW(net.parameters(), lr / 2, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, lr, total_steps=steps)
    losses, t0 = [], time.perf_counter()
    net.train()
    for it in range(steps):
        x, y = training_batch(poses, rng, batch, view)
        loss = (net(x) - y).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        losses.append(float(loss.detach()))
        if log_every and it % log_every == 0:
            log.info("step %d / %d: loss %.4f (%.0f s)", it, steps, np.mean(losses[-log_every:]), time.perf_counter() - t0)
    return net.eval(), losses


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cmu", type=Path, default=Path(__file__).resolve().parents[2].parent / "shared/data/mocap/cmu")
    ap.add_argument("--out", type=Path, default=DEFAULT_LIFTER)
    ap.add_argument("--steps", type=int, default=8000)
    ap.add_argument("--hidden", type=int, default=512)
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--hold-out", nargs="*", default=[], metavar="CLIP",
                    help="more clips to leave out (cross-validation), e.g. 005_02 005_09")  # fmt: skip
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    torch.set_num_threads(max(1, torch.get_num_threads()))
    held = HELD_OUT + tuple(c for c in args.hold_out if c not in HELD_OUT)
    poses, clips = load_world_poses(args.cmu, fps=args.fps, exclude=held)
    log.info("training poses: %d (with mirrors) from %d clips; held out: %s", len(poses), len(clips), " ".join(held))
    net, losses = train(poses, args.steps, hidden=args.hidden)
    log.info("final loss (mean of the last 500 steps) %.4f", float(np.mean(losses[-500:])))
    PoseLifter(net, clips=tuple(clips), held_out=held, credit=CMU_CREDIT).save(args.out)
    log.info("wrote %s (%.0f kB)", args.out, args.out.stat().st_size / 1e3)
    return 0


if __name__ == "__main__":
    sys.exit(main())
