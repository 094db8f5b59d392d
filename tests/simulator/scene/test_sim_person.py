"""The simulated person: committed clips, path following at the clip's speed, plausible joints, stops."""

from __future__ import annotations

import math

import numpy as np
import pytest

from simulator.scene.config import PersonConfig, StopConfig
from simulator.scene.person import BUILTIN_MOTIONS_DIR, PersonError, PersonSim, load_clip
from skycap.config import ConfigError, load_config
from skycap.skeleton import limb_lengths


@pytest.fixture(scope="module")
def person() -> PersonSim:
    return PersonSim(PersonConfig())


def test_committed_clips_are_small_and_valid():
    files = sorted(BUILTIN_MOTIONS_DIR.glob("*.npz"))
    names = {f.stem for f in files}
    assert {"walk", "stand", "jump", "punch"} <= names
    assert sum(f.stat().st_size for f in files) < 2_000_000
    for n in names:
        clip = load_clip(n)
        assert clip.fps == 30.0
        assert clip.joints_ned_m.shape[1:] == (17, 3)
        assert np.isfinite(clip.joints_ned_m).all()
        assert "CMU" in clip.source
        # the prepended T-pose is not kept: no frame has the arms spread horizontally (span ~1.6 m)
        j = clip.joints_ned_m
        span = np.linalg.norm(j[:, 9] - j[:, 10], axis=-1)
        level = np.abs(j[:, 9, 2] - j[:, 5, 2]) + np.abs(j[:, 10, 2] - j[:, 6, 2])
        assert not np.any((span > 1.3) & (level < 0.15)), n


def test_walk_clip_loops_seamlessly_and_walks_in_place():
    walk = load_clip("walk")
    assert walk.mode == "loop" and 1.0 < walk.speed_m_s < 1.8
    j = walk.joints_ned_m
    seam = np.abs(j[0] - j[-1]).max()  # last frame -> first frame is one ordinary step
    steps = np.abs(np.diff(j, axis=0)).max(axis=(1, 2))
    assert seam <= 1.5 * np.percentile(steps, 95)
    root = 0.5 * (j[:, 11] + j[:, 12])
    assert np.abs(root[:, :2]).max() < 0.12  # forward translation removed: it stays in place
    assert 1.8 <= walk.duration_s <= 3.0


def _walk_segments(p: PersonSim):
    return [s for s in p.segments if s.kind == "walk"]


def test_root_follows_waypoints_at_walking_speed(person):
    walk_speed = person.walk.speed_m_s
    for seg in _walk_segments(person):
        ts = np.linspace(seg.t0 + 0.5, seg.t1 - 0.1, 20)  # after the start-up blend
        roots = np.array([person.state_at(t).root_ned_m[:2] for t in ts])
        d = seg.p1 - seg.p0
        L = np.linalg.norm(d)
        u = d / L
        rel = roots - seg.p0
        along = rel @ u
        across = rel @ np.array([-u[1], u[0]])
        assert np.abs(across).max() < 0.15  # on the straight line between the waypoints
        speed = np.polyfit(ts, along, 1)[0]
        assert speed == pytest.approx(walk_speed, rel=0.08)
        # heading along the path
        h = person.state_at(0.5 * (seg.t0 + seg.t1) + 0.2).heading_rad
        assert abs(math.remainder(h - math.atan2(d[1], d[0]), 2 * math.pi)) < 0.05


def test_walk_speed_scale_scales_path_speed_and_cadence():
    base = PersonSim(PersonConfig(stops=[], waypoints_ne_m=[[0, 0], [20, 0]], loop=False))
    fast = PersonSim(PersonConfig(stops=[], waypoints_ne_m=[[0, 0], [20, 0]], loop=False, walk_speed_scale=1.3))
    for p, scale in ((base, 1.0), (fast, 1.3)):
        ts = np.linspace(1.0, 5.0, 30)
        n = [p.state_at(t).root_ned_m[0] for t in ts]
        assert np.polyfit(ts, n, 1)[0] == pytest.approx(p.walk.speed_m_s * scale, rel=0.03)
    # same pose at the same walked distance (stride kept): at distance 5 m both are in the same gait phase
    a = base.state_at(5.0 / base.walk_speed_m_s).joints_ned_m
    b = fast.state_at(5.0 / fast.walk_speed_m_s).joints_ned_m
    assert np.abs(a - b).max() < 0.02


def test_starts_at_first_waypoint_and_visits_all(person):
    wps = np.array(person.cfg.waypoints_ne_m)
    r0 = person.state_at(0.0).root_ned_m[:2]
    assert np.linalg.norm(r0 - wps[0]) < 0.2
    ts = np.arange(0, person.period_s, 0.05)
    roots = np.array([person.state_at(t).root_ned_m[:2] for t in ts])
    for w in wps:
        assert np.min(np.linalg.norm(roots - w, axis=1)) < 0.2


def test_joints_are_plausible_throughout(person):
    ts = np.arange(0, person.period_s * 1.5, 1 / 30)
    J = np.array([person.state_at(t).joints_ned_m for t in ts])
    assert np.isfinite(J).all()
    walking = np.array([person.state_at(t).walking for t in ts])
    height = -J[:, :, 2]
    # while walking: head at ~1.6-1.8 m, ankles near the ground (heel strike <= 15 cm), never under it
    assert np.median(height[walking, 0]) == pytest.approx(1.7, abs=0.12)
    assert np.percentile(height[walking][:, 15:17].min(axis=1), 5) < 0.13
    assert height[:, 15:17].min() > 0.0
    # feet near the ground most of the time overall (a jump leaves it briefly)
    assert np.mean(height[:, 15:17].min(axis=1) < 0.2) > 0.8
    # bones keep their length (mocap is rigid; cross-fades shorten them only slightly)
    L = limb_lengths(J)
    ref = np.median(L, axis=0)
    assert np.max(np.abs(L - ref) / ref) < 0.2


