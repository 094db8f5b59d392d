"""The 3D view's projection maths (no Qt): orbit camera, NED -> view, perspective projection."""

from __future__ import annotations

import math

import numpy as np
import pytest

from groundstation.app import view3d


def test_camera_north_of_target_looks_south_with_east_on_the_left():
    pos, R = view3d.orbit_camera((0.0, 0.0, 0.0), azimuth_rad=0.0, elevation_rad=0.0, distance_m=10.0)
    assert np.allclose(pos, [10.0, 0.0, 0.0])
    assert np.allclose(R @ R.T, np.eye(3))  # a rotation
    assert np.isclose(np.linalg.det(R), 1.0)
    v = view3d.ned_to_view([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]], pos, R)
    assert np.allclose(v[0], [0, 0, 10])  # the target straight ahead, 10 m deep
    assert v[1][0] < 0  # east is on the image's left when looking south
    assert v[2][1] < 0  # up (negative down) is up in the image


def test_elevation_puts_the_camera_above_and_looking_down():
    pos, R = view3d.orbit_camera((1.0, 2.0, -1.0), azimuth_rad=math.pi / 2, elevation_rad=math.radians(30),
                                 distance_m=4.0)
    assert np.allclose(pos, [1.0, 2.0 + 4 * math.cos(math.radians(30)), -1.0 - 2.0])  # east of it, 2 m higher
    assert R[2, 2] > 0  # forward has a downward component


def test_projection_of_known_points():
    pos, R = view3d.orbit_camera((0.0, 0.0, 0.0), 0.0, 0.0, 10.0)
    w, h, vfov = 800, 600, math.radians(60)
    f = 300 / math.tan(math.radians(30))
    uv = view3d.project_ned([[0, 0, 0], [0, -1, 0], [0, 0, -2], [20, 0, 0]], pos, R, w, h, vfov)
    assert np.allclose(uv[0], [400, 300])
    assert np.allclose(uv[1], [400 + f * 0.1, 300])  # west 1 m at 10 m: right of centre when looking south
    assert np.allclose(uv[2], [400, 300 - f * 0.2])
    assert np.all(np.isnan(uv[3]))  # behind the camera


def test_helpers_shapes_and_bone_sides():
    g = view3d.ground_grid(0.0, 0.0, 5.0, 1.0)
    assert g.shape[1:] == (2, 3) and np.all(g[:, :, 2] == 0.0)
    c = view3d.circle_ned(1.0, 2.0, -6.0, 8.0, n=32)
    assert c.shape == (33, 3) and np.allclose(np.hypot(c[:, 0] - 1, c[:, 1] - 2), 8.0) and np.allclose(c[:, 2], -6)
    fr = view3d.frustum_segments((0, 0, -5), 0.0, math.radians(45), math.radians(60), math.radians(40), 2.0)
    assert fr.shape == (8, 2, 3) and np.all(fr[:4, 1, 0] > 0) and np.all(fr[:4, 1, 2] > -5)  # north and down
    from skycap.skeleton import COCO17_NAMES as N
    assert view3d.bone_side(N, 5, 7) == view3d.LEFT and view3d.bone_side(N, 6, 8) == view3d.RIGHT
    assert view3d.bone_side(N, 5, 6) == view3d.CENTRE
    with pytest.raises(ValueError, match="positive"):
        view3d.orbit_camera((0, 0, 0), 0, 0, 0.0)
