"""The simulated person: real recorded human motion (CMU mocap clips) moved along a path of waypoints.

    person = PersonSim(PersonConfig())
    s = person.state_at(12.3)       # PersonState: s.joints_ned_m (17, 3) COCO-17, s.root_ned_m, s.heading_rad

How it moves (a deterministic function of the simulation time ``t_s``):

* A **timeline** of segments is built from the config: at each waypoint the stops listed for it (a clip
  played in place: "stand", "jump", "punch", ...), then a walk to the next waypoint; with ``loop`` the
  timeline repeats after walking back to the first waypoint.
* **Walking** plays the walk clip's in-place cycle (its straight-line root translation removed, see
  ``simulator/data/make_clips.py``) while the root moves along the straight path at the clip's own
  speed, so the feet do not slide; the heading is the path direction. The gait phase is the walked
  distance divided by the clip speed, continuous across corners and loops.
* **Stops** play a clip once (or a standing clip back and forth) in the person's local frame at the
  waypoint, keeping the clip's own small root displacement (a jump moves forward a little).
* **Transitions** cross-fade the local poses over ``blend_s`` (walk <-> stop) and turn the heading
  over ``turn_s`` (smoothstep), anchored positions are blended too, so nothing pops.

Local frame of a pose: NED axes rotated by the heading (x forward, y right, z down), origin on the
ground under the anchor; world = Rz(heading) @ local + (anchor_n, anchor_e, 0).

**A recorded motion instead** (``skycap sim --motion FILE.bvh``, ``skycap demo --motion FILE.bvh``;
:class:`PersonMotionConfig`, :func:`load_bvh_motion`, :class:`BvhPerson`): any CMU-style BVH (a rig of
:data:`skycap.skeleton.BVH_RIGS`) played as recorded, root trajectory included, from the simulation's start:

* **Joints**: the rig's joints mapped to COCO-17 (:func:`skycap.skeleton.bvh_rig_to_coco17`); a file without the
  12 limb joints, the head and the neck of a known rig is refused, naming what it lacks.
* **Axes and units**: the up axis is the one along which the head stands above the ankles (Y-up, the BVH norm, or
  Z-up); the unit is detected from the person's size: of metres, centimetres, millimetres, inches, CMU's ASF units
  (inches / 0.45) and feet, the one that puts the head joint 1.1-1.9 m above the ankles (90th percentile over the
  clip; closest to 1.5 m if several do); ``units_to_m`` overrides it. What was assumed (unit, height) is logged
  and in :meth:`BvhMotion.info`.
* **Placement**: the middle of the root's horizontal track at ``center_ne_m``; on the ground: the recorded floor
  when the feet stand on it (lowest ankle, 5th percentile over the clip, 3-25 cm above it), else the feet moved
  onto the ground (that ankle height 10 cm). The first frame is left out when it is the CC_Base conversions'
  prepended T-pose (or any T-pose).
* **Past the end**: ``end="loop"`` plays it again, each seam cross-faded over ``loop_blend_s`` (the person
  slides back to the start pose), or ``end="clamp"`` holds the last frame.
"""

from __future__ import annotations

import bisect
import dataclasses
import functools
import hashlib
import logging
import math
from dataclasses import field
from pathlib import Path

import numpy as np

from simulator.scene.config import PersonConfig
from skycap.config import ConfigError
from skycap.errors import SkycapError

log = logging.getLogger(__name__)

BUILTIN_MOTIONS_DIR = Path(__file__).resolve().parents[1] / "data" / "motions"

__all__ = ["MotionClip", "PersonState", "PersonSim", "load_clip", "PersonError", "BUILTIN_MOTIONS_DIR",
           "PersonMotionConfig", "BvhMotion", "BvhPerson", "load_bvh_motion", "make_person"]


class PersonError(SkycapError):
    """A person configuration or motion clip that cannot be used."""


