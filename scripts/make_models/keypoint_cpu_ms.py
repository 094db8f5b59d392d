"""CPU milliseconds per crop of keypoint model files, on recorded crops (``keypoint_crops.py``).

Each file in a 1-thread onnxruntime session as skycap opens it (sequential, all graph optimisations, no spinning),
one crop per call, timed with ``time.process_time`` (this process's CPU time: robust to other work on a shared
machine, unlike wall time; cache and SMT contention still show):

    python scripts/make_models/keypoint_cpu_ms.py --crops crops.npz \\
        movenet_lightning=reconstruction/keypoints/models/movenet_lightning.onnx \\
        movenet_lightning=/tmp/q/movenet_lightning_int8.onnx ...

``NETWORK=FILE``: NETWORK names the crops in the npz (movenet_lightning, blazepose_full, blazepose_detector).
Prints one line per file: mean and median CPU ms per crop over ``--n`` crops (after 3 warm-up calls).
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np


def cpu_ms_per_crop(path: str, x: np.ndarray, n: int) -> tuple[float, float]:
    from onboard.detector.modelfile import ThreadSettings
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads, so.inter_op_num_threads = 1, 1
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.log_severity_level = 3
    so.add_session_config_entry("session.intra_op.allow_spinning", "1" if ThreadSettings(1, 1).allow_spinning else "0")
    s = ort.InferenceSession(path, so, providers=["CPUExecutionProvider"])
    name = s.get_inputs()[0].name
    for i in range(3):
        s.run(None, {name: x[i % len(x)][None]})
    times = []
    for i in range(n):
        t = time.process_time()
        s.run(None, {name: x[i % len(x)][None]})
        times.append(time.process_time() - t)
    return 1e3 * float(np.mean(times)), 1e3 * float(np.median(times))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--crops", required=True)
    ap.add_argument("--n", type=int, default=60)
    ap.add_argument("files", nargs="+", help="NETWORK=FILE")
    a = ap.parse_args(argv)
    from reconstruction.keypoints.detectors import network_input

    z = np.load(a.crops)
    for spec in a.files:
        net, path = spec.split("=", 1)
        mean, med = cpu_ms_per_crop(path, network_input(net, z[net]), a.n)
        print(f"{net:20s} {path}: {mean:6.2f} CPU ms/crop (median {med:.2f})", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
