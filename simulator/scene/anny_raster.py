"""A small vectorised z-buffer triangle rasteriser in numpy (for the Anny body mesh, a few thousand
triangles covering at most a few hundred pixels squared).

    out = rasterize(uv_px, depth_m, faces, colors, roi=(x0, y0, x1, y1), scale=2)
    out.color  # (h, w, 3) float32 at the ROI's (super)sampled resolution; out.mask (h, w) bool

How: every triangle's pixel-centre bounding box is enumerated at once (``np.repeat``), barycentric
coordinates from the three edge functions keep the samples inside it, and the nearest sample per pixel
wins (one ``np.lexsort`` by pixel then depth). Colours are interpolated (Gouraud) from per-vertex
colours. Depth is interpolated linearly in screen space (triangles are a few pixels wide: the error
against perspective-correct interpolation is far below the depth gaps between body parts).

Why numpy and not OpenGL: this machine (and the CI's) has no GPU and no OSMesa/EGL libraries, pyrender
and moderngl are not installed, and the simulator must not need torch; a mesh of ~2.5k triangles in a
person's box costs a few milliseconds this way.
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["Raster", "rasterize", "MAX_SAMPLES"]

#: cap on enumerated candidate samples per call (a person filling the screen is rendered coarser)
MAX_SAMPLES = 4_000_000


@dataclasses.dataclass
class Raster:
    """color (h, w, C) float32 (0 where empty), mask (h, w) bool, depth (h, w) float32 (inf where empty),
    face (h, w) int32 (-1 where empty)."""

    color: np.ndarray
    mask: np.ndarray
    depth: np.ndarray
    face: np.ndarray


def rasterize(
    uv_px: np.ndarray,
    depth: np.ndarray,
    faces: np.ndarray,
    colors: np.ndarray | None,
    roi: tuple[int, int, int, int],
    scale: float = 1.0,
    cull_back: bool = False,
) -> Raster:
    """Rasterise triangles ``faces`` (F, 3) of vertices at image pixels ``uv_px`` (V, 2) (pixel centres at
    +0.5) with depths ``depth`` (V,) into the ROI ``(x0, y0, x1, y1)`` sampled ``scale`` times per pixel
    per axis. ``colors`` (V, C) are interpolated (None: no colour). ``cull_back`` keeps only triangles
    with a positive signed area in pixel coordinates (x right, y down); callers order the faces' vertices
    so that front faces have it."""
    x0, y0, x1, y1 = roi
    w = max(int(round((x1 - x0) * scale)), 1)
    h = max(int(round((y1 - y0) * scale)), 1)
    C = 0 if colors is None else colors.shape[1]
    zbuf = np.full((h, w), np.inf, np.float32)
    fbuf = np.full((h, w), -1, np.int32)
    cbuf = np.zeros((h, w, C), np.float32)
    # vertices in sample coordinates: sample (i, j) centre at (j + 0.5, i + 0.5)
    sx = (uv_px[:, 0] - x0) * (w / max(x1 - x0, 1e-9))
    sy = (uv_px[:, 1] - y0) * (h / max(y1 - y0, 1e-9))
    fa, fb, fc = faces[:, 0], faces[:, 1], faces[:, 2]
    ax, ay, bx, by, cx, cy = sx[fa], sy[fa], sx[fb], sy[fb], sx[fc], sy[fc]
    area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
    keep = np.abs(area) > 1e-9
    if cull_back:
        keep &= area > 0
    keep &= (depth[fa] > 0) & (depth[fb] > 0) & (depth[fc] > 0)
    xmin = np.maximum(np.ceil(np.minimum(np.minimum(ax, bx), cx) - 0.5), 0).astype(np.int64)
    xmax = np.minimum(np.floor(np.maximum(np.maximum(ax, bx), cx) - 0.5), w - 1).astype(np.int64)
    ymin = np.maximum(np.ceil(np.minimum(np.minimum(ay, by), cy) - 0.5), 0).astype(np.int64)
    ymax = np.minimum(np.floor(np.maximum(np.maximum(ay, by), cy) - 0.5), h - 1).astype(np.int64)
    keep &= (xmax >= xmin) & (ymax >= ymin)
    fi = np.nonzero(keep)[0]
    if len(fi) == 0:
        return Raster(cbuf, np.zeros((h, w), bool), zbuf, fbuf)
    bw = (xmax[fi] - xmin[fi] + 1)
    bh = (ymax[fi] - ymin[fi] + 1)
    n = bw * bh
    total = int(n.sum())
    if total > MAX_SAMPLES:
        raise ValueError(f"rasterize: {total} candidate samples exceed {MAX_SAMPLES}; lower the scale")
    start = np.cumsum(n) - n
    f_rep = np.repeat(np.arange(len(fi)), n)
    k = np.arange(total) - start[f_rep]
    bw_r = bw[f_rep]
    px = xmin[fi][f_rep] + k % bw_r
    py = ymin[fi][f_rep] + k // bw_r
    F = fi[f_rep]
    qx = px + 0.5
    qy = py + 0.5
    inv = 1.0 / area[F]
    # barycentric weights of a, b, c from the edge functions (either winding)
    wa = ((bx[F] - qx) * (cy[F] - qy) - (by[F] - qy) * (cx[F] - qx)) * inv
    wb = ((cx[F] - qx) * (ay[F] - qy) - (cy[F] - qy) * (ax[F] - qx)) * inv
    wc = 1.0 - wa - wb
    eps = -1e-6
    inside = (wa >= eps) & (wb >= eps) & (wc >= eps)
    if not inside.any():
        return Raster(cbuf, np.zeros((h, w), bool), zbuf, fbuf)
    F, px, py, wa, wb, wc = F[inside], px[inside], py[inside], wa[inside], wb[inside], wc[inside]
    z = wa * depth[fa[F]] + wb * depth[fb[F]] + wc * depth[fc[F]]
    pix = py * w + px
    order = np.lexsort((z, pix))
    ps = pix[order]
    first = np.ones(len(ps), bool)
    first[1:] = ps[1:] != ps[:-1]
    win = order[first]
    P = pix[win]
    zbuf.reshape(-1)[P] = z[win]
    fbuf.reshape(-1)[P] = F[win]
    if C:
        Fw = F[win]
        col = (wa[win, None] * colors[fa[Fw]] + wb[win, None] * colors[fb[Fw]] + wc[win, None] * colors[fc[Fw]])
        cbuf.reshape(-1, C)[P] = col
    return Raster(cbuf, fbuf >= 0, zbuf, fbuf)
