"""Intrinsic calibration of the drone's camera from views of a ChArUco board (OpenCV's aruco module): pinhole +
plumb_bob distortion, the RMS reprojection error, the views used and rejected (each with its reason). Pure
functions over images (no file or video I/O: ``skycap camera calibrate``, :mod:`onboard.camera.calibration_cli`,
reads the source); also a renderer of the board as a known, distorted camera sees it, for tests and for checking
the procedure end to end.

    spec = CharucoBoardSpec(squares_x=7, squares_y=5, square_mm=40, marker_mm=30, dictionary="DICT_5X5_100")
    result = calibrate_charuco(images, spec)           # images: arrays, or (label, array) pairs
    result.camera.to_toml("camera.toml", calibration=result.calibration_table(spec, source="board.mp4"))

Board frame (OpenCV's): origin at the board's top-left outer corner, x along the ``squares_x`` squares, y along the
``squares_y`` squares (down the printed image), z into the board; lengths in metres.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
from collections.abc import Iterable

import cv2
import numpy as np

from skycap.camera import PinholeCamera
from skycap.errors import SkycapError

__all__ = [
    "CalibrationError", "CharucoBoardSpec", "CalibrationResult", "ViewReport", "SyntheticView",
    "detect_charuco", "calibrate_charuco", "board_image", "render_charuco_view", "synthetic_views",
    "dictionary_names", "projection_difference_px",
]  # fmt: skip

log = logging.getLogger(__name__)


class CalibrationError(SkycapError):
    """A board spec that describes no board, or views that cannot calibrate the camera."""


def dictionary_names() -> list[str]:
    """The ArUco dictionaries OpenCV knows (``--dict``)."""
    return sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_") and n == n.upper())


@dataclasses.dataclass(frozen=True, kw_only=True)
class CharucoBoardSpec:
    """A printed ChArUco board: ``squares_x`` x ``squares_y`` chessboard squares of ``square_mm``, ArUco markers of
    ``marker_mm`` from ``dictionary`` in the white squares."""

    squares_x: int = 7
    squares_y: int = 5
    square_mm: float = 40.0
    marker_mm: float = 30.0
    dictionary: str = "DICT_5X5_100"

    def __post_init__(self) -> None:
        if self.squares_x < 3 or self.squares_y < 3:
            raise CalibrationError(f"board {self.squares_x}x{self.squares_y} squares: use at least 3x3 (--squares, "
                                   "e.g. 7x5)")
        if not self.square_mm > 0:
            raise CalibrationError(f"--square-mm {self.square_mm}: the square size must be > 0 mm")
        if not 0 < self.marker_mm < self.square_mm:
            raise CalibrationError(f"--marker-mm {self.marker_mm} with --square-mm {self.square_mm}: the marker must "
                                   "be smaller than the square (typically 0.6-0.8 of it)")
        if self.dictionary not in dictionary_names():
            raise CalibrationError(f"--dict {self.dictionary!r} is not an ArUco dictionary; use one of "
                                   f"{', '.join(dictionary_names())}")
        size = _dictionary_size(self.dictionary)
        if self.n_markers > size:
            raise CalibrationError(f"board {self.squares_x}x{self.squares_y} needs {self.n_markers} markers but "
                                   f"{self.dictionary} has {size}; use a larger dictionary (e.g. DICT_5X5_100)")

    @classmethod
    def parse(cls, squares: str, square_mm: float, marker_mm: float, dictionary: str) -> CharucoBoardSpec:
        """From the CLI's ``--squares 7x5`` form."""
        try:
            sx, sy = (int(v) for v in squares.lower().split("x"))
        except ValueError:
            raise CalibrationError(f"--squares {squares!r}: write it as COLUMNSxROWS, e.g. 7x5") from None
        return cls(squares_x=sx, squares_y=sy, square_mm=float(square_mm), marker_mm=float(marker_mm),
                   dictionary=dictionary)

    @property
    def n_markers(self) -> int:
        return self.squares_x * self.squares_y // 2

    @property
    def size_mm(self) -> tuple[float, float]:
        return self.squares_x * self.square_mm, self.squares_y * self.square_mm

    def describe(self) -> str:
        return (f"charuco {self.squares_x}x{self.squares_y} squares of {self.square_mm:g} mm, markers "
                f"{self.marker_mm:g} mm, {self.dictionary}")

    def as_table(self) -> dict:
        return {"type": "charuco", **dataclasses.asdict(self)}

    def board(self) -> cv2.aruco.CharucoBoard:
        """The OpenCV board (lengths in metres)."""
        return _board(self)