@dataclasses.dataclass(frozen=True)
class MotionClip:
    """One motion in the person's canonical local frame (facing north, root at the origin at frame 0).

    joints_ned_m: (T, 17, 3) COCO-17 joints; mode: "loop" | "once" | "pingpong".
    """

    name: str
    joints_ned_m: np.ndarray
    fps: float
    mode: str
    speed_m_s: float
    source: str

    @property
    def num_frames(self) -> int:
        return int(self.joints_ned_m.shape[0])

    @property
    def duration_s(self) -> float:
        """Loop: the period; once: time of the last frame; pingpong: one forward-and-back period."""
        n = self.num_frames
        if self.mode == "loop":
            return n / self.fps
        if self.mode == "pingpong":
            return 2 * (n - 1) / self.fps
        return (n - 1) / self.fps

    def frame_position(self, t_s: float) -> float:
        """Fractional frame index played at clip time ``t_s``."""
        n = self.num_frames
        f = t_s * self.fps
        if self.mode == "loop":
            return f % n
        if self.mode == "pingpong":
            period = 2 * (n - 1)
            f = f % period if period > 0 else 0.0
            return period - f if f > n - 1 else f
        return min(max(f, 0.0), n - 1)

    def sample(self, t_s: float) -> np.ndarray:
        """Joints (17, 3) at clip time ``t_s`` (linear interpolation between frames; loops wrap)."""
        f = self.frame_position(t_s)
        n = self.num_frames
        i0 = int(math.floor(f))
        w = f - i0
        i0 %= n
        i1 = (i0 + 1) % n if self.mode == "loop" else min(i0 + 1, n - 1)
        return (1.0 - w) * self.joints_ned_m[i0] + w * self.joints_ned_m[i1]


@functools.lru_cache(maxsize=64)
def _load_npz(path: str) -> MotionClip:
    p = Path(path)
    try:
        d = np.load(p, allow_pickle=False)
        joints = np.asarray(d["joints_ned_m"], dtype=float)
        clip = MotionClip(
            name=p.stem,
            joints_ned_m=joints,
            fps=float(d["fps"]),
            mode=str(d["mode"]),
            speed_m_s=float(d["speed_m_s"]),
            source=str(d["source"]),
        )
    except (OSError, KeyError, ValueError) as e:
        raise PersonError(f"motion clip {p} is not a valid clip file ({e}); regenerate it with simulator/data/make_clips.py") from e
    if joints.ndim != 3 or joints.shape[1:] != (17, 3) or len(joints) < 2:
        raise PersonError(f"motion clip {p} has joints of shape {joints.shape}, expected (T>=2, 17, 3)")
    if clip.mode not in ("loop", "once", "pingpong"):
        raise PersonError(f"motion clip {p} has mode {clip.mode!r}; expected loop, once or pingpong")
    return clip


def available_clips(motions_dir: str | Path = "") -> list[str]:
    names = {p.stem for p in BUILTIN_MOTIONS_DIR.glob("*.npz")}
    if motions_dir:
        names |= {p.stem for p in Path(motions_dir).glob("*.npz")}
    return sorted(names)


def load_clip(name: str, motions_dir: str | Path = "") -> MotionClip:
    """A clip by name from ``motions_dir`` (if given) or the built-in ``simulator/data/motions``."""
    for d in ([Path(motions_dir)] if motions_dir else []) + [BUILTIN_MOTIONS_DIR]:
        p = d / f"{name}.npz"
        if p.is_file():
            return _load_npz(str(p))
    raise PersonError(f"no motion clip named {name!r}; available: {', '.join(available_clips(motions_dir))}")


@dataclasses.dataclass
class PersonState:
    """The person at one time. joints_ned_m: (17, 3) COCO-17 world NED; root_ned_m: (3,) hip midpoint."""

    t_s: float
    joints_ned_m: np.ndarray
    root_ned_m: np.ndarray
    heading_rad: float
    motion: str  #: name of the clip playing (the dominant one during a cross-fade)
    walking: bool

    def body(self):
        """The rendered body's ellipsoids (:func:`simulator.scene.body.body_ellipsoids`) in the world frame."""
        from simulator.scene.body import body_ellipsoids

        return body_ellipsoids(self.joints_ned_m)

    def truth_fields(self) -> dict:
        """Keyword arguments for the person part of :class:`shared_msgs.SimTruth`."""
        return dict(
            person_joints_ned_m=tuple(float(v) for v in self.joints_ned_m.reshape(-1)),
            person_root_ned_m=tuple(float(v) for v in self.root_ned_m),
            person_heading_rad=float(self.heading_rad),
            person_motion=self.motion,
        )


