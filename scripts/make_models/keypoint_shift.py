"""How far a keypoint model variant moves the keypoints from the reference models, on a processed flight.

Both model sets must have been run by ``skycap process FLIGHT`` with the cache on (their keypoints are read from
``FLIGHT/processing/keypoints/``, the boxes from ``processing/boxes/``):

    python scripts/make_models/keypoint_shift.py FLIGHT --ref movenet_lightning,blazepose_full \\
        --variant movenet_lightning_int8,blazepose_full_int8

Per model pair (i-th reference vs i-th variant): the distance between their keypoints in % of the person box's
diagonal over the frames and joints both found (confidence >= 0.05), median / p90 / p99, and the mean confidence
change. Prints one JSON object.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def shift_stats(kp_ref: np.ndarray, kp_var: np.ndarray, box_xywh: np.ndarray, min_conf: float = 0.05) -> dict:
    """kp_* (F, 17, 3) x_px, y_px, confidence; box (F, 4) -> the distances' median / p90 / p99 in % of the
    box diagonal over the joints both models found."""
    diag = np.hypot(box_xywh[:, 2], box_xywh[:, 3])[:, None]
    ok = (kp_ref[..., 2] >= min_conf) & (kp_var[..., 2] >= min_conf) & np.isfinite(diag)
    ok &= np.all(np.isfinite(kp_ref[..., :2]), -1) & np.all(np.isfinite(kp_var[..., :2]), -1)
    d = 100.0 * np.linalg.norm(kp_ref[..., :2] - kp_var[..., :2], axis=-1) / np.where(ok, diag, 1.0)
    d = d[ok]
    if d.size == 0:
        return {"joints": 0}
    both = np.all(np.isfinite(box_xywh), axis=1)
    return {"joints": int(d.size), "median_pct": round(float(np.median(d)), 3),
            "p90_pct": round(float(np.percentile(d, 90)), 3), "p99_pct": round(float(np.percentile(d, 99)), 3),
            "confidence_change_mean": round(float(np.mean(kp_var[both][..., 2] - kp_ref[both][..., 2])), 4)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("flight")
    ap.add_argument("--ref", required=True)
    ap.add_argument("--variant", required=True)
    ap.add_argument("--crop-scale", type=float, default=None)
    a = ap.parse_args(argv)
    from reconstruction.process.cache import make_key, read_npz
    from reconstruction.process.config import KeypointsConfig
    from reconstruction.process.pipeline import CACHE_VERSION

    kc = KeypointsConfig()
    crop = a.crop_scale if a.crop_scale is not None else kc.crop_scale
    proc = Path(a.flight) / "processing"
    ref, var = a.ref.split(","), a.variant.split(",")
    per: dict[str, list] = {f"{r}->{v}": [] for r, v in zip(ref, var)}
    for bfile in sorted((proc / "boxes").glob("*.npz")):
        drone = bfile.stem.rsplit("-", 1)[0]
        b = read_npz(bfile)
        loaded = []
        for models in (ref, var):
            key = make_key("keypoints", CACHE_VERSION, str(b["key"]), models, crop, kc.chunk_frames, kc.track_rois)
            z = read_npz(proc / "keypoints" / f"{drone}-{key}.npz")
            loaded.append(None if z is None else z["kp"])
        if any(x is None for x in loaded):
            print(f"{drone}: keypoints of {ref if loaded[0] is None else var} not in the cache; skipped", file=sys.stderr)
            continue
        for i, (r, v) in enumerate(zip(ref, var)):
            per[f"{r}->{v}"].append((loaded[0][:, i], loaded[1][:, i], b["box_xywh"]))
    out = {}
    for k, parts in per.items():
        if parts:
            out[k] = shift_stats(*(np.concatenate(x) for x in zip(*parts)))
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
