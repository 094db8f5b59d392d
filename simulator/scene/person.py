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
"""

from __future__ import annotations

import bisect
import dataclasses
import functools
import logging
import math
from pathlib import Path

import numpy as np

from simulator.scene.config import PersonConfig
from skycap.errors import SkycapError

log = logging.getLogger(__name__)

BUILTIN_MOTIONS_DIR = Path(__file__).resolve().parents[1] / "data" / "motions"

__all__ = ["MotionClip", "PersonState", "PersonSim", "load_clip", "PersonError", "BUILTIN_MOTIONS_DIR"]


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
