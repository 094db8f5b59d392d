"""onnxruntime static int8 (QDQ) quantisations of the keypoint networks, calibrated on crops from a recorded flight
-- an experiment, not shipped: on the AMD EPYC (Zen 2: AVX2, no VNNI) of the 2-core machine they are SLOWER than
the float models (MoveNet Lightning 26 vs 21 CPU ms per crop, BlazePose full 32 vs 24) and BlazePose's landmarks
move by ~9% of the crop side (reconstruction/process/README.md, "Keypoint models"). Kept to redo the measurement on
a CPU with VNNI / AVX512-VNNI, where onnxruntime's u8s8 kernels are fast.

Runs in the converter venv (it needs ``onnx``; ``make_models.sh`` sets it up), from the shipped float models:

    # 1. calibration crops (project venv; a flight that is NOT the one the models are evaluated on)
    python scripts/make_models/keypoint_crops.py CALIB_FLIGHT --out /tmp/crops.npz
    # 2. the int8 models (converter venv) into a folder of their own
    $CONVENV/bin/python scripts/make_models/quantize_keypoints.py --crops /tmp/crops.npz --out-dir /tmp/int8
    # 3. CPU time per crop (project venv)
    python scripts/make_models/keypoint_cpu_ms.py --crops /tmp/crops.npz movenet_lightning=/tmp/int8/movenet_lightning_int8.onnx

Per model (``--quantize``, default movenet_lightning, blazepose_full, blazepose_detector): float16 weight casts
folded to float32, then ``onnxruntime.quantization.quantize_static`` in QDQ format, per-channel int8 weights, uint8
activations, MinMax calibration on the crops. ``--reduce-range`` (7-bit weights, the default) avoids the u8s8
saturation of AVX2 CPUs without VNNI (vpmaddubsw's pair sums overflow int16); ``--no-reduce-range`` gives full-range
u8s8; ``--weight-type uint8`` is u8u8; ``--skip-depthwise`` leaves the depthwise convolutions in float.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
MODELS = ROOT / "reconstruction" / "keypoints" / "models"


def fold_fp16_casts(model):
    """Replace each Cast of a float16 initializer by a float32 initializer (the quantiser wants float weights)."""
    from onnx import numpy_helper

    g = model.graph
    inits = {i.name: i for i in g.initializer}
    keep = []
    for n in g.node:
        if n.op_type == "Cast" and n.input[0] in inits and inits[n.input[0]].data_type == 10:  # FLOAT16
            a = numpy_helper.to_array(inits[n.input[0]]).astype(np.float32)
            g.initializer.append(numpy_helper.from_array(a, n.output[0]))
        else:
            keep.append(n)
    del g.node[:]
    g.node.extend(keep)
    used = {x for n in g.node for x in n.input} | {o.name for o in g.output}
    live = [i for i in g.initializer if i.name in used]
    del g.initializer[:]
    g.initializer.extend(live)
    return model


class CropReader:
    """onnxruntime CalibrationDataReader over recorded crops, one crop per call."""

    def __init__(self, input_name: str, name: str, crops_u8: np.ndarray):
        self.input_name, self.name, self.crops = input_name, name, crops_u8
        self.i = 0

    def get_next(self):
        if self.i >= len(self.crops):
            return None
        from reconstruction.keypoints.detectors import network_input

        x = network_input(self.name, self.crops[self.i : self.i + 1])
        self.i += 1
        return {self.input_name: x}

    def rewind(self):
        self.i = 0


def depthwise_convs(model) -> list[str]:
    """Names of the grouped (depthwise) Conv nodes."""
    out = []
    for n in model.graph.node:
        if n.op_type == "Conv" and any(a.name == "group" and a.i > 1 for a in n.attribute):
            out.append(n.name)
    return out


def quantize(name: str, src: Path, dst: Path, crops_u8: np.ndarray, reduce_range: bool, weight_type: str,
             per_channel: bool, calibrate: str, exclude: list[str], skip_depthwise: bool = False) -> None:
    import onnx
    from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static

    with tempfile.TemporaryDirectory() as tmp:
        f32 = Path(tmp) / f"{name}.f32.onnx"
        m = fold_fp16_casts(onnx.load(str(src)))
        onnx.save(m, str(f32))
        input_name = m.graph.input[0].name
        if skip_depthwise:
            exclude = [*exclude, *depthwise_convs(m)]
        quantize_static(
            str(f32), str(dst), CropReader(input_name, name, crops_u8),
            quant_format=QuantFormat.QDQ, per_channel=per_channel, reduce_range=reduce_range,
            activation_type=QuantType.QUInt8,
            weight_type=QuantType.QInt8 if weight_type == "int8" else QuantType.QUInt8,
            calibrate_method={"minmax": CalibrationMethod.MinMax, "percentile": CalibrationMethod.Percentile,
                              "entropy": CalibrationMethod.Entropy}[calibrate],
            nodes_to_exclude=exclude or None,
            extra_options={"ActivationSymmetric": False, "WeightSymmetric": True},
        )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--crops", action="append", default=[], help="npz from keypoint_crops.py (repeatable)")
    ap.add_argument("--src-dir", default=str(MODELS), help="the shipped float models")
    ap.add_argument("--out-dir", required=True, help="where the int8 files go (not the shipped models' folder)")
    ap.add_argument("--quantize", default="movenet_lightning,blazepose_full,blazepose_detector",
                    help="comma-separated models to quantise ('' for none)")
    ap.add_argument("--suffix", default="_int8", help="the quantised files are <model><suffix>.onnx")
    ap.add_argument("--reduce-range", action=argparse.BooleanOptionalAction, default=True)
    ap.add_argument("--weight-type", choices=["int8", "uint8"], default="int8")
    ap.add_argument("--per-channel", action=argparse.BooleanOptionalAction, default=True)
    ap.add_argument("--calibrate", choices=["minmax", "percentile", "entropy"], default="minmax")
    ap.add_argument("--exclude", default="", help="comma-separated node names left in float")
    ap.add_argument("--skip-depthwise", action="store_true", help="leave the depthwise convolutions in float")
    ap.add_argument("--max-crops", type=int, default=0, help="calibrate on at most this many crops (evenly spaced)")
    a = ap.parse_args(argv)
    src_dir, out_dir = Path(a.src_dir), Path(a.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    names = [n for n in a.quantize.split(",") if n]
    if names:
        if not a.crops:
            ap.error("--crops is needed to quantise (calibration crops from keypoint_crops.py)")
        crops: dict[str, list[np.ndarray]] = {}
        for p in a.crops:
            with np.load(p) as z:
                for k in z.files:
                    crops.setdefault(k, []).append(z[k])
        for n in names:
            if n not in crops:
                ap.error(f"no calibration crops of {n} in {a.crops}")
            c = np.concatenate(crops[n])
            if a.max_crops and len(c) > a.max_crops:
                c = c[np.linspace(0, len(c) - 1, a.max_crops).round().astype(int)]
            src = src_dir / f"{n}.onnx"
            dst = out_dir / f"{n}{a.suffix}.onnx"
            quantize(n, src, dst, c, a.reduce_range, a.weight_type, a.per_channel, a.calibrate,
                     [x for x in a.exclude.split(",") if x], a.skip_depthwise)
            print(f"{dst}: int8 from {len(c)} crops ({dst.stat().st_size / 1e6:.1f} MB)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