def _dictionary_size(name: str) -> int:
    return int(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name)).bytesList.shape[0])


@functools.lru_cache(maxsize=8)
def _board(spec: CharucoBoardSpec) -> cv2.aruco.CharucoBoard:
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, spec.dictionary))
    return cv2.aruco.CharucoBoard((spec.squares_x, spec.squares_y), spec.square_mm / 1000.0,
                                  spec.marker_mm / 1000.0, d)


@functools.lru_cache(maxsize=8)
def _detector(spec: CharucoBoardSpec) -> cv2.aruco.CharucoDetector:
    return cv2.aruco.CharucoDetector(_board(spec))


def _gray(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
    if image.ndim != 2:
        raise CalibrationError(f"image of shape {image.shape}: expected a grey (H, W) or BGR (H, W, 3) image")
    return image


def detect_charuco(image: np.ndarray, spec: CharucoBoardSpec) -> tuple[np.ndarray, np.ndarray] | None:
    """The board's inner chessboard corners seen in ``image``: (pixels (N, 2) float32, corner ids (N,) int), or
    None when the board is not found."""
    corners, ids, _, _ = _detector(spec).detectBoard(_gray(image))
    if ids is None or len(ids) == 0:
        return None
    return np.asarray(corners, dtype=np.float32).reshape(-1, 2), np.asarray(ids, dtype=int).reshape(-1)


# ----------------------------------------------------------------------------------------------- calibration
@dataclasses.dataclass(frozen=True)
class ViewReport:
    """One view: its label (file name or ``frame N``), the corners found, its RMS reprojection error after the
    calibration (used views) and why it was left out (rejected views)."""

    label: str
    n_corners: int
    rms_px: float | None = None
    reason: str = ""


@dataclasses.dataclass(frozen=True)
class CalibrationResult:
    camera: PinholeCamera
    #: RMS reprojection error over all corners of the used views
    rms_px: float
    views_used: tuple[ViewReport, ...]
    views_rejected: tuple[ViewReport, ...]
    #: fraction of the image's 4x4 cells holding a detected corner of a used view (1.0: the board reached every
    #: part of the image, the corners included)
    coverage: float

    def calibration_table(self, spec: CharucoBoardSpec, *, source: str = "", created_utc: str | None = None) -> dict:
        """The ``[calibration]`` table of the calibration file (how it was made)."""
        import datetime

        created = created_utc or datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
        return {
            "rms_reprojection_px": round(self.rms_px, 4), "views_used": len(self.views_used),
            "views_rejected": len(self.views_rejected), "coverage": round(self.coverage, 3),
            "image_width_px": self.camera.width_px, "image_height_px": self.camera.height_px,
            "board": spec.describe(), "board_spec": spec.as_table(), "created_utc": created, "source": source,
            "rejected": [f"{v.label}: {v.reason}" for v in self.views_rejected],
        }  # fmt: skip

    def summary(self) -> str:
        c = self.camera
        k1, k2, p1, p2, k3 = c.distortion
        lines = [
            f"image {c.width_px}x{c.height_px} px",
            f"fx {c.fx_px:.2f} px  fy {c.fy_px:.2f} px  cx {c.cx_px:.2f} px  cy {c.cy_px:.2f} px",
            f"distortion plumb_bob k1 {k1:.5f}  k2 {k2:.5f}  p1 {p1:.6f}  p2 {p2:.6f}  k3 {k3:.5f}",
            f"RMS reprojection error {self.rms_px:.3f} px ({_verdict(self.rms_px)})",
            f"views used {len(self.views_used)}, rejected {len(self.views_rejected)}; corners cover "
            f"{100 * self.coverage:.0f} % of the image's 4x4 cells",
        ]  # fmt: skip
        lines += [f"  rejected {v.label}: {v.reason}" for v in self.views_rejected[:20]]
        if len(self.views_rejected) > 20:
            lines.append(f"  ... and {len(self.views_rejected) - 20} more rejected")
        return "\n".join(lines)


def _verdict(rms_px: float) -> str:
    if rms_px < 0.5:
        return "good"
    if rms_px <= 1.0:
        return "acceptable; < 0.5 px is better"
    return "poor: redo with sharper, better-lit views filling the image corners"


@dataclasses.dataclass
class _Detection:
    label: str
    index: int
    corners: np.ndarray
    ids: np.ndarray


def calibrate_charuco(images: Iterable[np.ndarray | tuple[str, np.ndarray]], spec: CharucoBoardSpec, *,
                      min_corners: int = 6, min_views: int = 8, max_views: int = 40, fix_k3: bool = False,
                      outlier_factor: float = 3.0, outlier_min_px: float = 1.0) -> CalibrationResult:
    """Calibrate pinhole + plumb_bob intrinsics from views of the board.

    images: arrays (labelled ``view N``) or (label, array) pairs, all of one size; read one at a time (only the
    detections are kept). A view is rejected when the board is not found, has fewer than ``min_corners`` corners,
    or they lie on one line; beyond ``max_views`` good views an evenly spread subset is used. After a first
    calibration, views whose RMS error exceeds ``outlier_factor`` x the median (and ``outlier_min_px``) are
    dropped and the camera calibrated once more. Fewer than ``min_views`` usable views: :class:`CalibrationError`.
    ``fix_k3`` holds k3 at 0 (ordinary, non-wide lenses; fewer views suffice)."""
    if min_views < 3:
        raise CalibrationError(f"min_views={min_views}: a calibration needs at least 3 views (8+ recommended)")
    if max_views < min_views:
        raise CalibrationError(f"max_views={max_views} < min_views={min_views}")
    board = spec.board()
    size: tuple[int, int] | None = None
    good: list[_Detection] = []
    rejected: list[ViewReport] = []
    n_seen = 0
    for i, item in enumerate(images):
        label, image = item if isinstance(item, tuple) else (f"view {i}", item)
        n_seen += 1
        gray = _gray(image)
        hw = (gray.shape[1], gray.shape[0])
        if size is None:
            size = hw
        elif hw != size:
            why = f"image {hw[0]}x{hw[1]} differs from the first, {size[0]}x{size[1]}"
            rejected.append(ViewReport(label, 0, reason=why))
            continue
        det = detect_charuco(gray, spec)
        if det is None:
            rejected.append(ViewReport(label, 0, reason="board not found"))
            continue
        corners, ids = det
        if len(ids) < min_corners:
            rejected.append(ViewReport(label, len(ids), reason=f"{len(ids)} corners < {min_corners}"))
            continue
        cols, rows = ids % (spec.squares_x - 1), ids // (spec.squares_x - 1)
        if len(set(cols.tolist())) < 2 or len(set(rows.tolist())) < 2:
            rejected.append(ViewReport(label, len(ids), reason="corners on one line"))
            continue
        good.append(_Detection(label, i, corners, ids))
    if len(good) < min_views:
        raise CalibrationError(
            f"the board was found with >= {min_corners} corners in {len(good)} of {n_seen} views; {min_views} are "
            f"needed ({spec.describe()}). Check that --squares, --dict, --square-mm and --marker-mm match the printed "
            "board, light it evenly without glare, keep it sharp (no motion blur) and wholly in view, and film more "
            "views (or lower --min-views)")  # fmt: skip
    if len(good) > max_views:
        keep = set(np.round(np.linspace(0, len(good) - 1, max_views)).astype(int).tolist())
        rejected += [ViewReport(d.label, len(d.ids), reason=f"more than --max-views {max_views} good views: thinned")
                     for j, d in enumerate(good) if j not in keep]
        good = [d for j, d in enumerate(good) if j in keep]
    assert size is not None
    rms, K, dist, per_view = _calibrate(board, good, size, fix_k3)
    med = float(np.median(per_view))
    limit = max(outlier_factor * med, outlier_min_px)
    out = per_view > limit
    if out.any() and len(good) - int(out.sum()) >= min_views:
        rejected += [ViewReport(d.label, len(d.ids), float(e), reason=f"outlier: view RMS {e:.2f} px > {limit:.2f} px "
                                f"({outlier_factor:g} x the median {med:.2f} px)")
                     for d, e, o in zip(good, per_view, out) if o]  # fmt: skip
        good = [d for d, o in zip(good, out) if not o]
        rms, K, dist, per_view = _calibrate(board, good, size, fix_k3)
    d5 = np.zeros(5)
    d5[: min(5, dist.size)] = dist.ravel()[:5]
    camera = PinholeCamera(width_px=size[0], height_px=size[1], fx_px=float(K[0, 0]), fy_px=float(K[1, 1]),
                           cx_px=float(K[0, 2]), cy_px=float(K[1, 2]), distortion_model="plumb_bob",
                           distortion=tuple(float(x) for x in d5))
    used = tuple(ViewReport(d.label, len(d.ids), float(e)) for d, e in zip(good, per_view))
    rejected.sort(key=lambda v: _label_order(v.label))
    result = CalibrationResult(camera, float(rms), used, tuple(rejected), _coverage(good, size))
    log.info("calibrated from %d views (%d rejected): RMS %.3f px", len(used), len(rejected), rms)
    return result


def _label_order(label: str):
    digits = "".join(ch for ch in label if ch.isdigit())
    return (int(digits) if digits else -1, label)


def _calibrate(board, views: list[_Detection], size: tuple[int, int], fix_k3: bool):
    obj, img = [], []
    for d in views:
        o, p = board.matchImagePoints(d.corners.reshape(-1, 1, 2), d.ids.reshape(-1, 1))
        obj.append(o.astype(np.float32))
        img.append(p.astype(np.float32))
    flags = cv2.CALIB_FIX_K3 if fix_k3 else 0
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-9)
    try:
        rms, K, dist, _, _, _, _, per_view = cv2.calibrateCameraExtended(obj, img, size, None, None, flags=flags,
                                                                         criteria=crit)
    except cv2.error as e:
        raise CalibrationError(f"OpenCV could not calibrate from {len(views)} views ({e.err}); film the board at "
                               "more varied angles (tilted 10-45 degrees) and distances") from None
    return float(rms), K, dist, np.asarray(per_view, dtype=float).reshape(-1)


