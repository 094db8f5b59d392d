"""``skycap keypoints``: COCO-17 keypoints of a person in one image from the shipped ONNX models."""

from __future__ import annotations

import argparse
from pathlib import Path

from skycap.config import add_config_args


def register(sub: argparse._SubParsersAction) -> None:
    from reconstruction.keypoints import DEFAULT_MODELS, KEYPOINT_MODELS

    p = sub.add_parser(
        "keypoints",
        help="2D keypoints (COCO-17) of a person in an image from several ONNX models",
        description="Crop around the person box (--box x,y,w,h; without it the detector's best box in full "
        "mode) and run each keypoint model. Example: skycap keypoints img.png --box 20,15,350,497 --json",
    )
    add_config_args(p)
    p.add_argument("image", type=Path, help="PNG/JPEG image")
    p.add_argument("--box", default=None, help="person box x,y,w,h in pixels")
    p.add_argument(
        "--model",
        action="append",
        default=None,
        choices=(*KEYPOINT_MODELS, "all"),
        help=f"model (repeatable; 'all' for every model; default: {', '.join(DEFAULT_MODELS)})",
    )
    p.add_argument("--threads", type=int, default=None, help="onnxruntime threads per model (default 1)")
    p.add_argument("--json", action="store_true", help="print the keypoints as JSON")
    p.add_argument("--png", type=Path, default=None, help="write the image with each model's skeleton drawn")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    import json

    import cv2

    from onboard.detector.cli import parse_xywh, read_image
    from reconstruction.keypoints.detectors import KEYPOINT_MODELS, KeypointConfig, KeypointDetectors, draw_keypoints
    from skycap.config import config_from_args
    from skycap.errors import SkycapError
    from skycap.skeleton import COCO17_NAMES

    models = None
    if args.model:
        models = list(KEYPOINT_MODELS) if "all" in args.model else list(dict.fromkeys(args.model))
    cfg = config_from_args(KeypointConfig, args, {"threads": args.threads, "models": models})
    img = read_image(args.image)
    if args.box:
        box = parse_xywh(args.box, "--box")
    else:
        from onboard.detector.detector import PersonDetector

        res = PersonDetector().detect(img, mode="full")
        if not res.detections:
            raise SkycapError(f"no person found in {args.image}; pass the person's box with --box x,y,w,h")
        box = res.detections[0].xywh
    kd = KeypointDetectors(cfg)
    people = kd.detect(img, [box])
    if args.json:
        print(json.dumps({"image": str(args.image), "box_xywh": list(box), "models": {n: p[0].to_dict() for n, p in people.items()}}, indent=1))
    else:
        names = list(people)
        print(f"{'keypoint':16s}" + "".join(f"{n:>28s}" for n in names))
        for j, kn in enumerate(COCO17_NAMES):
            row = "".join(
                f"{people[n][0].keypoints_px[j, 0]:10.1f}{people[n][0].keypoints_px[j, 1]:10.1f}{people[n][0].confidence[j]:8.2f}"
                for n in names
            )
            print(f"{kn:16s}{row}")
    if args.png:
        args.png.parent.mkdir(parents=True, exist_ok=True)
        if not cv2.imwrite(str(args.png), draw_keypoints(img, people)):
            raise SkycapError(f"cannot write {args.png}; use a .png path in a writable folder")
    return 0
