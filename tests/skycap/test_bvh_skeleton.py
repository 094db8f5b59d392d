import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from skycap.bvh import BvhError, Skeleton, read_bvh, write_bvh
from skycap.skeleton import COCO17_FLIP, COCO17_LIMBS, limb_lengths, mocap_to_coco17

SIMPLE = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Knee
  {
    OFFSET 0 -10 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    End Site
    {
      OFFSET 0 -10 0
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.5
1 2 3 0 0 0 0 0 0
0 0 0 90 0 0 90 0 0
"""


def test_forward_kinematics_by_hand(tmp_path):
    f = tmp_path / "s.bvh"
    f.write_text(SIMPLE)
    m = read_bvh(f)
    assert m.skeleton.names == ["Hips", "Knee", "Knee_End"] and m.fps == 2.0
    p = m.world_positions()
    assert np.allclose(p[0], [[1, 2, 3], [1, -8, 3], [1, -18, 3]])
    # Hips rotated 90 deg about Z: (0,-10,0) -> (10,0,0); knee another 90: end goes to (0, 10, 0) from knee.
    assert np.allclose(p[1], [[0, 0, 0], [10, 0, 0], [10, 10, 0]], atol=1e-9)


def test_truncated_and_malformed_files_are_named(tmp_path):
    f = tmp_path / "t.bvh"
    f.write_text(SIMPLE.rsplit("\n", 2)[0])  # drop the last frame
    with pytest.raises(BvhError, match="truncated"):
        read_bvh(f)
    f.write_text(SIMPLE.replace("CHANNELS 3", "CHANNELS 4"))
    with pytest.raises(BvhError, match=r"t\.bvh:\d+"):
        read_bvh(f)


def test_write_then_independent_reader(tmp_path):
    bvhio = pytest.importorskip("bvhio")
    rng = np.random.default_rng(1)
    sk = Skeleton(
        names=["root", "a", "b", "b_End"],
        parents=np.array([-1, 0, 1, 2]),
        offsets=np.array([[0, 0, 0], [0, 10, 0], [0, 0, 12], [5, 0, 0.0]]),
        channels=[[], [], [], []],
        end_site=np.array([False, False, False, True]),
    )
    T = 4
    R = Rotation.random(T * 4, random_state=2).as_matrix().reshape(T, 4, 3, 3)
    root = rng.normal(size=(T, 3)) * 10
    f = write_bvh(tmp_path / "w.bvh", sk, 1 / 30, root, R)
    ours = read_bvh(f).world_positions()
    hier = bvhio.readAsHierarchy(str(f))
    for t in range(T):
        hier.loadPose(t)
        for j, name in enumerate(["root", "a", "b"]):
            pos = np.array(hier.filter(name)[0].PositionWorld)
            assert np.allclose(pos, ours[t, j], atol=1e-3), (t, name)


def test_cmu_mapping_plausible(cmu_dir):
    m = read_bvh(cmu_dir / "002" / "002_01.bvh").slice(1)  # frame 0 is a T-pose
    j = mocap_to_coco17(m)
    assert j.shape == (m.num_frames, 17, 3)
    height = -(j[..., 0, 2] - j[..., [15, 16], 2].max(-1))  # nose above the lower ankle (NED down)
    assert 1.4 < np.median(height) < 1.8
    L = limb_lengths(j)
    assert np.all(L.std(0) < 0.02), "bone lengths must be constant over time"
    # Left is the person's left: with forward = walking direction and up = -down, left = up x forward.
    fwd = j[-1, 11] - j[0, 11]
    fwd[2] = 0
    left = np.cross([0, 0, -1.0], fwd / np.linalg.norm(fwd))
    assert np.mean((j[:, 5] - j[:, 6]) @ left) > 0.2
    assert np.mean((j[:, 0] - 0.5 * (j[:, 3] + j[:, 4])) @ (fwd / np.linalg.norm(fwd))) > 0.05
    assert sorted(COCO17_FLIP) == list(range(17)) and len(COCO17_LIMBS) == 16