@dataclasses.dataclass
class _Segment:
    kind: str  # "walk" | "stop"
    t0: float
    t1: float
    heading: float
    p0: np.ndarray  # (2,) start (walk) or anchor (stop), north/east metres
    p1: np.ndarray  # (2,) end (walk) or anchor (stop)
    dist0: float = 0.0  # walked distance at t0 within one period
    clip: MotionClip | None = None


def _rot_z(yaw_rad: float) -> np.ndarray:
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _smoothstep(x: float) -> float:
    x = min(max(x, 0.0), 1.0)
    return x * x * (3.0 - 2.0 * x)


#: Limb chains (parent, child) from the hips and shoulders outwards.
_LIMB_CHAIN = ((11, 13), (13, 15), (12, 14), (14, 16), (5, 7), (7, 9), (6, 8), (8, 10))


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v)
    return v / n if n > 1e-9 else np.array([0.0, 0.0, 1.0])


def _slerp_dir(u0: np.ndarray, u1: np.ndarray, w: float) -> np.ndarray:
    """Unit vector rotated from u0 towards u1 by the fraction w of the angle between them."""
    c = float(np.clip(np.dot(u0, u1), -1.0, 1.0))
    theta = math.acos(c)
    k = np.cross(u0, u1)
    nk = np.linalg.norm(k)
    if nk < 1e-9:
        if c > 0:
            return u0
        k = np.cross(u0, [0.0, 0.0, 1.0] if abs(u0[2]) < 0.9 else [1.0, 0.0, 0.0])
        nk = np.linalg.norm(k)
    k = k / nk
    a = w * theta
    return u0 * math.cos(a) + np.cross(k, u0) * math.sin(a)


def _blend_poses(p0: np.ndarray, p1: np.ndarray, w: float) -> np.ndarray:
    """Cross-fade of two poses (17, 3): trunk and face joints lerped, limbs rotated (slerp of each bone's
    direction) with the bone lengths of ``p1``, so limbs neither shrink nor pass through the body."""
    out = (1.0 - w) * p0 + w * p1
    for a, b in _LIMB_CHAIN:
        u = _slerp_dir(_unit(p0[b] - p0[a]), _unit(p1[b] - p1[a]), w)
        out[b] = out[a] + u * np.linalg.norm(p1[b] - p1[a])
    return out


def _lerp_angle(a: float, b: float, w: float) -> float:
    d = (b - a + math.pi) % (2 * math.pi) - math.pi
    return a + w * d