def test_motion_is_continuous_including_loop_wraps(person):
    P = person.period_s
    ts = np.concatenate([np.arange(0, 2 * P + 1, 0.01)])
    J = np.array([person.state_at(t).joints_ned_m for t in ts])
    step = np.abs(np.diff(J, axis=0)).max(axis=(1, 2))
    assert step.max() < 0.1  # < 10 m/s of any joint at 100 Hz: no pops at transitions or loop wraps


def test_stops_play_their_motions(person):
    stops = [s for s in person.segments if s.kind == "stop"]
    assert [s.clip.name for s in stops] == [s.motion for s in person.cfg.stops]
    for s in stops:
        st = person.state_at(0.5 * (s.t0 + s.t1))
        assert st.motion == s.clip.name and not st.walking
        assert np.linalg.norm(st.root_ned_m[:2] - s.p0) < 0.6


def test_default_stays_near_origin(person):
    ts = np.arange(0, person.period_s, 0.1)
    roots = np.array([person.state_at(t).root_ned_m[:2] for t in ts])
    assert np.linalg.norm(roots, axis=1).max() < 3.0


def test_truth_fields_fill_simtruth(person):
    from shared_msgs import SimTruth, decode, encode

    st = person.state_at(3.3)
    msg = SimTruth(header=SimTruth.make_header("sim"), vehicles=[], **st.truth_fields())
    back = decode(encode(msg), SimTruth)
    assert np.allclose(np.array(back.person_joints_ned_m).reshape(17, 3), st.joints_ned_m)
    assert back.person_motion == st.motion


def test_turns_are_centred_on_corners_without_stops():
    cfg = PersonConfig(waypoints_ne_m=[[0, 0], [4, 0], [4, 4]], stops=[], loop=False, turn_s=0.6)
    p = PersonSim(cfg)
    corner = p.segments[0].t1
    h = [p.state_at(corner + dt).heading_rad for dt in (-0.5, -0.1, 0.0, 0.1, 0.5)]
    assert h[0] == pytest.approx(0.0, abs=1e-6) and h[-1] == pytest.approx(math.pi / 2, abs=1e-6)
    assert h[2] == pytest.approx(math.pi / 4, abs=1e-6)  # halfway round exactly at the corner
    assert h[0] < h[1] < h[2] < h[3] < h[4]


def test_no_loop_ends_standing_at_last_waypoint():
    p = PersonSim(PersonConfig(waypoints_ne_m=[[0, 0], [3, 0]], stops=[], loop=False))
    st = p.state_at(100.0)
    assert np.linalg.norm(st.root_ned_m[:2] - [3, 0]) < 0.2
    assert not st.walking and st.motion == "stand"


def test_config_errors_are_clear(tmp_path):
    with pytest.raises(ConfigError, match="waypoint=7"):
        PersonSim(PersonConfig(stops=[StopConfig(7, "jump")]))
    with pytest.raises(PersonError, match="no motion clip named 'moonwalk'"):
        PersonSim(PersonConfig(stops=[StopConfig(0, "moonwalk")]))
    f = tmp_path / "p.toml"
    f.write_text('waypoints_ne_m = [[0.0, 0.0], [2.0, 0.0]]\n[[stops]]\nwaypoint = 1\nmotion = "jump"\n')
    cfg = load_config(PersonConfig, f)
    assert cfg.stops[0].motion == "jump" and PersonSim(cfg).period_s > 0


@pytest.mark.shared_data
def test_make_clips_regenerates_the_committed_clips(cmu_dir, tmp_path):
    import importlib.util

    spec = importlib.util.spec_from_file_location("make_clips", BUILTIN_MOTIONS_DIR.parent / "make_clips.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod.main(["--cmu", str(cmu_dir), "--out", str(tmp_path)]) == 0
    for f in BUILTIN_MOTIONS_DIR.glob("*.npz"):
        a, b = np.load(f), np.load(tmp_path / f.name)
        assert np.allclose(a["joints_ned_m"], b["joints_ned_m"], atol=1e-5), f.name
        assert str(a["source"]) == str(b["source"])


def test_extra_motions_dir(tmp_path):
    import shutil

    shutil.copy(BUILTIN_MOTIONS_DIR / "jump.npz", tmp_path / "myjump.npz")
    (tmp_path / "broken.npz").write_bytes(b"not a zip")
    p = PersonSim(PersonConfig(stops=[StopConfig(0, "myjump")], motions_dir=str(tmp_path)))
    assert p.segments[0].clip.name == "myjump"
    with pytest.raises(PersonError, match="not a valid clip file"):
        PersonSim(PersonConfig(stops=[StopConfig(0, "broken")], motions_dir=str(tmp_path)))


def test_scene_config_round_trips_through_toml(tmp_path):
    from simulator.scene.config import SceneConfig
    from skycap.config import save_config

    cfg = load_config(SceneConfig, overrides=["camera.width_px=960", "person.loop=false", "sim_detector.seed=4"])
    path = save_config(cfg, tmp_path / "scene.toml")
    back = load_config(SceneConfig, path)
    assert back == cfg and back.camera.width_px == 960 and back.person.stops == cfg.person.stops
    with pytest.raises(ConfigError, match="unknown config key 'camera.widht_px'"):
        load_config(SceneConfig, overrides=["camera.widht_px=3"])
