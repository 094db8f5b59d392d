"""Overlapping time windows over a long flight and their stitching into one motion (pure functions).

Windows of ``window_s`` start every ``window_s - overlap_s``; the last one ends at the span's end and is as long as
the others (it overlaps its neighbour more), a short tail is folded into it. Each is fitted on its own; :func:`stitch` cross-fades neighbouring windows over their
overlap with weights that ramp linearly from 0 at a window's edge to 1 at ``overlap_s`` inside it, so the motion is
continuous at every boundary and equals the single window's result away from the overlaps.
"""

from __future__ import annotations

import numpy as np

__all__ = ["plan_windows", "stitch", "window_weight"]


def plan_windows(t0_ns: int, t1_ns: int, window_s: float, overlap_s: float) -> list[tuple[int, int]]:
    """[(start_ns, end_ns)] covering [t0, t1], consecutive windows sharing ``overlap_s``."""
    span = (t1_ns - t0_ns) * 1e-9
    if span <= window_s:
        return [(int(t0_ns), int(t1_ns))]
    step = window_s - overlap_s
    n = max(1, int(np.ceil((span - overlap_s) / step - 1e-9)))
    if n > 1 and (span - (n - 1) * step) < overlap_s + 0.5 * step:  # fold a short tail into the last window
        n -= 1
    out = []
    for k in range(n):
        a = t0_ns + int(round(k * step * 1e9))
        b = t1_ns if k == n - 1 else a + int(round(window_s * 1e9))
        if k == n - 1:  # a full-length last window (it overlaps its neighbour more)
            a = min(a, t1_ns - int(round(window_s * 1e9)))
        out.append((int(a), int(min(b, t1_ns))))
    return out


def window_weight(t_ns: np.ndarray, start_ns: int, end_ns: int, overlap_s: float, first: bool, last: bool) -> np.ndarray:
    """Blend weight of a window at times ``t_ns``: 0 outside it, ramping to 1 over ``overlap_s`` from each inner
    edge (the flight's own start and end -- ``first`` / ``last`` -- get no ramp)."""
    t = np.asarray(t_ns, dtype=np.int64)
    w = ((t >= start_ns) & (t <= end_ns)).astype(float)
    if overlap_s > 0:
        ov = overlap_s * 1e9
        if not first:
            w *= np.clip((t - start_ns) / ov, 0.0, 1.0)
        if not last:
            w *= np.clip((end_ns - t) / ov, 0.0, 1.0)
    return w


def stitch(grid_ns: np.ndarray, windows: list[tuple[int, int]], results: list[tuple[np.ndarray, np.ndarray] | None],
           overlap_s: float) -> tuple[np.ndarray, np.ndarray]:
    """One motion on ``grid_ns`` (T,) from per-window results [(t_ns (Tw,), joints (Tw, 17, 3)) or None (failed)].
    Each window's joints are interpolated linearly to the grid times inside it and cross-faded (see the module doc).
    Returns (t_ns (T',), joints (T', 17, 3)): the grid times some window covers."""
    grid = np.asarray(grid_ns, dtype=np.int64)
    acc = np.zeros((len(grid), 17, 3))
    wsum = np.zeros(len(grid))
    n = len(windows)
    ok = [k for k in range(n) if results[k] is not None and len(results[k][0])]
    for k in ok:
        a, b = windows[k]
        t, J = results[k]
        t = np.asarray(t, dtype=np.int64)
        # a neighbour that failed leaves no overlap to fade into: keep full weight at that edge
        first = k == 0 or (k - 1) not in ok
        last = k == n - 1 or (k + 1) not in ok
        a_eff, b_eff = max(a, int(t[0])), min(b, int(t[-1]))
        w = window_weight(grid, a_eff, b_eff, overlap_s, first, last)
        if first:
            w = np.where(grid >= a_eff, w, 0.0)
        sel = w > 0
        if not sel.any():
            continue
        tq = (grid[sel] - t[0]).astype(float)
        tt = (t - t[0]).astype(float)
        Ji = np.stack([np.stack([np.interp(tq, tt, J[:, j, c]) for c in range(3)], -1) for j in range(17)], 1)
        acc[sel] += w[sel, None, None] * Ji
        wsum[sel] += w[sel]
    keep = wsum > 1e-9
    return grid[keep], acc[keep] / wsum[keep, None, None]
