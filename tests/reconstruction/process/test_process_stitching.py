"""Window stitching of a long flight (pure functions): many windows whose fits disagree by an offset each still give
one continuous motion (no position or velocity jump at a seam beyond what the cross-fade spreads over the overlap);
the seam figures of the long-flight bench find a jump; a killed writer's temporary cache file is cleaned."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np

from reconstruction.process.cache import atomic_write_npz, read_npz, remove_stale_temporaries
from reconstruction.process.windows import plan_windows, seam_figures, seam_mask, stitch

S = 1_000_000_000


def _walk(grid_ns: np.ndarray) -> np.ndarray:
    """A smooth 'motion' (T, 17, 3): 1.3 m/s forward, a 1 Hz sway per joint."""
    t = grid_ns * 1e-9
    J = np.zeros((len(t), 17, 3))
    J[..., 0] = 1.3 * t[:, None]
    J[..., 1] = 0.1 * np.sin(2 * np.pi * t[:, None] + np.arange(17)[None])
    J[..., 2] = -0.05 * np.arange(17)[None]
    return J


def test_many_windows_with_offsets_stitch_into_one_continuous_motion():
    rate_hz, window_s, overlap_s = 10.0, 60.0, 6.0
    grid = np.arange(0, int(600 * S) + 1, int(S / rate_hz))  # a 10-minute flight
    truth = _walk(grid)
    windows = plan_windows(int(grid[0]), int(grid[-1]), window_s, overlap_s)
    assert len(windows) == 11 and windows[0][0] == 0 and windows[-1][1] == grid[-1]
    rng = np.random.default_rng(3)
    offsets = rng.normal(0.0, 0.05, size=(len(windows), 1, 3))  # each window's fit off by ~5 cm (its own bias)
    results = []
    for k, (a, b) in enumerate(windows):
        sel = (grid >= a) & (grid <= b)
        results.append((grid[sel], truth[sel] + offsets[k]))
    t, J = stitch(grid, windows, results, overlap_s)
    np.testing.assert_array_equal(t, grid)  # every frame covered, once
    err = J - truth
    # each window's own result away from the overlaps
    for k, (a, b) in enumerate(windows):
        inner = (grid >= (windows[k - 1][1] if k else a)) & (grid <= (windows[k + 1][0] if k + 1 < len(windows) else b))
        np.testing.assert_allclose(err[inner], np.broadcast_to(offsets[k], err[inner].shape), atol=1e-12)
    # no jump: a seam changes the error by at most the offset difference spread over the overlap's frames
    d_off = np.abs(np.diff(offsets[:, 0], axis=0)).max()
    step_err = np.abs(np.diff(err, axis=0)).max()
    assert step_err <= d_off / (overlap_s * rate_hz) + 1e-9, (step_err, d_off)
    # the motion's frame-to-frame steps at the seams are the truth's plus that ramp, not more
    f = seam_figures(t, J, windows)
    ft = seam_figures(t, truth, windows)
    assert f["seams"] == 10 and f["steps_at_seams"] > 0 and f["steps_inside"] > 0
    assert f["step_m_seam_max"] <= ft["step_m_seam_max"] + np.sqrt(3) * d_off / (overlap_s * rate_hz) + 1e-9
    # velocity: the ramp changes the velocity by at most offset difference / overlap at its two ends
    assert f["dv_mps_seam_max"] <= ft["dv_mps_seam_max"] + np.sqrt(3) * d_off / overlap_s + 1e-9


def test_a_jump_at_a_seam_shows_in_the_seam_figures():
    grid = np.arange(0, int(120 * S) + 1, S // 10)
    truth = _walk(grid)
    windows = plan_windows(0, int(grid[-1]), 60.0, 6.0)
    assert len(windows) == 2
    # stitched without cross-fade (overlap 0 given to stitch: the overlap is their mean): the second window's 60 cm
    # offset appears in two 30 cm steps
    results = [(grid[(grid >= a) & (grid <= b)], truth[(grid >= a) & (grid <= b)] + (0.6 if k else 0.0))
               for k, (a, b) in enumerate(windows)]
    t, J = stitch(grid, windows, results, 0.0)
    f = seam_figures(t, J, windows)
    assert f["step_m_seam_max"] > f["step_m_inside_max"] + 0.25, f
    t, J = stitch(grid, windows, results, 6.0)  # the cross-fade removes it
    f = seam_figures(t, J, windows)
    assert f["step_m_seam_max"] < 1.2 * f["step_m_inside_max"], f


def test_seam_mask_marks_the_overlaps_and_their_pad():
    t = np.arange(0, 21) * S  # 1 Hz
    m = seam_mask(t, [(0, 12 * S), (8 * S, 20 * S)], pad_s=1.0)
    mid = (t[:-1] + t[1:]) / 2 / S
    assert mid[m].min() == 7.5 and mid[m].max() == 12.5
    assert not seam_mask(t, [(0, 20 * S)]).any()


def test_a_killed_writers_temporary_is_removed_when_the_entry_is_written_again(tmp_path):
    target = tmp_path / "fit" / "key-w003.npz"
    target.parent.mkdir()
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead_pid = int(dead.stdout)  # a process that has ended
    stale = target.with_name(f".{target.name}.{dead_pid}.tmp")
    stale.write_bytes(b"half an npz")
    live = target.with_name(f".{target.name}.{os.getppid()}.tmp")  # a writer that is still running
    live.write_bytes(b"being written")
    other = target.with_name(f".key-w004.npz.{dead_pid}.tmp")  # another entry's: left to that entry
    other.write_bytes(b"x")
    atomic_write_npz(target, x=np.arange(3))
    assert read_npz(target)["x"].tolist() == [0, 1, 2]
    assert not stale.exists() and live.exists() and other.exists()
    assert remove_stale_temporaries(target.with_name("key-w004.npz")) == [other]
