"""Overlapping time windows over a long flight and their stitching into one motion (pure functions).

Windows of ``window_s`` start every ``window_s - overlap_s``; the last one ends at the span's end and is as long as
the others (it overlaps its neighbour more), a short tail is folded into it. Each is fitted on its own; :func:`stitch` cross-fades neighbouring windows over their
overlap with weights that ramp linearly from 0 at a window's edge to 1 at ``overlap_s`` inside it, so the motion is
continuous at every boundary and equals the single window's result away from the overlaps.
"""

from __future__ import annotations

import numpy as np

__all__ = ["motion_steps", "plan_windows", "seam_figures", "seam_mask", "stitch", "window_weight"]


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


def seam_mask(t_ns: np.ndarray, windows: list[tuple[int, int]], pad_s: float = 0.5) -> np.ndarray:
    """(T-1,) True for the frame-to-frame steps ``t[i] -> t[i+1]`` that touch a seam: the overlap of two
    neighbouring windows (``[start of window k+1, end of window k]``) widened by ``pad_s`` on both sides."""
    t = np.asarray(t_ns, dtype=np.int64)
    mid = (t[:-1] + t[1:]) // 2 if len(t) > 1 else t[:0]
    pad = int(pad_s * 1e9)
    m = np.zeros(len(mid), bool)
    for (_, b0), (a1, _) in zip(windows, windows[1:]):
        m |= (mid >= min(a1, b0) - pad) & (mid <= max(a1, b0) + pad)
    return m


def motion_steps(t_ns: np.ndarray, joints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per frame-to-frame step of a motion (T, J, 3): the largest joint displacement (m, (T-1,)) and the largest
    change of a joint's velocity against the previous step (m/s, (T-1,); 0 for the first step)."""
    t = np.asarray(t_ns, dtype=np.int64)
    d = np.diff(np.asarray(joints, dtype=float), axis=0)  # (T-1, J, 3)
    disp = np.linalg.norm(d, axis=-1).max(axis=-1) if len(d) else np.zeros(0)
    dt = np.maximum(np.diff(t) * 1e-9, 1e-9)
    v = d / dt[:, None, None]
    dv = np.zeros(len(d))
    if len(d) > 1:
        dv[1:] = np.linalg.norm(np.diff(v, axis=0), axis=-1).max(axis=-1)
    return disp, dv


def seam_figures(t_ns: np.ndarray, joints: np.ndarray, windows: list[tuple[int, int]], pad_s: float = 0.5) -> dict:
    """How continuous a stitched motion is at the window seams against inside the windows: the largest and the 99th
    percentile frame-to-frame joint displacement (``step_m``) and velocity change (``dv_mps``), for the steps at a seam
    (:func:`seam_mask`) and for the others. A jump at a seam shows as a seam maximum far above the inside maximum."""
    disp, dv = motion_steps(t_ns, joints)
    m = seam_mask(t_ns, windows, pad_s)
    out: dict = {"seams": max(0, len(windows) - 1), "steps_at_seams": int(m.sum()), "steps_inside": int((~m).sum())}
    for name, x in (("step_m", disp), ("dv_mps", dv)):
        for where, sel in (("seam", m), ("inside", ~m)):
            v = x[sel]
            out[f"{name}_{where}_max"] = float(v.max()) if len(v) else None
            out[f"{name}_{where}_p99"] = float(np.percentile(v, 99)) if len(v) else None
    return out
