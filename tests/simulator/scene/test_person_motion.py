"""The simulated person performing a recorded BVH motion (``skycap sim --motion`` / ``skycap demo --motion``)."""

from __future__ import annotations

import hashlib
import math

import numpy as np
import pytest

from simulator.scene.person import BvhPerson, PersonError, PersonMotionConfig, load_bvh_motion
from simulator.truth import PersonTruth
from tests.helpers.bvh import write_bvh


def test_tiny_bvh_in_inches_is_detected_placed_and_played(tmp_path):
    f = write_bvh(tmp_path / "walk.bvh")
    m = load_bvh_motion(PersonMotionConfig(file=str(f), center_ne_m=[2.0, -1.0]))
    assert m.rig == "cmu" and m.units == "inches" and m.units_detected and m.up_axis == "y"
    assert m.units_to_m == pytest.approx(0.0254) and m.head_above_ankles_m == pytest.approx(1.47, abs=1e-3)
    assert 1.55 < m.height_m < 1.85
    assert m.skipped_first_frame and m.num_frames == 30  # the T-pose frame left out
    assert m.sha256 == hashlib.sha256(f.read_bytes()).hexdigest()
    J = m.joints_ned_m
    assert J.shape == (30, 17, 3)
    # on the recorded floor (ankles 8 cm up), facing +z of the file = east in NED, walking east 1 m
    assert np.min(-J[:, 15:17, 2]) == pytest.approx(0.08, abs=1e-3) and "as recorded" in m.ground
    root = 0.5 * (J[:, 11] + J[:, 12])
    assert root[-1, 1] - root[0, 1] == pytest.approx(1.0 * 29 / 30, abs=1e-3) and np.ptp(root[:, 0]) < 1e-6
    mid = 0.5 * (root[:, :2].min(axis=0) + root[:, :2].max(axis=0))
    assert np.allclose(mid, [2.0, -1.0], atol=1e-6)  # the middle of the root track at the centre
    assert J[0, 5, 0] > J[0, 6, 0]  # facing east, the left shoulder is north of the right one
    assert J[0, 9, 2] > J[0, 5, 2] + 0.4  # arms down: wrists below the shoulders (NED: down is +)
    # the person: heading east, the nose ahead of the head
    s = BvhPerson(m).state_at(0.2)
    assert s.heading_rad == pytest.approx(math.pi / 2, abs=1e-6) and s.motion == "bvh:walk" and not s.walking
    assert np.allclose(s.root_ned_m, 0.5 * (s.joints_ned_m[11] + s.joints_ned_m[12]))
    # loop: period = duration - seam blend; continuous across the seam (the root slides back within the blend)
    assert m.end == "loop" and m.period_s == pytest.approx(m.duration_s - m.blend_s)
    ts = np.arange(0.0, 3 * m.period_s, 0.002)
    P = np.array([m.sample(t) for t in ts])
    assert np.max(np.linalg.norm(np.diff(P, axis=0), axis=-1)) < 0.05  # no jump (< 5 cm in 2 ms anywhere)
    assert np.allclose(m.sample(m.period_s + m.blend_s + 0.1), m.sample(m.blend_s + 0.1))  # then as recorded
    assert "loops" in m.note(60.0) and "played it" in m.info(60.0)["note"]
    # clamp: the last frame held
    c = load_bvh_motion(PersonMotionConfig(file=str(f), end="clamp"))
    assert np.allclose(c.sample(100.0), c.joints_ned_m[-1]) and "holds its last frame" in c.note(100.0)


def test_z_up_and_metres_give_the_same_person(tmp_path):
    a = load_bvh_motion(PersonMotionConfig(file=str(write_bvh(tmp_path / "y.bvh", 1.0, arms_down=False)),
                                           skip_first_frame="no"))
    b = load_bvh_motion(PersonMotionConfig(file=str(write_bvh(tmp_path / "z.bvh", 0.01, z_up=True)),
                                           skip_first_frame="no"))
    assert (a.units, a.up_axis, b.units, b.up_axis) == ("metres", "y", "centimetres", "z")
    assert np.allclose(a.joints_ned_m, b.joints_ned_m, atol=1e-4)  # the files hold 5 decimals