class PersonSim:
    """The person's motion as a function of time (see the module doc). Deterministic; no state."""

    STAND_DEFAULT_S = 2.0

    def __init__(self, cfg: PersonConfig | None = None):
        self.cfg = (cfg or PersonConfig()).validate()
        self.walk = load_clip(self.cfg.walk_motion, self.cfg.motions_dir)
        if self.walk.mode != "loop" or self.walk.speed_m_s <= 0:
            raise PersonError(f"walk_motion {self.cfg.walk_motion!r} must be a 'loop' clip with a speed > 0")
        #: walking speed along the path: the clip's own speed times walk_speed_scale (the cadence scales too)
        self.walk_speed_m_s = self.walk.speed_m_s * self.cfg.walk_speed_scale
        self.segments: list[_Segment] = []
        self.period_s = 0.0
        self.period_dist_m = 0.0
        self._build()
        self._t0s = [s.t0 for s in self.segments]

    # ------------------------------------------------------------------ timeline
    def _stops_at(self, i: int) -> list:
        return [s for s in self.cfg.stops if s.waypoint == i]

    def _build(self) -> None:
        wps = [np.asarray(p, dtype=float) for p in self.cfg.waypoints_ne_m]
        n = len(wps)
        legs = list(range(n if self.cfg.loop else n - 1))
        headings = []
        for k in legs:
            d = wps[(k + 1) % n] - wps[k]
            headings.append(math.atan2(d[1], d[0]) if np.linalg.norm(d) > 1e-6 else None)
        valid = [h for h in headings if h is not None]
        h_cur = (valid[-1] if self.cfg.loop else valid[0]) if valid else 0.0
        t, dist = 0.0, 0.0
        for i in range(n):
            for stop in self._stops_at(i):
                clip = load_clip(stop.motion, self.cfg.motions_dir)
                dur = stop.duration_s or (self.STAND_DEFAULT_S if clip.mode != "once" else clip.duration_s)
                self.segments.append(_Segment("stop", t, t + dur, h_cur, wps[i], wps[i], clip=clip))
                t += dur
            if i < len(legs):
                p0, p1 = wps[i], wps[(i + 1) % n]
                L = float(np.linalg.norm(p1 - p0))
                if L < 1e-6:
                    continue
                h_cur = headings[i]
                dur = L / self.walk_speed_m_s
                self.segments.append(_Segment("walk", t, t + dur, h_cur, p0, p1, dist0=dist))
                t += dur
                dist += L
        if not self.segments:  # one waypoint, no stops: stand there
            self.segments.append(_Segment("stop", 0.0, self.STAND_DEFAULT_S, h_cur, wps[0], wps[0], clip=load_clip("stand")))
            t = self.STAND_DEFAULT_S
        self.period_s = t
        self.period_dist_m = dist
        if not self.cfg.loop:  # stand at the end forever
            last = self.segments[-1]
            self.segments.append(
                _Segment("stop", t, math.inf, last.heading, last.p1, last.p1, clip=load_clip("stand", self.cfg.motions_dir))
            )
        log.debug("person timeline: %d segments, period %.2f s, %.2f m walked", len(self.segments), t, dist)

    # ------------------------------------------------------------------ evaluation
    def _eval(self, seg: _Segment, t: float, k: int) -> tuple[np.ndarray, np.ndarray, float]:
        """(local joints (17,3), anchor_ne (2,), heading) of ``seg`` at period-local time ``t`` (may lie
        outside the segment: walks then hold their end point while stepping in place, clips hold their ends)."""
        if seg.kind == "walk":
            dur = seg.t1 - seg.t0
            s = min(max(t - seg.t0, 0.0), dur) / dur if dur > 0 else 1.0
            anchor = seg.p0 + s * (seg.p1 - seg.p0)
            # gait phase from the distance walked (stride length kept), stepping on in place past the end
            phase_t = (seg.dist0 + k * self.period_dist_m) / self.walk.speed_m_s + (t - seg.t0) * self.cfg.walk_speed_scale
            return self.walk.sample(phase_t), anchor, seg.heading
        clip = seg.clip
        assert clip is not None
        ct = min(max(t - seg.t0, 0.0), seg.t1 - seg.t0)
        return clip.sample(ct), seg.p0, seg.heading

    def _locate(self, t_s: float) -> tuple[int, float, int]:
        """(segment index, period-local time, period number) of absolute time t_s."""
        if self.cfg.loop and self.period_s > 0:
            k = math.floor(t_s / self.period_s)
            tau = t_s - k * self.period_s
        else:
            k, tau = 0, max(t_s, 0.0)
        i = max(bisect.bisect_right(self._t0s, tau) - 1, 0)
        return i, tau, k

    def state_at(self, t_s: float) -> PersonState:
        """The person at simulation time ``t_s`` (seconds since the simulation started)."""
        i, tau, k = self._locate(float(t_s))
        seg = self.segments[i]
        local, anchor, heading = self._eval(seg, tau, k)
        motion = seg.clip.name if seg.kind == "stop" else self.walk.name
        T = self.cfg.turn_s
        # previous segment (wrapping round when looping) for the transitions
        if i > 0 or self.cfg.loop:
            j = i - 1 if i > 0 else len(self.segments) - 1
            prev = self.segments[j]
            tau_p, k_p = (tau, k) if i > 0 else (tau + self.period_s, k - 1)
            dt = tau - seg.t0
            lp, ap, hp = self._eval(prev, tau_p, k_p)
            # walk -> walk: the turn is centred on the corner (it began before it, see below)
            w0 = 0.5 if (prev.kind == "walk" and seg.kind == "walk") else 0.0
            wh = _smoothstep(w0 + dt / T) if T > 0 else 1.0
            heading = _lerp_angle(hp, heading, wh)
            if prev.kind == "stop" or seg.kind == "stop":
                wb = _smoothstep(dt / self.cfg.blend_s) if self.cfg.blend_s > 0 else 1.0
                if wb < 1.0:
                    local = _blend_poses(lp, local, wb)
                anchor = (1.0 - wb) * ap + wb * anchor
                if wb < 0.5:
                    motion = prev.clip.name if prev.kind == "stop" else self.walk.name
        # walk -> walk ahead: start turning half a turn time before the corner
        if seg.kind == "walk" and T > 0 and (i + 1 < len(self.segments) or self.cfg.loop):
            nxt = self.segments[(i + 1) % len(self.segments)]
            remaining = seg.t1 - tau
            if nxt.kind == "walk" and remaining < 0.5 * T:
                heading = _lerp_angle(heading, nxt.heading, _smoothstep(0.5 - remaining / T))
        joints = local @ _rot_z(heading).T
        joints[:, 0] += anchor[0]
        joints[:, 1] += anchor[1]
        root = 0.5 * (joints[11] + joints[12])
        return PersonState(float(t_s), joints, root, float(heading), motion, seg.kind == "walk")



