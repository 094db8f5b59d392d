"""Record the keypoint models' input crops on a flight (calibration data for ``quantize_keypoints.py``).

Runs the ``skycap process`` keypoint step (the float32 models; BlazePose's pose detector on every frame for more of its crops) on a
recorded flight and keeps every ``--every``-th input of each network, as uint8 RGB crops:

    python scripts/make_models/keypoint_crops.py FLIGHT_DIR --out crops.npz [--every 3] [--max 400]

Output npz: ``<model>`` -> (N, S, S, 3) uint8 for each network that ran (``movenet_lightning``,
``blazepose_full``, ``blazepose_detector``, ...). The flight's ``processing/`` cache gets the boxes and keypoints
(the flight's recordings are only read); processing stops after the keypoint step. Use a flight that is NOT the
one the quantised models are evaluated on.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import numpy as np

log = logging.getLogger("keypoint_crops")


def to_uint8(name: str, x: np.ndarray) -> np.ndarray:
    """The network input ``x`` (N, S, S, 3) back to the uint8 RGB crop it was made from."""
    if x.dtype == np.int32:  # MoveNet: RGB 0..255
        return x.astype(np.uint8)
    if name.startswith("blazepose_detector"):  # [-1, 1]
        return np.clip(np.rint((x + 1.0) * 127.5), 0, 255).astype(np.uint8)
    return np.clip(np.rint(x * 255.0), 0, 255).astype(np.uint8)  # BlazePose landmarks: [0, 1]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("flight")
    ap.add_argument("--out", required=True)
    ap.add_argument("--every", type=int, default=3, help="keep every N-th input of each network")
    ap.add_argument("--max", type=int, default=400, help="at most this many crops per network")
    ap.add_argument("--networks", type=int, default=3, help="stop when this many networks have --max crops each")
    ap.add_argument("--set", action="append", default=[], help="extra ProcessConfig overrides")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")

    import threading

    import onnxruntime as ort

    from reconstruction.process import Cancelled, process

    seen: dict[str, int] = {}
    kept: dict[str, list[np.ndarray]] = {}
    lock = threading.Lock()
    orig_run = ort.InferenceSession.run

    def run(self, output_names, input_feed, run_options=None):
        name = Path(self._model_path).stem
        x = np.asarray(next(iter(input_feed.values())))
        if x.ndim != 4 or x.shape[-1] != 3 or x.shape[1] != x.shape[2]:  # not a keypoint network's crop
            return orig_run(self, output_names, input_feed, run_options)
        name = f"{name}@{x.shape[1]}"
        with lock:
            for crop in x:
                k = seen.get(name, 0)
                seen[name] = k + 1
                if k % a.every == 0 and len(kept.setdefault(name, [])) < a.max:
                    kept[name].append(to_uint8(name, crop[None])[0])
        return orig_run(self, output_names, input_feed, run_options)

    ort.InferenceSession.run = run

    def progress(ev) -> None:
        with lock:
            full = len(kept) >= a.networks and all(len(v) >= a.max for v in kept.values())
        if ev.step not in ("boxes", "keypoints") or full:
            raise Cancelled("keypoint crops recorded")

    try:
        # the pose detector on every frame (not only where the landmark track starts): more of its crops
        process(a.flight, ["keypoints.workers=1", "keypoints.track_rois=false", *a.set], progress=progress)
    except Cancelled:
        pass
    finally:
        ort.InferenceSession.run = orig_run
    out = {k.split("@")[0]: np.stack(v) for k, v in kept.items() if v}
    if not out:
        log.error("no keypoint model ran on %s (keypoints already cached? delete its processing/keypoints/)", a.flight)
        return 1
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(a.out, **out)
    for k, v in out.items():
        log.info("%s: %d crops kept, %s", k, len(v), v.shape)
    return 0


if __name__ == "__main__":
    sys.exit(main())
