"""``skycap detect``: find people in one image with the onboard detector (ONNX, CPU)."""

from __future__ import annotations

import argparse
from pathlib import Path

from skycap.config import add_config_args


def parse_xywh(text: str, what: str = "--roi") -> tuple[float, float, float, float]:
    """``"x,y,w,h"`` -> 4 floats (pixels); a clear error otherwise."""
    from skycap.errors import SkycapError

    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError:
        vals = ()
    if len(vals) != 4 or vals[2] <= 0 or vals[3] <= 0:
        raise SkycapError(f"{what} {text!r} must be x,y,w,h in pixels with w, h > 0 (example: {what} 800,400,320,320)")
    return vals  # type: ignore[return-value]


def read_image(path: Path):
    """BGR uint8 image from a file, or a clear error."""
    import cv2

    from skycap.errors import SkycapError

    if not Path(path).is_file():
        raise SkycapError(f"image {path} does not exist; pass a PNG or JPEG file")
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise SkycapError(f"image {path} cannot be read by OpenCV; pass a PNG or JPEG file")
    return img


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "detect",
        help="find people in an image with the onboard detector (NanoDet ONNX)",
        description="Find people in IMAGE. Modes: roi (the tracker's region, --roi x,y,w,h), tiles (whole frame "
        "in overlapping tiles at native resolution, for small distant people) and full (whole frame scaled down). "
        "Example: skycap detect frame.png --mode tiles --json --png boxes.png",
    )
    add_config_args(p)
    p.add_argument("image", type=Path, help="PNG/JPEG image")
    p.add_argument("--mode", choices=("roi", "tiles", "full"), default=None, help="default: roi with --roi, else tiles")
    p.add_argument("--roi", default=None, help="region x,y,w,h in pixels (for --mode roi)")
    p.add_argument("--threads", type=int, default=None, help="onnxruntime threads (default: detector.threads = 1)")
    p.add_argument("--json", action="store_true", help="print the detections as JSON")
    p.add_argument("--png", type=Path, default=None, help="write the image with the boxes drawn")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    import json

    import cv2

    from onboard.detector.detector import DetectorConfig, PersonDetector, draw_detections
    from skycap.config import config_from_args
    from skycap.errors import SkycapError

    cfg = config_from_args(DetectorConfig, args, {"threads": args.threads})
    roi = parse_xywh(args.roi) if args.roi else None
    mode = args.mode or ("roi" if roi else "tiles")
    if mode == "roi" and roi is None:
        raise SkycapError("--mode roi needs --roi x,y,w,h (or use --mode tiles / full)")
    img = read_image(args.image)
    det = PersonDetector(cfg)
    res = det.detect(img, mode=mode, roi_xywh=roi)
    if args.json:
        print(
            json.dumps(
                {
                    "image": str(args.image),
                    "width_px": img.shape[1],
                    "height_px": img.shape[0],
                    "detector": det.name,
                    "mode": res.mode,
                    "roi_px": res.roi_px,
                    "inferences": res.inferences,
                    "elapsed_s": round(res.elapsed_s, 4),
                    "detections": [d.to_dict() for d in res.detections],
                },
                indent=1,
            )
        )
    else:
        print(f"{len(res.detections)} people ({res.mode}, {res.inferences} inferences, {res.elapsed_s * 1e3:.0f} ms)")
        for d in res.detections:
            x, y, w, h = d.xywh
            print(f"  x={x:7.1f} y={y:7.1f} w={w:6.1f} h={h:6.1f} score={d.score:.2f}")
    if args.png:
        args.png.parent.mkdir(parents=True, exist_ok=True)
        if not cv2.imwrite(str(args.png), draw_detections(img, res)):
            raise SkycapError(f"cannot write {args.png}; use a .png path in a writable folder")
    return 0