# ------------------------------------------------------------------------------------------------------------
# a recorded motion from a BVH file (--motion FILE.bvh)

#: Units a BVH may be written in: (name, metres per unit). CMU's ASF/AMC unit is 1/0.45 inch.
BVH_UNITS: tuple[tuple[str, float], ...] = (
    ("metres", 1.0), ("centimetres", 0.01), ("millimetres", 0.001), ("inches", 0.0254),
    ("CMU ASF units (inches / 0.45)", 0.0254 / 0.45), ("feet", 0.3048),
)  # fmt: skip
#: Plausible height (m) of the head joint above the ankles of a standing adult (90th percentile over a clip).
HEAD_ABOVE_ANKLES_M = (1.1, 1.9)


@dataclasses.dataclass
class PersonMotionConfig:
    """The simulated person performs a recorded motion instead of the default waypoint walk (see the module doc)."""

    #: a BVH file of a CMU-style rig (skycap.skeleton.BVH_RIGS); "" = the default walk with stops
    file: str = ""
    #: the file's expected sha256 (hex); "" = not checked. ``skycap demo`` fills it in, so that its saved
    #: config.toml names exactly the motion flown and refuses a changed file
    sha256: str = ""
    #: past the clip's end: "loop" (again from the start, the seam cross-faded) or "clamp" (hold the last frame)
    end: str = "loop"
    #: cross-fade of a loop's seam, seconds
    loop_blend_s: float = 1.0
    #: metres per file unit; 0 = detected from the person's size (and logged)
    units_to_m: float = 0.0
    #: the middle of the root's horizontal track is placed here (world NED [north_m, east_m])
    center_ne_m: list[float] = field(default_factory=lambda: [0.0, 0.0])
    #: leave the first frame out: "auto" (when it is a T-pose, or the CC_Base conversions' prepended one), "yes", "no"
    skip_first_frame: str = "auto"

    def validate(self) -> "PersonMotionConfig":
        if self.end not in ("loop", "clamp"):
            raise ConfigError(f"motion.end={self.end!r}; use 'loop' or 'clamp'")
        if self.loop_blend_s < 0 or self.units_to_m < 0:
            raise ConfigError("motion.loop_blend_s and motion.units_to_m must be >= 0 (units_to_m 0 = detect)")
        if len(self.center_ne_m) != 2:
            raise ConfigError(f"motion.center_ne_m={self.center_ne_m}: give [north_m, east_m]")
        if self.skip_first_frame not in ("auto", "yes", "no"):
            raise ConfigError(f"motion.skip_first_frame={self.skip_first_frame!r}; use 'auto', 'yes' or 'no'")
        return self