def _coverage(views: list[_Detection], size: tuple[int, int], cells: int = 4) -> float:
    hit = np.zeros((cells, cells), dtype=bool)
    for d in views:
        c = np.clip((d.corners[:, 0] / size[0] * cells).astype(int), 0, cells - 1)
        r = np.clip((d.corners[:, 1] / size[1] * cells).astype(int), 0, cells - 1)
        hit[r, c] = True
    return float(hit.mean())


# ----------------------------------------------------------------------------------------------- the board image
def board_image(spec: CharucoBoardSpec, px_per_mm: float = 300 / 25.4, margin_mm: float = 10.0) -> np.ndarray:
    """The printable board (grey uint8), the squares exactly ``round(square_mm * px_per_mm)`` pixels, with a white
    margin of ``margin_mm``. Default: 300 dpi."""
    s_px = int(round(spec.square_mm * px_per_mm))
    if s_px < 8:
        raise CalibrationError(f"{px_per_mm:.2f} px/mm makes {s_px}-pixel squares; use a higher resolution")
    img = spec.board().generateImage((spec.squares_x * s_px, spec.squares_y * s_px), marginSize=0, borderBits=1)
    m = int(round(margin_mm * px_per_mm))
    return cv2.copyMakeBorder(img, m, m, m, m, cv2.BORDER_CONSTANT, value=255) if m > 0 else img