def test_clear_errors(tmp_path):
    with pytest.raises(PersonError, match="does not exist"):
        load_bvh_motion(PersonMotionConfig(file=str(tmp_path / "none.bvh")))
    (tmp_path / "junk.bvh").write_text("not a bvh\n")
    with pytest.raises(PersonError, match="cannot be read as BVH"):
        load_bvh_motion(PersonMotionConfig(file=str(tmp_path / "junk.bvh")))
    # no elbows: refused, naming what each known rig lacks
    with pytest.raises(PersonError, match=r"cmu: lacks LeftForeArm.*retarget"):
        load_bvh_motion(PersonMotionConfig(file=str(write_bvh(tmp_path / "noelbow.bvh", drop="LeftForeArm"))))
    # a unit none of the known ones explains (1 unit = 0.2 mm: a 7 m tall person in millimetres, 0.3 m in metres...)
    odd = write_bvh(tmp_path / "odd.bvh", 0.0002)
    with pytest.raises(PersonError, match=r"cannot tell its unit.*7350 file units.*motion\.units_to_m"):
        load_bvh_motion(PersonMotionConfig(file=str(odd)))
    m = load_bvh_motion(PersonMotionConfig(file=str(odd), units_to_m=0.0002))
    assert not m.units_detected and m.head_above_ankles_m == pytest.approx(1.47, abs=1e-3)
    # the configuration's sha256 must match
    with pytest.raises(PersonError, match="changed since"):
        load_bvh_motion(PersonMotionConfig(file=str(odd), units_to_m=0.0002, sha256="0" * 64))


def test_truth_carries_the_motion(tmp_path):
    f = write_bvh(tmp_path / "walk.bvh")
    truth = PersonTruth(True, PersonMotionConfig(file=str(f), center_ne_m=[3.0, 0.0]))
    fields = truth.fields(0.5)
    J = np.asarray(fields["person_joints_ned_m"]).reshape(17, 3)
    assert fields["person_motion"] == "bvh:walk" and abs(J[11, 0] - 3.0) < 0.2
    with pytest.raises(PersonError):  # a bad file is an error, not a silent default walk
        PersonTruth(True, PersonMotionConfig(file=str(tmp_path / "none.bvh")))


def test_shared_cmu_motion(cmu_dir):
    """A real CMU file of the shared data (CC_Base rig, centimetres, prepended T-pose)."""
    from skycap.bvh import read_bvh
    from skycap.skeleton import mocap_to_coco17

    f = cmu_dir / "005" / "005_10.bvh"
    m = load_bvh_motion(PersonMotionConfig(file=str(f), center_ne_m=[1.0, 2.0]))
    assert m.rig == "cc_base" and m.units == "centimetres" and m.up_axis == "y" and m.skipped_first_frame
    assert 1.55 < m.height_m < 1.95 and m.fps == pytest.approx(60.0, rel=1e-3)
    ref = mocap_to_coco17(read_bvh(f))[1:]
    d = (m.joints_ned_m - ref).reshape(-1, 3)
    assert np.ptp(d, axis=0).max() < 1e-9  # the same joints as the project's mapping, only moved
    assert np.allclose(d[0], [*(d[0, :2]), 0.0])  # on the recorded floor


def test_sim_and_demo_refuse_a_bad_motion_before_starting(tmp_path):
    from apps.cli import main
    from apps.demo import DemoConfig, run_demo

    bad = write_bvh(tmp_path / "noelbow.bvh", drop="RightForeArm")
    assert main(["sim", "--drones", "1", "--duration", "1", "--motion", str(bad)]) == 2
    out = tmp_path / "flight"
    with pytest.raises(PersonError, match="lacks RightForeArm"):
        run_demo(DemoConfig(out=str(out), motion=PersonMotionConfig(file=str(bad))).validate())
    assert not out.exists()  # nothing started, no folder made