@dataclasses.dataclass(frozen=True)
class BvhMotion:
    """A BVH motion as the person plays it: ``joints_ned_m`` (T, 17, 3) COCO-17, world NED, placed (see
    :func:`load_bvh_motion`), at ``fps``; what was read and assumed in the other fields."""

    path: Path
    sha256: str
    rig: str
    joints_ned_m: np.ndarray
    fps: float
    end: str
    loop_blend_s: float
    units: str
    units_to_m: float
    units_detected: bool
    up_axis: str
    height_m: float
    head_above_ankles_m: float
    ground: str
    skipped_first_frame: bool
    center_ne_m: tuple[float, float]

    @property
    def num_frames(self) -> int:
        return int(self.joints_ned_m.shape[0])

    @property
    def duration_s(self) -> float:
        return (self.num_frames - 1) / self.fps

    @property
    def blend_s(self) -> float:
        """The loop seam's cross-fade actually used (at most a third of the clip)."""
        return min(self.loop_blend_s, self.duration_s / 3.0)

    @property
    def period_s(self) -> float:
        """Loop: seconds between two starts (the clip less its cross-faded seam); clamp: the clip's length."""
        return self.duration_s - self.blend_s if self.end == "loop" else self.duration_s

    def _at(self, u_s: float) -> np.ndarray:
        f = min(max(u_s * self.fps, 0.0), self.num_frames - 1.0)
        i0 = min(int(math.floor(f)), self.num_frames - 2)
        w = f - i0
        return (1.0 - w) * self.joints_ned_m[i0] + w * self.joints_ned_m[i0 + 1]

    def sample(self, t_s: float) -> np.ndarray:
        """Joints (17, 3) world NED at ``t_s`` seconds after the start (looped or clamped past the end)."""
        t_s = max(float(t_s), 0.0)
        if self.end == "clamp" or self.period_s <= 0:
            return self._at(t_s)
        k = math.floor(t_s / self.period_s)
        u = t_s - k * self.period_s
        pose = self._at(u)
        b = self.blend_s
        if k >= 1 and b > 0 and u < b:  # the seam: the clip's last b seconds fade into its first ones
            pose = _blend_poses(self._at(self.period_s + u), pose, _smoothstep(u / b))
        return pose

    def note(self, played_s: float | None = None) -> str:
        """What the person does over ``played_s`` seconds of simulation (the flight)."""
        d = f"the motion lasts {self.duration_s:.1f} s"
        if self.end == "loop":
            s = f"{d} and loops (each seam cross-faded over {self.blend_s:.2f} s: the person slides back to the start)"
            if played_s:
                s += f"; {played_s:.0f} s of simulation played it {played_s / self.period_s:.1f} times"
            return s
        s = f"{d}, then holds its last frame"
        if played_s and played_s > self.duration_s:
            s += f" (still for the last {played_s - self.duration_s:.0f} s of {played_s:.0f} s of simulation)"
        return s

    def info(self, played_s: float | None = None) -> dict:
        """The motion for ``config.toml`` / ``summary.json``: file, sha256 and everything assumed."""
        return {
            "file": str(self.path), "sha256": self.sha256, "rig": self.rig, "frames": self.num_frames,
            "fps": round(self.fps, 3), "duration_s": round(self.duration_s, 3),
            "skipped_first_frame": self.skipped_first_frame, "up_axis": self.up_axis, "units": self.units,
            "units_to_m": self.units_to_m, "units_detected": self.units_detected,
            "height_m": round(self.height_m, 2), "head_above_ankles_m": round(self.head_above_ankles_m, 3),
            "ground": self.ground, "center_ne_m": list(self.center_ne_m), "end": self.end, "note": self.note(played_s),
        }  # fmt: skip


