"""``skycap camera calibrate``: intrinsic calibration from a video or images of a ChArUco board -> camera.toml.

    skycap camera calibrate board.mp4 --board charuco --squares 7x5 --square-mm 40 --marker-mm 30 \\
        --dict DICT_5X5_100 --out camera.toml
    skycap camera calibrate --print-board board.png --squares 7x5 --square-mm 40 --marker-mm 30 --dict DICT_5X5_100

``skycap camera`` (:mod:`onboard.camera.cli`) adds this subcommand with :func:`add_parser`; :func:`main` runs it
alone (tests, ``python -m onboard.camera.calibration_cli calibrate ...``). The workflow: deploy/CAMERA.md.
"""

from __future__ import annotations

import argparse
import glob
import logging
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from skycap.errors import SkycapError

__all__ = ["add_parser", "main", "read_views", "IMAGE_SUFFIXES"]

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add ``calibrate`` to the ``skycap camera`` subparsers; it sets ``func``."""
    p = subparsers.add_parser(
        "calibrate", help="intrinsic calibration (pinhole + distortion) from a video or images of a ChArUco board",
        description="Calibrate the camera's intrinsics from views of a ChArUco board and write camera.toml "
                    "(set camera.calibration_file to it). Real-lens workflow: deploy/CAMERA.md.")  # fmt: skip
    p.add_argument("source", nargs="?", metavar="SOURCE",
                   help="a video file, a folder of images, or a glob such as 'shots/*.jpg' (quote it)")
    p.add_argument("--board", choices=("charuco",), default="charuco", help="calibration target (default: charuco)")
    p.add_argument("--squares", default="7x5", help="chessboard squares COLUMNSxROWS (default: 7x5)")
    p.add_argument("--square-mm", type=float, default=40.0, help="printed square side, measured (default: 40)")
    p.add_argument("--marker-mm", type=float, default=30.0, help="printed marker side, measured (default: 30)")
    p.add_argument("--dict", dest="dictionary", default="DICT_5X5_100", help="ArUco dictionary (default: DICT_5X5_100)")
    p.add_argument("--out", default="camera.toml", help="calibration file to write (default: camera.toml)")
    p.add_argument("--force", action="store_true", help="overwrite --out (or --print-board) if it exists")
    p.add_argument("--every", type=int, default=10, help="use every Nth frame of a video (default: 10)")
    p.add_argument("--min-views", type=int, default=8, help="fewest usable views to calibrate (default: 8)")
    p.add_argument("--max-views", type=int, default=40,
                   help="most views used; more good ones are thinned evenly (default: 40)")
    p.add_argument("--min-corners", type=int, default=6, help="fewest board corners for a view to count (default: 6)")
    p.add_argument("--fix-k3", action="store_true", help="hold k3 at 0 (ordinary lenses, few views)")
    p.add_argument("--print-board", metavar="PNG", default=None,
                   help="write the printable board (with the size to print it at) instead of calibrating")
    p.add_argument("--dpi", type=float, default=300.0, help="resolution of --print-board (default: 300)")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    """The subcommand: unpack the arguments and call the library."""
    from onboard.camera.calibration import CharucoBoardSpec

    spec = CharucoBoardSpec.parse(args.squares, args.square_mm, args.marker_mm, args.dictionary)
    if args.print_board:
        print(print_board(spec, Path(args.print_board), dpi=args.dpi, overwrite=args.force))
        return 0
    if not args.source:
        raise CalibrationSourceError("give SOURCE (a video, an image folder or a glob of images), or --print-board PNG")
    out = Path(args.out)
    if out.exists() and not args.force:  # before the (long) detection, not after
        raise CalibrationSourceError(f"{out} exists; pass --force to overwrite it, or choose another --out")
    text = calibrate_source(args.source, spec, out, every=args.every, min_views=args.min_views,
                            max_views=args.max_views, min_corners=args.min_corners, fix_k3=args.fix_k3,
                            overwrite=args.force)
    print(text)
    return 0


class CalibrationSourceError(SkycapError):
    """A calibration SOURCE that cannot be read, or arguments that do not fit together."""


def calibrate_source(source: str, spec, out: Path, *, every: int = 10, min_views: int = 8, max_views: int = 40,
                     min_corners: int = 6, fix_k3: bool = False, overwrite: bool = False) -> str:
    """Read ``source``, calibrate, write ``out``; returns the summary to print."""
    from onboard.camera.calibration import calibrate_charuco

    result = calibrate_charuco(read_views(source, every=every), spec, min_views=min_views, max_views=max_views,
                               min_corners=min_corners, fix_k3=fix_k3)
    result.camera.to_toml(out, calibration=result.calibration_table(spec, source=str(source)), overwrite=overwrite)
    return f"{result.summary()}\nwrote {out}; set camera.calibration_file = \"{out}\" in the drone's config"


def read_views(source: str, *, every: int = 10) -> Iterator[tuple[str, np.ndarray]]:
    """(label, BGR image) of ``source``: every ``every``-th frame of a video (``frame N``), or each image (its file
    name) of a folder or glob, in name order. Unreadable images are skipped with a warning."""
    import cv2

    if every < 1:
        raise CalibrationSourceError(f"--every {every}: use 1 or more")
    p = Path(source)
    if p.is_dir():
        files = sorted(f for f in p.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES)
        if not files:
            raise CalibrationSourceError(f"{p} holds no images ({', '.join(IMAGE_SUFFIXES)})")
    elif any(ch in source for ch in "*?["):
        files = sorted(Path(f) for f in glob.glob(source) if Path(f).suffix.lower() in IMAGE_SUFFIXES)
        if not files:
            raise CalibrationSourceError(f"no images match {source!r}")
    elif p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES:
        files = [p]
    elif p.is_file():
        yield from _video_frames(p, every)
        return
    else:
        raise CalibrationSourceError(f"{source} not found: give a video file, an image folder or a glob of images")
    for f in files:
        img = cv2.imread(str(f), cv2.IMREAD_COLOR)
        if img is None:
            log.warning("%s: not a readable image; skipped", f)
            continue
        yield f.name, img


def _video_frames(path: Path, every: int) -> Iterator[tuple[str, np.ndarray]]:
    import cv2

    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise CalibrationSourceError(f"{path}: OpenCV cannot open it as a video (or it is not an image file)")
    n = 0
    try:
        while True:
            if n % every == 0:
                ok, frame = cap.read()
                if not ok:
                    break
                yield f"frame {n}", frame
            elif not cap.grab():
                break
            n += 1
    finally:
        cap.release()
    if n == 0:
        raise CalibrationSourceError(f"{path}: no frames could be read (codec missing, or not a video)")


def print_board(spec, path: Path, *, dpi: float = 300.0, margin_mm: float = 10.0, overwrite: bool = False) -> str:
    """Write the printable board PNG (with its DPI, so printing at 100 % gives the true size); returns what to do."""
    import cv2

    from onboard.camera.calibration import board_image

    if path.exists() and not overwrite:
        raise CalibrationSourceError(f"{path} exists; pass --force to overwrite it")
    img = board_image(spec, px_per_mm=dpi / 25.4, margin_mm=margin_mm)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        from PIL import Image

        Image.fromarray(img).save(path, dpi=(dpi, dpi))
    except ImportError:  # no DPI in the file: the size below is what counts
        cv2.imwrite(str(path), img)
    w_mm, h_mm = spec.size_mm
    pw, ph = img.shape[1] / dpi * 25.4, img.shape[0] / dpi * 25.4
    return (f"wrote {path}: {img.shape[1]}x{img.shape[0]} px at {dpi:g} dpi = {pw:.0f} x {ph:.0f} mm on paper "
            f"(board {w_mm:g} x {h_mm:g} mm, {spec.describe()}). Print at 100 % (no 'fit to page'), glue it flat "
            "to a rigid board, measure a square and a marker and pass the measured sizes as --square-mm/--marker-mm")


def main(argv: list[str] | None = None) -> int:
    """``calibrate ...`` without the rest of ``skycap camera`` (the same parser and error handling)."""
    parser = argparse.ArgumentParser(prog="skycap camera")
    sub = parser.add_subparsers(dest="command", required=True)
    add_parser(sub)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        return int(args.func(args) or 0)
    except SkycapError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