# ----------------------------------------------------------------------------------------------- synthetic views
@functools.lru_cache(maxsize=4)
def _rays(camera: PinholeCamera, supersample: int) -> np.ndarray:
    """Undistorted normalised rays (x, y, 1) of every (sub)pixel of the camera's image, (H*s, W*s, 3)."""
    s = supersample
    u = (np.arange(camera.width_px * s) + 0.5) / s - 0.5
    v = (np.arange(camera.height_px * s) + 0.5) / s - 0.5
    uu, vv = np.meshgrid(u, v)
    xy = camera.undistort_normalized(np.stack([uu, vv], axis=-1))
    return np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1)


def render_charuco_view(camera: PinholeCamera, spec: CharucoBoardSpec, R_cam_board: np.ndarray,
                        t_cam_board_m: np.ndarray, *, px_per_mm: float = 4.0, margin_mm: float = 10.0,
                        background: int = 128, supersample: int = 2, blur_px: float = 0.0, noise_std: float = 0.0,
                        rng: np.random.Generator | None = None) -> np.ndarray:
    """The board (printed on white paper with ``margin_mm``) as ``camera``, distortion included, sees it at pose
    ``(R_cam_board, t_cam_board_m)`` (board frame: see the module docstring): grey uint8 (H, W). Every output
    (sub)pixel's ray is undistorted, intersected with the board plane and the board image sampled there
    (``supersample`` x ``supersample`` samples per pixel, averaged); ``background`` elsewhere and behind the camera.
    ``blur_px``: Gaussian sigma; ``noise_std``: grey levels of Gaussian noise."""
    img = board_image(spec, px_per_mm, margin_mm).astype(np.float32)
    s_px = round(spec.square_mm * px_per_mm)
    mm_per_px = spec.square_mm / s_px
    margin_px = round(margin_mm * px_per_mm)
    R = np.asarray(R_cam_board, dtype=float)
    t = np.asarray(t_cam_board_m, dtype=float).reshape(3)
    H = np.column_stack([R[:, 0], R[:, 1], t])  # board (x, y, 1) [m] -> camera ray (up to scale)
    rays = _rays(camera, supersample)
    b = rays @ np.linalg.inv(H).T  # rays -> board (x w, y w, w)
    w = b[..., 2]
    # in front of the camera: the board point along +ray, i.e. lambda = 1 / w > 0
    front = w > 1e-12
    ws = np.where(front, w, 1.0)
    bx_mm, by_mm = 1000.0 * b[..., 0] / ws, 1000.0 * b[..., 1] / ws
    map_x = np.where(front, bx_mm / mm_per_px + margin_px - 0.5, -1e6).astype(np.float32)
    map_y = np.where(front, by_mm / mm_per_px + margin_px - 0.5, -1e6).astype(np.float32)
    hi = cv2.remap(img, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=float(background))
    out = cv2.resize(hi, (camera.width_px, camera.height_px), interpolation=cv2.INTER_AREA) if supersample > 1 else hi
    if blur_px > 0:
        out = cv2.GaussianBlur(out, (0, 0), blur_px)
    if noise_std > 0:
        out = out + (rng or np.random.default_rng()).normal(0.0, noise_std, out.shape).astype(np.float32)
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