def _file_sha256(path: Path) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


#: file axes -> NED for the up axes a BVH may use (both right-handed, proper rotations)
_UP_TO_NED = {
    "y": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]),  # (x, y, z) -> (x, z, -y)
    "z": np.diag([1.0, -1.0, -1.0]),  # (x, y, z) -> (x, -y, -z)
}


def _is_t_pose(j: np.ndarray) -> bool:
    """Arms out sideways at shoulder height (j (17, 3) NED metres)."""
    level = all(abs(j[w, 2] - j[s, 2]) < 0.12 for w, s in ((9, 5), (10, 6)))
    return level and np.linalg.norm(j[9] - j[10]) > 1.25 * np.linalg.norm(j[5] - j[6]) + 0.6


def load_bvh_motion(cfg: PersonMotionConfig) -> BvhMotion:
    """Read ``cfg.file`` and make it the person's motion (see the module doc). Raises :class:`PersonError` naming
    the problem and the fix (no file, not a BVH, no known rig, unit or axes not recognised)."""
    from skycap.bvh import BvhError, read_bvh
    from skycap.skeleton import BVH_RIGS, bvh_rig_to_coco17, detect_bvh_rig

    cfg = cfg.validate()
    path = Path(cfg.file).expanduser().resolve()
    if not path.is_file():
        raise PersonError(f"motion file {cfg.file} does not exist; give a BVH file (e.g. one of "
                          "../shared/data/mocap/cmu/*/*.bvh) to --motion")
    sha = _file_sha256(path)
    if cfg.sha256 and cfg.sha256.lower() != sha:
        raise PersonError(f"motion file {path} has sha256 {sha}, not the {cfg.sha256} the configuration names: it "
                          "changed since; use the original file or clear motion.sha256")
    try:
        motion = read_bvh(path)
    except BvhError as e:
        raise PersonError(f"motion file {path} cannot be read as BVH: {e}") from None
    names = motion.skeleton.names
    rig, missing = detect_bvh_rig(names)
    if rig is None:
        lack = "; ".join(f"{r}: lacks {', '.join(m[:6])}{' ...' if len(m) > 6 else ''}" for r, m in missing.items())
        raise PersonError(f"motion file {path} has none of the rigs the person can play ({lack}); it needs the "
                          "shoulders, elbows, wrists, hips, knees, ankles, head and neck of a CMU-style skeleton "
                          "(skycap.skeleton.BVH_RIGS names them); retarget it onto one")
    if motion.num_frames < 2:
        raise PersonError(f"motion file {path} holds {motion.num_frames} frame(s); the person needs at least 2")
    world = motion.world_positions()  # (T, J, 3) file units and axes
    # up axis: along which the head stands above the ankles
    spec = BVH_RIGS[rig]
    idx = {n.rsplit(":", 1)[-1]: i for i, n in enumerate(names)}
    head_u = world[:, idx[spec["head"]]]
    ankles_u = 0.5 * (world[:, idx[spec["limbs"][15]]] + world[:, idx[spec["limbs"][16]]])
    v = np.mean(head_u - ankles_u, axis=0)
    ax = int(np.argmax(np.abs(v)))
    if ax == 0 or v[ax] <= 0:
        raise PersonError(f"motion file {path}: the head stands above the ankles along {'-' if v[ax] < 0 else '+'}"
                          f"{'xyz'[ax]}, not +y (the BVH norm) or +z; re-export it Y-up or Z-up")
    up = "xyz"[ax]
    h_u = float(np.percentile((head_u - ankles_u)[:, ax], 90))
    if cfg.units_to_m > 0:
        units, scale, detected = f"{cfg.units_to_m:g} m per unit (given)", cfg.units_to_m, False
        if not HEAD_ABOVE_ANKLES_M[0] <= h_u * scale <= HEAD_ABOVE_ANKLES_M[1]:
            log.warning("motion %s: with units_to_m=%g the head is %.2f m above the ankles (a standing adult: "
                        "%.1f-%.1f m); check motion.units_to_m", path.name, scale, h_u * scale, *HEAD_ABOVE_ANKLES_M)
    else:
        fits = [(abs(math.log(h_u * s / 1.5)), n, s) for n, s in BVH_UNITS
                if HEAD_ABOVE_ANKLES_M[0] <= h_u * s <= HEAD_ABOVE_ANKLES_M[1]]
        if not fits:
            raise PersonError(
                f"motion file {path}: cannot tell its unit: the head joint is {h_u:.4g} file units above the "
                f"ankles, which in none of {', '.join(n for n, _ in BVH_UNITS)} makes a person whose head is "
                f"{HEAD_ABOVE_ANKLES_M[0]}-{HEAD_ABOVE_ANKLES_M[1]} m above the ankles; give the metres per file "
                "unit with --set motion.units_to_m=...")
        _, units, scale = min(fits)
        detected = True
    j = bvh_rig_to_coco17(world, names, rig, cm_units=0.01 / scale) * scale @ _UP_TO_NED[up].T
    skip = cfg.skip_first_frame == "yes" or (cfg.skip_first_frame == "auto" and (rig == "cc_base" or _is_t_pose(j[0])))
    if skip:
        j = j[1:]
    if len(j) < 2:
        raise PersonError(f"motion file {path} holds one frame after its T-pose; the person needs at least 2")
    # on the ground
    low = np.percentile(np.min(-j[:, 15:17, 2], axis=1), 5)
    if 0.03 <= low <= 0.25:
        ground = f"as recorded (the file's floor; lowest ankle {low:.2f} m above it)"
    else:
        j[..., 2] += low - 0.10
        ground = f"feet moved onto the ground (lowest ankle was {low:.2f} m above the file's zero, now 0.10 m)"
    # in the middle of the plan
    root = 0.5 * (j[:, 11, :2] + j[:, 12, :2])
    mid = 0.5 * (root.min(axis=0) + root.max(axis=0))
    j[..., :2] += np.asarray(cfg.center_ne_m, dtype=float) - mid
    nose_above = float(np.percentile(-j[:, 0, 2] + np.mean(j[:, 15:17, 2], axis=1), 90))
    height = nose_above + 0.2  # + nose to crown (~12 cm) + ankle to sole (~8 cm)
    m = BvhMotion(path=path, sha256=sha, rig=rig, joints_ned_m=j, fps=float(motion.fps),
                  end=cfg.end, loop_blend_s=cfg.loop_blend_s, units=units, units_to_m=float(scale),
                  units_detected=detected, up_axis=up, height_m=height, head_above_ankles_m=h_u * scale, ground=ground,
                  skipped_first_frame=bool(skip), center_ne_m=(float(cfg.center_ne_m[0]), float(cfg.center_ne_m[1])))
    log.info("motion %s: rig %s, %d frames at %.1f fps (%.1f s), %s-up, unit %s (%s; person about %.2f m tall), "
             "ground %s, %s", path.name, rig, m.num_frames, m.fps, m.duration_s, up, units,
             "detected from the size" if detected else "given", height, ground, m.note())
    return m


class BvhPerson:
    """The person performing a :class:`BvhMotion` (the same ``state_at`` as :class:`PersonSim`)."""

    def __init__(self, motion: BvhMotion):
        self.motion = motion
        self.name = f"bvh:{motion.path.stem}"

    def state_at(self, t_s: float) -> PersonState:
        j = self.motion.sample(t_s)
        left = j[11] - j[12]
        fwd = np.cross(left, np.array([0.0, 0.0, -1.0]))  # left x up = forward (NED)
        root = 0.5 * (j[11] + j[12])
        return PersonState(float(t_s), j, root, float(math.atan2(fwd[1], fwd[0])), self.name, False)


def make_person(person_cfg: PersonConfig | None = None, motion: PersonMotionConfig | None = None):
    """The simulated person: :class:`BvhPerson` when ``motion.file`` is set, else :class:`PersonSim`."""
    if motion is not None and motion.file:
        return BvhPerson(load_bvh_motion(motion))
    return PersonSim(person_cfg)
