"""write_blender_bvh streams the motion in windows: the same file as one pass over the whole motion, memory that
does not grow with the motion's length."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from reconstruction.export import BLENDER_FPS, _fit_skeleton, _write_skeleton_bvh, write_blender_bvh
from reconstruction.synth import procedural_walker
from skycap.bvh import read_bvh


@pytest.fixture(scope="module")
def walk():
    """A rigid walker at ~10 Hz with irregular frame times, noise (not rigid), a NaN frame and a repeated time."""
    J, t_ns, shape, *_ = procedural_walker(90, fps=10.0)
    rng = np.random.default_rng(3)
    J = J + rng.normal(0, 0.01, J.shape)
    t_ns = t_ns + rng.integers(-20_000_000, 20_000_000, len(t_ns))
    t_ns[0] = 0
    J[17, 4] = np.nan
    t_ns[40] = t_ns[39]
    return J, t_ns, shape


def _one_pass_bvh(path, joints_ned, t_ns, shape):
    """The former write_blender_bvh (before it was windowed): the skeleton fitted and slerped over all frames."""
    keep = np.all(np.isfinite(joints_ned), axis=(1, 2))
    t_max = np.maximum.accumulate(np.where(keep, t_ns, np.iinfo(np.int64).min))
    keep[1:] &= t_ns[1:] > t_max[:-1]
    t_first = int(t_ns[0])
    joints_ned, t_ns = joints_ned[keep], t_ns[keep]
    shape, R_root, R_loc, transl, err = _fit_skeleton(joints_ned, shape)
    t_s = (t_ns - t_first) * 1e-9
    t_new = np.arange(int(np.floor(t_s[-1] * BLENDER_FPS + 1e-9)) + 1) / BLENDER_FPS
    t_new = np.clip(t_new, t_s[0], t_s[-1])
    R_root = Slerp(t_s, Rotation.from_matrix(R_root))(t_new).as_matrix()
    R_loc = np.stack([Slerp(t_s, Rotation.from_matrix(R_loc[:, j]))(t_new).as_matrix() for j in range(R_loc.shape[1])], 1)
    transl = np.stack([np.interp(t_new, t_s, transl[:, a]) for a in range(3)], axis=-1)
    return _write_skeleton_bvh(path, shape, R_root, R_loc, transl, 1.0 / BLENDER_FPS, 1.0), err


@pytest.mark.parametrize("given_shape", [True, False])
def test_windows_write_the_same_file_as_one_pass(walk, tmp_path, given_shape):
    J, t_ns, shape = walk
    shape = shape if given_shape else None
    ref, err_ref = _one_pass_bvh(tmp_path / "one_pass.bvh", J, t_ns, shape)
    n_frames = read_bvh(ref).num_frames
    assert n_frames > 200
    for w in (2, 7, 10**6):  # small and odd windows, the whole motion at once
        p, err = write_blender_bvh(tmp_path / f"w{w}.bvh", J, t_ns, shape, window_frames=w)
        assert p.read_bytes() == ref.read_bytes(), f"window_frames={w}"
        assert err == err_ref


def test_single_frame(tmp_path, walk):
    J, t_ns, shape = walk
    p, err = write_blender_bvh(tmp_path / "one.bvh", J[:1], t_ns[:1], shape, window_frames=4)
    assert read_bvh(p).num_frames == 1 and err < 0.05


def _peak_bytes(tmp_path, J, t_ns, shape, name) -> int:
    tracemalloc.start()
    try:
        write_blender_bvh(tmp_path / name, J, t_ns, shape, window_frames=128)
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_memory_does_not_grow_with_the_motion(tmp_path):
    """Twice the frames (BVH 1440 vs 2880 frames at 24 fps, windows of 128): the peak grows only by the
    input-sized arrays."""
    base, t_base, shape, *_ = procedural_walker(100, fps=10.0)
    n = 600  # 60 s at 10 Hz
    reps = -(-2 * n // len(base))
    J2 = np.concatenate([base + np.array([k * 12.0, 0, 0]) for k in range(reps)])[: 2 * n]
    t2 = (np.arange(2 * n) * 100_000_000).astype(np.int64)
    J1, t1 = J2[:n], t2[:n]
    peak1 = _peak_bytes(tmp_path, J1, t1, shape, "short.bvh")
    peak2 = _peak_bytes(tmp_path, J2, t2, shape, "long.bvh")
    input_bytes = J1.nbytes  # what the caller's motion itself grows by
    assert read_bvh(tmp_path / "long.bvh").num_frames > 1.99 * read_bvh(tmp_path / "short.bvh").num_frames
    # one pass over the whole motion (before the windows) peaked at 13.9 MB here, 27.7 MB for the 2x motion
    assert peak1 < 10e6, peak1
    print(f"tracemalloc peak: {peak1 / 1e6:.1f} MB for {n} frames, {peak2 / 1e6:.1f} MB for {2 * n}")
    assert peak2 - peak1 < 3 * input_bytes + 2e6, (peak1, peak2, input_bytes)