@dataclasses.dataclass(frozen=True)
class SyntheticView:
    image: np.ndarray
    R_cam_board: np.ndarray
    t_cam_board_m: np.ndarray


def _rot(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    R, _ = cv2.Rodrigues(np.asarray(axis, dtype=float).reshape(3) * angle_rad)
    return R


def synthetic_views(camera: PinholeCamera, spec: CharucoBoardSpec, n: int, seed: int = 0, *,
                    tilt_deg: tuple[float, float] = (10.0, 45.0), fill: tuple[float, float] = (0.3, 0.8),
                    **render) -> list[SyntheticView]:
    """``n`` renders of the board at varied poses, as a calibration video should have them: tilted ``tilt_deg``
    about a random in-plane axis, rolled up to +-30 degrees, at distances where the board spans ``fill`` of the
    image width, placed in turn toward the image's corners, edges and centre (all inner corners in view; the
    outer squares may leave the image, as ChArUco allows, so that corners reach into the image's corners).
    ``render``: options of :func:`render_charuco_view`."""
    rng = np.random.default_rng(seed)
    w_m, h_m = (x / 1000.0 for x in spec.size_mm)
    centre_b = np.array([w_m / 2, h_m / 2, 0.0])
    sq = spec.square_mm / 1000.0  # the inner corners (all of them) must be in view; the outer squares may not
    outline_b = np.array([[sq, sq, 0], [w_m - sq, sq, 0], [w_m - sq, h_m - sq, 0], [sq, h_m - sq, 0],
                          [w_m / 2, sq, 0], [w_m - sq, h_m / 2, 0], [w_m / 2, h_m - sq, 0], [sq, h_m / 2, 0]])
    spots = [(a, b) for b in (0.0, 1.0, 0.5) for a in (0.0, 1.0, 0.5)]  # corners first, then edges, centre last
    views = []
    m = 6.0  # pixels between the outermost inner corners and the image's edge
    lo, hi = np.array([m, m]), np.array([camera.width_px - 1 - m, camera.height_px - 1 - m])
    for i in range(n):
        a, b = spots[i % len(spots)]
        corner = a != 0.5 and b != 0.5
        for _ in range(200):
            phi = rng.uniform(0, 2 * np.pi)
            roll = 10.0 if corner else 30.0  # a rolled board cannot reach into the image's corner
            R = _rot([math.cos(phi), math.sin(phi), 0.0], math.radians(rng.uniform(*tilt_deg))) @ \
                _rot([0, 0, 1.0], math.radians(rng.uniform(-roll, roll)))
            f = rng.uniform(*fill)
            z = camera.fx_px * w_m / (f * camera.width_px)
            inner = (1 - 2 * sq / w_m)  # the inner corners' share of the board's width
            half_u, half_v = 0.5 * f * inner * camera.width_px, 0.5 * f * camera.width_px * (h_m - 2 * sq) / w_m
            jit = rng.uniform(-0.1, 0.1, 2)
            u = half_u + (camera.width_px - 2 * half_u) * np.clip(a + jit[0], 0, 1)
            v = half_v + (camera.height_px - 2 * half_v) * np.clip(b + jit[1], 0, 1)
            ray = np.append(camera.undistort_normalized(np.array([u, v])), 1.0)
            t = z * ray - R @ centre_b
            for _ in range(5):  # slide the board until its inner corners touch the edges it is placed at
                uv, depth = camera.project_cam(outline_b @ R.T + t)
                if not np.all(depth > 0):
                    break
                shift = np.zeros(2)
                for k, pos in enumerate((a, b)):
                    if pos == 0.0:
                        shift[k] = lo[k] - uv[:, k].min()
                    elif pos == 1.0:
                        shift[k] = hi[k] - uv[:, k].max()
                t = t + np.array([shift[0] / camera.fx_px, shift[1] / camera.fy_px, 0.0]) * (t + R @ centre_b)[2]
            uv, depth = camera.project_cam(outline_b @ R.T + t)
            if np.all(depth > 0) and np.all((uv >= lo - 0.5) & (uv <= hi + 0.5)):
                break
        else:
            raise CalibrationError(f"no pose for synthetic view {i} keeps the board in view; widen fill/tilt ranges")
        img = render_charuco_view(camera, spec, R, t, rng=rng, **render)
        views.append(SyntheticView(img, R, t))
    return views


# ----------------------------------------------------------------------------------------------- comparing models
def projection_difference_px(camera_a: PinholeCamera, camera_b: PinholeCamera, *, grid: tuple[int, int] = (32, 24),
                             fit_rotation: bool = True) -> np.ndarray:
    """How far apart two models of one camera put the same rays: for a ``grid`` of pixels over ``camera_a``'s image,
    the distance (px, shape (rows, cols)) between each pixel and where ``camera_b`` projects its ray.

    ``fit_rotation``: first rotate the rays by the small rotation that best aligns the models (as mrcal's
    ``projection_diff`` does): a principal point off by a pixel is, to within a small fraction of a pixel, the same
    camera turned by 1/f radians, which a calibration cannot tell apart from the board's pose and which the
    drone's attitude absorbs; what remains is the difference in the lens model (focal lengths, distortion)."""
    u, v = np.meshgrid(np.linspace(0.5, camera_a.width_px - 0.5, grid[0]),
                       np.linspace(0.5, camera_a.height_px - 0.5, grid[1]))
    uv = np.stack([u, v], axis=-1)
    xy = camera_a.undistort_normalized(uv)
    rays = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1).reshape(-1, 3)

    def resid(w: np.ndarray) -> np.ndarray:
        R = _rot(w, 1.0) if np.any(w) else np.eye(3)
        return (camera_b.project_cam(rays @ R.T)[0] - uv.reshape(-1, 2)).ravel()

    w = np.zeros(3)
    if fit_rotation:
        for _ in range(10):  # Gauss-Newton on the rotation vector (numeric Jacobian; the rotation is tiny)
            r0 = resid(w)
            J = np.column_stack([(resid(w + e) - r0) / 1e-7 for e in np.eye(3) * 1e-7])
            step = np.linalg.lstsq(J, -r0, rcond=None)[0]
            w = w + step
            if np.linalg.norm(step) < 1e-10:
                break
    return np.linalg.norm(resid(w).reshape(-1, 2), axis=-1).reshape(uv.shape[:-1])
